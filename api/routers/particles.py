"""`/v1/jobs/{id}/particles`: a job's reconstructed particle positions and its scene box, as JSON,
for the browser's 3D what-if view (where a ball sits, where the wind blows), and the air saved
with the frame sampled on a coarse lattice (the view draws it as arrows).

Read from the run folder the worker checkpoints to storage, so it answers while a job still
runs (frames done so far). numpy only: the API process never imports torch.
"""

from __future__ import annotations

from typing import Annotated

import numpy as np
from fastapi import APIRouter, HTTPException, Query, status

from api.deps import OwnerDep, SessionDep, StorageDep
from api.errors import error_responses
from api.schemas import AirSample, ParticlesOut, RunScene
from fluidcore.runs import FrameState, RunError, SavedAir, state_file
from fluidcore.spec.scene import Scene
from service import jobs
from service.runs import stored_run
from service.storage import ObjectNotFound, Storage, run_prefix

router = APIRouter(prefix="/v1/jobs", tags=["particles"], responses=error_responses(401, 422, 503))

DEFAULT_POINTS = 20_000
MAX_POINTS = 100_000  # 1.2 MB of float32 positions as JSON text is already ~2.5 MB
AIR_LATTICE = 5  # air samples along the box's long side: at most 125 arrows (a cubic box), readable at a glance


@router.get(
    "/{job_id}/particles",
    response_model=ParticlesOut,
    responses=error_responses(404, 409),
)
def get_particles(
    job_id: str,
    owner: OwnerDep,
    session: SessionDep,
    storage: StorageDep,
    frame: Annotated[int | None, Query(ge=0, description="video frame index; default: the last one written")] = None,
    max_points: Annotated[int, Query(ge=1, le=MAX_POINTS, description="subsampling cap")] = DEFAULT_POINTS,
) -> ParticlesOut:
    """Live particle positions (world units) of one frame, evenly subsampled to at most
    `max_points`, with the run's scene box, up axis, smoke source and solids."""
    job = jobs.owned(session, job_id, owner)
    record = stored_run(storage, job.id)
    scene = record.scene
    frames = record.frames()
    if not frames:
        raise HTTPException(status.HTTP_409_CONFLICT, f"job {job.id} has not written a frame yet")
    t = frames[-1] if frame is None else frame
    if t not in frames:
        raise HTTPException(
            status.HTTP_404_NOT_FOUND, f"frame {t} is not in job {job.id}'s run (frames {frames[0]}..{frames[-1]})"
        )
    state = _frame(storage, job.id, t)
    positions = state.positions[state.alive.astype(bool)].astype(np.float32)
    keep = _even_subsample(len(positions), max_points)
    return ParticlesOut(
        job_id=job.id,
        frame=t,
        frames=frames,
        total=len(positions),
        positions=np.round(positions[keep], 5).astype(float).ravel().tolist(),
        scene=RunScene(box_lo=scene.box_lo, box_hi=scene.box_hi, up=scene.up, source=scene.to_json()["source"], dt=scene.physics.dt,
                       solids=scene.to_json()["solids"]),
        air=None if state.air is None else _air_sample(state.air, scene),
    )


def _air_sample(air: SavedAir, scene: Scene) -> AirSample:
    """The air at the centres of a lattice of AIR_LATTICE cubes along the box's long side."""
    lo, hi = np.asarray(scene.box_lo), np.asarray(scene.box_hi)
    step = float((hi - lo).max()) / AIR_LATTICE
    axes = [np.arange(a + step / 2, b, step) for a, b in zip(lo, hi)]
    axes = [axis if len(axis) else np.asarray([(a + b) / 2]) for axis, a, b in zip(axes, lo, hi)]  # thinner than a cube
    points = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    return AirSample(points=np.round(points, 5).ravel().tolist(),
                     velocities=np.round(air.velocity_at(points), 6).astype(float).ravel().tolist())


def _frame(storage: Storage, job_id: str, t: int) -> FrameState:
    """Frame t's saved state."""
    try:
        return FrameState.from_bytes(storage.read_bytes(f"{run_prefix(job_id)}/{state_file(t)}"), f"frame {t} of job {job_id}")
    except ObjectNotFound:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"frame {t} of job {job_id} is missing from storage") from None
    except RunError as exc:
        raise HTTPException(status.HTTP_409_CONFLICT, str(exc)) from None


def _even_subsample(count: int, cap: int) -> np.ndarray:
    """Indices of at most `cap` of `count` items, evenly spaced: the same request always shows the
    same particles (a random sample would flicker between refreshes)."""
    if count <= cap:
        return np.arange(count)
    return np.linspace(0, count - 1, cap).round().astype(np.int64)

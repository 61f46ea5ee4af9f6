"""`/v1/jobs/{id}/particles`: a job's reconstructed particle positions and its scene box, as JSON,
for the browser's 3D what-if view (where a ball sits, where the wind blows).

Read from the run folder the worker checkpoints to storage, so it answers while a job still
runs (frames done so far). numpy only: the API process never imports torch.
"""

from __future__ import annotations

import io
import json
from typing import Annotated, Any

import numpy as np
from fastapi import APIRouter, HTTPException, Query, status

from api.deps import OwnerDep, SessionDep, StorageDep
from api.errors import error_responses
from api.routers.jobs import owned_job
from api.schemas import ParticlesOut, RunScene
from service.storage import ObjectNotFound, Storage, run_prefix

router = APIRouter(prefix="/v1/jobs", tags=["particles"], responses=error_responses(401, 422, 503))

DEFAULT_POINTS = 20_000
MAX_POINTS = 100_000  # 1.2 MB of float32 positions as JSON text is already ~2.5 MB


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
    `max_points`, with the run's scene box, up axis and smoke source."""
    job = owned_job(session, job_id, owner)
    manifest = _manifest(storage, job.id)
    frames = [int(entry["t"]) for entry in manifest.get("frames", [])]
    if not frames:
        raise HTTPException(status.HTTP_409_CONFLICT, f"job {job.id} has not written a frame yet")
    t = frames[-1] if frame is None else frame
    if t not in frames:
        raise HTTPException(
            status.HTTP_404_NOT_FOUND, f"frame {t} is not in job {job.id}'s run (frames {frames[0]}..{frames[-1]})"
        )
    positions = _positions(storage, job.id, t)
    keep = _even_subsample(len(positions), max_points)
    scene = manifest.get("scene") or {}
    return ParticlesOut(
        job_id=job.id,
        frame=t,
        frames=frames,
        total=len(positions),
        positions=np.round(positions[keep], 5).astype(float).ravel().tolist(),
        scene=RunScene(
            box_lo=scene["box"]["lo"], box_hi=scene["box"]["hi"], up=scene.get("up", [0.0, 1.0, 0.0]),
            source=scene.get("source") or {},
            dt=(scene.get("physics") or {}).get("dt"),
        ),
    )


def _manifest(storage: Storage, job_id: str) -> dict[str, Any]:
    try:
        manifest = json.loads(storage.read_bytes(f"{run_prefix(job_id)}/manifest.json"))
    except ObjectNotFound:
        raise HTTPException(status.HTTP_409_CONFLICT, f"job {job_id} has no run in storage yet") from None
    if not isinstance((manifest.get("scene") or {}).get("box"), dict):
        raise HTTPException(status.HTTP_409_CONFLICT, f"job {job_id}'s run records no scene box")
    return manifest


def _positions(storage: Storage, job_id: str, t: int) -> np.ndarray:
    """(P, 3) float32 positions of the particles alive at frame t."""
    try:
        data = storage.read_bytes(f"{run_prefix(job_id)}/states/frame_{t:06d}.npz")
    except ObjectNotFound:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"frame {t} of job {job_id} is missing from storage") from None
    with np.load(io.BytesIO(data)) as state:
        positions = np.asarray(state["positions"], dtype=np.float32)
        alive = np.asarray(state["alive"], dtype=bool) if "alive" in state.files else np.ones(len(positions), bool)
    return positions[alive]


def _even_subsample(count: int, cap: int) -> np.ndarray:
    """Indices of at most `cap` of `count` items, evenly spaced: the same request always shows the
    same particles (a random sample would flicker between refreshes)."""
    if count <= cap:
        return np.arange(count)
    return np.linspace(0, count - 1, cap).round().astype(np.int64)

"""Where things are in a scene, in world units: the box the smoke lives in, the smoke source the
reconstruction estimated, the solid balls in its scene, the world's up axis and each camera's
centre and viewing direction.
What a client needs to place a ball (it must lie inside the box, usually above the source) or
aim a wind, served by `fluidnexus scene info` and `GET /v1/scenes/{id}`.

Two readers: a camera file (box declared there, else the cameras' shared view; no source yet)
and a run (fluidcore.runs: the box, up and source the reconstruction used). Both are
torch-free JSON/numpy, so the API answers without importing the simulator.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from fluidcore.cameras import Camera, CameraError, capture_box, load
from fluidcore.cameras.world_up import world_up
from fluidcore.spec.solids import SolidBall

if TYPE_CHECKING:
    from fluidcore.health import Audience
    from fluidcore.runs import RunRecord

WORLD_UP = (0.0, 1.0, 0.0)  # docs/architecture.md: up is +y unless a run says otherwise


def describe(
    cameras: Mapping[str, Camera], box: tuple[Any, Any] | None, *, up: Any = WORLD_UP,
    source: Mapping[str, Any] | None = None, solids: Sequence[SolidBall] = (),
) -> dict[str, Any]:
    """The JSON object both readers return (docs/cameras.md, "Scene box"); `solids` is empty
    before a reconstruction (the balls are the run's scene's, `fluidcore.spec.solids`)."""
    return {
        "box": None if box is None else {"min": [float(v) for v in box[0]], "max": [float(v) for v in box[1]]},
        "up": [float(v) for v in up],
        "source": None if source is None else {
            "center": [float(v) for v in source["center"]], "radius": float(source["radius"]),
            **({"depth": source["depth"]} if "depth" in source else {}),
        },
        "solids": [solid.model_dump(mode="json") for solid in solids],
        "cameras": {
            name: {"center": camera.center().tolist(), "forward": camera.forward().tolist()}
            for name, camera in cameras.items()
        },
    }


def from_cameras_file(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Geometry of an uploaded capture before any reconstruction: no source estimate yet, and no
    box when the file declares none and the cameras share no bounded view (a reconstruction
    would refuse such a capture with the same reason)."""
    cameras = load(path)
    try:
        box = capture_box(path, cameras)
    except CameraError:
        box = None
    return describe(cameras, box, up=world_up(path, cameras).vector)


def from_run(run: RunRecord, audience: Audience) -> dict[str, Any]:
    """Geometry a run was made with (its manifest, read by `fluidcore.runs`): box, up, source,
    solids, cameras; for a reconstruction whose source was estimated, how its depth was found and, from
    one view, the stretch of the input ray the centre could lie on (`source.depth`); for a
    reconstruction, its health report (`fluidcore.health`), its advice worded for `audience`."""
    from fluidcore.health import report
    from fluidcore.runs import RunKind

    scene = run.scene
    box = (np.asarray(scene.box_lo), np.asarray(scene.box_hi))
    source: dict[str, Any] = {"center": scene.source.center, "radius": scene.source.radius}
    estimate = run.settings.source_estimate if run.kind is RunKind.RECONSTRUCT else None
    if estimate is not None:
        source["depth"] = {"cue": estimate.depth_cue,
                           "range": None if estimate.depth_range is None else [list(p) for p in estimate.depth_range]}
    found = describe(run.cameras(), box, up=scene.up, source=source, solids=scene.solids)
    health = report(run, audience=audience)
    return found if health is None else {**found, "health": health}

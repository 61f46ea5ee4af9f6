"""`GET /v1/cameras/single`: the scene box of one video's camera made from a field of view, as
that camera sees it, so the upload form draws it on the video's first frame while the user types
the field of view (issue 48: a guessed field of view could not be checked against the footage).
The camera and box are the ones `POST /v1/scenes` makes from `fov` (`fluidcore.cameras.single`),
projected by `fluidcore.cameras.box_edges`: the browser holds no copy of either.
"""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query

from api.deps import OwnerDep
from api.errors import error_responses
from api.schemas import SceneBox, SingleCameraView

router = APIRouter(prefix="/v1/cameras", tags=["scenes"], responses=error_responses(401, 422, 503))
MAX_SIDE = 16384  # pixels on a side of the frame asked about: any video an upload accepts


@router.get("/single", response_model=SingleCameraView)
def single_camera_view(
    owner: OwnerDep,
    width: Annotated[int, Query(ge=1, le=MAX_SIDE, description="the video's width, pixels")],
    height: Annotated[int, Query(ge=1, le=MAX_SIDE, description="the video's height, pixels")],
    fov: Annotated[float, Query(description="horizontal field of view, degrees (as `fov` of POST /v1/scenes)")],
    up: Annotated[str, Query(description="where world up points in the image: up, down, left, right")] = "up",
    distance: Annotated[float, Query(description="camera distance from the scene centre, world units")] = 1.0,
) -> SingleCameraView:
    """The box (world units) and its 12 edges in the video's pixels, each cut to its part in front
    of the camera; a field of view, up or distance the upload would refuse is a 422 naming it."""
    from fluidcore.cameras import box_edges
    from fluidcore.cameras.single import single_camera

    camera, box = single_camera("video", width, height, fov, distance, up)
    return SingleCameraView(box=SceneBox(min=box[0].tolist(), max=box[1].tolist()),
                            edges=[[list(a), list(b)] for a, b in box_edges(camera, box)])

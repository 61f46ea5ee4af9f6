"""`POST /v1/wind/accelerations`: a wind's acceleration at given heights, for the what-if view's
arrows, so the browser draws the gain the simulator applies (`WindParams.gain`, the one formula)
without a copy of it. A wind the model refuses is a 422 naming the field, which the view shows.
"""

from __future__ import annotations

import math

from fastapi import APIRouter, HTTPException, status

from api.deps import OwnerDep
from api.errors import StrictJSONRoute, error_responses
from api.schemas import WindAccelerations, WindHeights

router = APIRouter(prefix="/v1/wind", tags=["what-if"], route_class=StrictJSONRoute, responses=error_responses(401, 422, 503))


@router.post("/accelerations", response_model=WindAccelerations)
def wind_accelerations(body: WindHeights, owner: OwnerDep) -> WindAccelerations:
    """strength * gain(height - base height) at each height, the base height being the wind's own
    `base_height` or else `source_height` (`WindParams.reference_height`)."""
    wind = body.wind
    base = wind.reference_height(body.source_height)
    accelerations = [wind.strength * wind.gain(height - base) for height in body.heights]
    if not all(math.isfinite(a) for a in accelerations):  # heights or a base height far outside any scene
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, "heights: the wind's acceleration overflows there")
    return WindAccelerations(accelerations=accelerations)

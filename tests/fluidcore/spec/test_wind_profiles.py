"""Wind profiles: each profile's force field (physics) and its peak in a box (validation) agree
with the formulas in docs, and the parameters that make no sense are refused."""

from __future__ import annotations

import math

import pytest
import torch

from fluidcore.spec.controls import InteractionError, WindParams, parse_interaction
from fluidcore.physics import wind_force

HEIGHTS = torch.tensor([-0.2, 0.0, 0.1, 0.5, 1.0], dtype=torch.float64)
BASE = 0.25  # source height


def _wind(profile: str, growth: float, strength: float = 1.5, direction=(0.0, 0.0, 2.0)) -> WindParams:  # noqa: ANN001
    return parse_interaction({"direction": list(direction), "strength": strength, "growth": growth, "profile": profile}, None).wind


def _field(profile: str, growth: float) -> torch.Tensor:
    """Force at points straight above each other (x = z = 0), heights HEIGHTS + BASE, up = +y."""
    force = wind_force(_wind(profile, growth), lambda time: True, base_height=BASE)
    points = torch.zeros(len(HEIGHTS), 3, dtype=torch.float64)
    points[:, 1] = HEIGHTS + BASE
    return force(points, 0.0)


@pytest.mark.parametrize(
    ("profile", "growth", "gain"),
    [
        ("exponential", 2.0, lambda z: math.exp(2.0 * z)),
        ("linear", 2.0, lambda z: max(0.0, 1.0 + 2.0 * z)),
        ("linear", -4.0, lambda z: max(0.0, 1.0 - 4.0 * z)),  # a ramp that dies out at z = 0.25
        ("uniform", 0.0, lambda z: 1.0),
    ],
)
def test_each_profile_is_its_formula_along_the_direction(profile: str, growth: float, gain) -> None:
    field = _field(profile, growth)
    assert torch.all(field[:, :2] == 0)  # along the (normalised) direction only
    expected = torch.tensor([1.5 * gain(float(z)) for z in HEIGHTS], dtype=torch.float64)
    torch.testing.assert_close(field[:, 2], expected)


@pytest.mark.parametrize("profile", ["exponential", "linear", "uniform"])
def test_validation_peak_matches_the_field_at_the_box_corners(profile: str) -> None:
    wind = _wind(profile, 0.0 if profile == "uniform" else 3.0, strength=2.0, direction=(1, 0, 0))
    lo, hi = (-0.5, 0.0, -0.5), (0.5, 1.2, 0.5)
    corners = torch.tensor([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])], dtype=torch.float64)
    field = wind_force(wind, lambda time: True, base_height=0.3)(corners, 0.0)
    assert wind.peak_acceleration(lo, hi, 0.3) == pytest.approx(float(field.norm(dim=1).max()))


def test_profile_errors_name_the_field() -> None:
    with pytest.raises(InteractionError, match="wind.profile"):
        parse_interaction('{"direction": [1, 0, 0], "strength": 1, "profile": "gusty"}', None)
    with pytest.raises(InteractionError, match="growth must be 0 for a uniform wind"):
        parse_interaction('{"direction": [1, 0, 0], "strength": 1, "growth": 1, "profile": "uniform"}', None)


def test_default_profile_is_the_papers_exponential() -> None:
    wind = parse_interaction('{"direction": [0, 0, 1], "strength": 1, "growth": 2}', None).wind
    assert wind.profile == "exponential"
    torch.testing.assert_close(_field("exponential", 2.0), _field(wind.profile, wind.growth))


def test_ball_activity_and_motion_have_one_definition() -> None:
    ball = parse_interaction(None, {"center": [0, 0.5, 0], "radius": 0.1, "start_frame": 3, "velocity": [1, 0, 0]}).ball
    assert [ball.active(f) for f in (2, 3, 4)] == [False, True, True]
    assert ball.center_at(3, 0.1) == (0.0, 0.5, 0.0)
    assert ball.center_at(5, 0.1) == pytest.approx((0.2, 0.5, 0.0))

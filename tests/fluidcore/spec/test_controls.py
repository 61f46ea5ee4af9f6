"""Counterfactual parameters: what a user may ask for, and the clear refusals of what makes no sense."""

from __future__ import annotations

import math
import subprocess
import sys

import pytest

from fluidcore.spec.controls import (
    MAX_GAIN_EXPONENT,
    BallParams,
    InteractionError,
    InteractionParams,
    WindParams,
    branch_frame,
    parse_interaction,
)
from fluidcore.spec.physics import PBFConfig, Source
from fluidcore.spec.scene import Scene, SceneError

FRAMES = 30
LO, HI = (-1.0, 0.0, -1.0), (1.0, 2.0, 1.0)


def scene(hi: tuple[float, float, float] = HI) -> Scene:
    """A run's scene: speed limit 60 units/s at dt 1/30 (winds up to 1800 units/s^2), source at height 0."""
    return Scene(LO, hi, (0.0, 1.0, 0.0), PBFConfig(dt=1 / 30, h=1.0, max_speed=60.0), Source((0.0, 0.0, 0.0), 0.1, 1))


def test_wind_direction_is_normalised_and_window_is_exclusive() -> None:
    wind = WindParams(direction=(3.0, 0.0, 4.0), strength=2.0, start_frame=2, end_frame=5)
    assert wind.direction == pytest.approx((0.6, 0.0, 0.8))
    assert [wind.active(f) for f in range(7)] == [False, False, True, True, True, False, False]


def test_open_ended_wind_blows_until_the_end() -> None:
    wind = WindParams(direction=(1, 0, 0), strength=1.0, start_frame=3)
    assert not wind.active(2) and wind.active(3) and wind.active(10_000)


@pytest.mark.parametrize(
    ("wind", "ball", "field"),
    [
        ('{"direction": [1, 0, 0], "strength": NaN}', None, "wind.strength"),
        ('{"direction": [0, 0, 0], "strength": 1}', None, "wind.direction"),
        ('{"direction": [1, 0, Infinity], "strength": 1}', None, "wind.direction[2]"),
        ('{"direction": [1, 0, 0], "strength": -1}', None, "wind.strength"),
        ('{"direction": [1, 0, 0], "strength": 1e9}', None, "wind.strength"),
        ('{"direction": [1, 0, 0], "strength": 1, "start_frame": 4, "end_frame": 4}', None, "end_frame"),
        ('{"direction": [1, 0, 0], "strength": 1, "gust": true}', None, "wind.gust"),
        (None, '{"center": [0, 1, 0], "radius": -0.1}', "ball.radius"),
        (None, '{"center": [0, 1, 0], "radius": 0}', "ball.radius"),
        (None, '{"center": [0, NaN, 0], "radius": 0.1}', "ball.center[1]"),
        (None, '{"center": [0, 1], "radius": 0.1}', "ball.center[2]"),
        (None, '{"center": [0, 1, 0], "radius": 0.1, "start_frame": -1}', "ball.start_frame"),
        ("{not json", None, "wind is not valid JSON"),
        (None, "[0, 1, 0]", "ball must be a JSON object"),
    ],
)
def test_invalid_parameters_name_the_field(wind: str | None, ball: str | None, field: str) -> None:
    with pytest.raises(InteractionError, match=field.replace("[", r"\[").replace("]", r"\]")) as info:
        parse_interaction(wind, ball)
    assert "\n" not in str(info.value) and "errors.pydantic.dev" not in str(info.value)


def test_both_at_once_and_from_dicts() -> None:
    params = parse_interaction({"direction": [0, 0, 2], "strength": 5}, '{"center": [0, 1, 0], "radius": 0.2}')
    assert params.wind is not None and params.wind.direction == (0.0, 0.0, 1.0)
    assert params.ball is not None and params.ball.radius == 0.2 and params.ball.velocity == (0.0, 0.0, 0.0)
    assert parse_interaction(None, None) == InteractionParams()


def test_ball_outside_the_scene_box_is_refused() -> None:
    params = InteractionParams(ball=BallParams(center=(0.0, 3.0, 0.0), radius=0.1))
    with pytest.raises(InteractionError, match="ball.center .* outside the scene box"):
        params.check_scene(scene(), FRAMES)
    InteractionParams(ball=BallParams(center=(0.0, 1.0, 0.0), radius=0.1)).check_scene(scene(), FRAMES)


def test_ball_larger_than_the_scene_is_refused() -> None:
    with pytest.raises(InteractionError, match="ball.radius"):
        InteractionParams(ball=BallParams(center=(0.0, 1.0, 0.0), radius=5.0)).check_scene(scene(), FRAMES)


def test_wind_beyond_what_the_simulator_resolves_is_absurd_for_this_scene() -> None:
    calm = WindParams(direction=(1, 0, 0), strength=100.0)
    InteractionParams(wind=calm).check_scene(scene(), FRAMES)
    # The same strength is absurd once it grows tenfold per unit of height over a 2-unit box.
    growing = WindParams(direction=(1, 0, 0), strength=100.0, growth=math.log(10.0))
    assert growing.peak_acceleration(LO, HI, 0.0) == pytest.approx(100.0 * 100.0)
    with pytest.raises(InteractionError, match="wind.strength"):
        InteractionParams(wind=growing).check_scene(scene(), FRAMES)


def test_wind_peak_is_at_the_bottom_when_it_decays_with_height() -> None:
    wind = WindParams(direction=(1, 0, 0), strength=1.0, growth=-2.0)
    assert wind.peak_acceleration((0, -1, 0), (1, 1, 1), base_height=0.0) == pytest.approx(math.exp(2.0))


def test_a_growth_past_the_gain_cap_is_judged_by_the_gain_the_physics_applies_and_refused() -> None:
    """exp(50 * 20) overflows a float; the check measures the capped gain the simulator applies
    (`WindParams.gain`, the one formula), which is still far too strong for the scene."""
    wind = WindParams(direction=(1, 0, 0), strength=1.0, growth=50.0)
    assert wind.peak_acceleration(LO, (1.0, 20.0, 1.0), 0.0) == math.exp(MAX_GAIN_EXPONENT)
    with pytest.raises(InteractionError, match="wind.strength"):
        InteractionParams(wind=wind).check_scene(scene(hi=(1.0, 20.0, 1.0)), FRAMES)


@pytest.mark.parametrize("which", ["wind", "ball"])
def test_intervention_starting_after_the_horizon_is_refused(which: str) -> None:
    params = parse_interaction(
        {"direction": [1, 0, 0], "strength": 1, "start_frame": 30} if which == "wind" else None,
        {"center": [0, 1, 0], "radius": 0.1, "start_frame": 30} if which == "ball" else None,
    )
    with pytest.raises(InteractionError, match=f"{which}.start_frame"):
        params.check_scene(scene(), FRAMES)


def test_parameters_import_without_torch() -> None:
    code = "import sys, fluidcore.spec.controls, fluidcore.spec.jobs, fluidcore.spec.limits; sys.exit('torch' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code]).returncode == 0


def test_run_scene_from_a_manifest_is_checked_without_torch() -> None:
    manifest_scene = Scene.from_json({
        "box": {"lo": [-1.0, 0.0, -1.0], "hi": [1.0, 2.0, 1.0]},
        "up": [0.0, 1.0, 0.0],
        "physics": {"dt": 1 / 30, "h": 1.0, "max_speed": None},  # h / dt = 30 units/s: winds up to 900 units/s^2
        "source": {"center": [0.0, 0.5, 0.0], "radius": 0.1, "rate": 1},
    })
    InteractionParams(wind=WindParams(direction=(1, 0, 0), strength=850.0)).check_scene(manifest_scene, frames=10)
    with pytest.raises(InteractionError, match="wind.strength"):
        InteractionParams(wind=WindParams(direction=(1, 0, 0), strength=950.0)).check_scene(manifest_scene, frames=10)
    with pytest.raises(InteractionError, match="ball.center"):
        InteractionParams(ball=BallParams(center=(0.0, -0.5, 0.0), radius=0.1)).check_scene(manifest_scene, frames=10)
    with pytest.raises(SceneError, match="scene: malformed"):
        Scene.from_json({"box": {}})


def test_a_what_if_needs_wind_or_ball_and_its_schema_says_so() -> None:
    """Issue 20 item 9: one rule (`Intervention`), stated in the JSON Schema the API publishes, so a
    schema-valid interact request is never refused for asking for neither."""
    import jsonschema

    from fluidcore.spec.controls import Intervention
    from fluidcore.spec.jobs import InteractParams

    assert InteractionParams().wind is None  # a prediction asks for neither
    with pytest.raises(InteractionError, match="needs a wind, a ball or both"):
        parse_interaction(None, None, Intervention)
    wind = {"direction": [1.0, 0.0, 0.0], "strength": 0.1}
    schema = InteractParams.model_json_schema()
    for params, valid in (({"frames": 3}, False), ({"frames": 3, "wind": None, "ball": None}, False),
                          ({"frames": 3, "wind": wind}, True)):
        errors = list(jsonschema.Draft202012Validator(schema).iter_errors(params))
        assert (not errors) == valid, (params, errors)
        try:
            InteractParams.model_validate(params)
            accepted = True
        except ValueError:
            accepted = False
        assert accepted == valid, params  # the model and its schema agree


def test_a_wind_base_height_replaces_the_source_height_in_the_scene_check() -> None:
    """The peak is measured from the wind's own base height when it names one: the same wind is
    fine measured from the source (z <= 0 in a decaying wind) and absurd from a base far above."""
    decaying = {"direction": (1, 0, 0), "strength": 100.0, "growth": -math.log(10.0)}
    InteractionParams(wind=WindParams(**decaying)).check_scene(scene(), FRAMES)
    assert WindParams(**decaying).reference_height(0.25) == 0.25
    high = WindParams(**decaying, base_height=2.0)
    assert high.reference_height(0.25) == 2.0
    with pytest.raises(InteractionError, match="wind.strength"):
        InteractionParams(wind=high).check_scene(scene(), FRAMES)


@pytest.mark.parametrize("base_height", [-1e308, 1e308, -1e6, 50.0])
def test_a_wind_base_height_far_outside_the_scene_is_refused(base_height: float) -> None:
    """A base height more than BASE_HEIGHT_REACH box heights from the box names no height of this
    scene; -1e308 used to pass the check and end the job on NaN."""
    from fluidcore.spec.controls import BASE_HEIGHT_REACH

    box = scene()
    extent = box.box_hi[1] - box.box_lo[1]
    wind = {"direction": (1, 0, 0), "strength": 0.1, "growth": 0.0, "profile": "uniform"}
    with pytest.raises(InteractionError, match="wind.base_height"):
        InteractionParams(wind=WindParams(**wind, base_height=base_height)).check_scene(box, FRAMES)
    inside = box.box_hi[1] + 0.5 * BASE_HEIGHT_REACH * extent  # above the box, within reach: a user's ramp
    InteractionParams(wind=WindParams(**wind, base_height=inside)).check_scene(box, FRAMES)


def test_the_branch_frame_is_a_finished_frame_or_the_last() -> None:
    """`branch_frame`, the one from_frame rule the API and the job ask: None is the last finished
    frame, a finished frame is itself, any other is refused naming the field and the run."""
    assert branch_frame(None, [3, 4, 5], "run r") == 5
    assert branch_frame(3, [3, 4, 5], "run r") == 3
    with pytest.raises(InteractionError, match=r"from_frame: 6 is not a finished frame of the parent run \(run r: frames 3..5\)"):
        branch_frame(6, [3, 4, 5], "run r")
    with pytest.raises(InteractionError, match="from_frame: run r has no finished frame"):
        branch_frame(None, [], "run r")


def test_the_api_and_the_job_refuse_a_branch_frame_by_the_one_rule() -> None:
    """Neither the API's check of a new job (`service.jobs`) nor the prediction job states the rule
    again: both call `branch_frame`."""
    import inspect

    import fluidcore.predict.job
    import service.jobs

    for module in (service.jobs, fluidcore.predict.job):
        source = inspect.getsource(module)
        assert "branch_frame(" in source and "not in frames" not in source and "not in record.frames" not in source, module


@pytest.mark.parametrize(("profile", "growth"), [("exponential", 2.0), ("exponential", 40.0), ("linear", -3.0), ("uniform", 0.0)])
def test_the_gain_is_one_formula_for_floats_and_tensors(profile: str, growth: float) -> None:
    """`WindParams.gain` on a float (the scene check, the browser's arrows) equals it on a tensor
    (the physics), the exponent's cap included."""
    import torch

    wind = WindParams(direction=(1, 0, 0), strength=1.0, growth=growth, profile=profile)
    heights = [-1.0, -0.2, 0.0, 0.3, 1.0, 2.0]  # 40 * 2 is past the exponent's cap
    on_tensor = wind.gain(torch.tensor(heights, dtype=torch.float64)).tolist()
    assert on_tensor == pytest.approx([wind.gain(h) for h in heights], rel=1e-12)
    if profile == "exponential":
        assert wind.gain(2.0) == math.exp(min(2.0 * growth, MAX_GAIN_EXPONENT))

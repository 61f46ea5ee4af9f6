"""Interventions: the one place where wind and ball parameters become physics.

The parameters arrive validated (fluidcore.spec.controls: `WindParams`, `BallParams`, checked
against the run's scene by `InteractionParams.check_scene`) and are counted in new frames from
the first predicted one. Here they meet the run's scene and clock: frame numbers become
simulator seconds, the wind becomes a force field on the smoke and on the air around it
(`fluidcore.physics.wind_force`, `wind_air`) and the ball a moving `Sphere` that enters the scene
on its start frame.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from fluidcore.spec.controls import BallParams, InteractionParams, WindParams
from fluidcore.physics import AirField, ForceField, PBFConfig, Source, Sphere, wind_air, wind_force
from fluidcore.physics.motion import Controls


@dataclass(frozen=True)
class Ball:
    """A ball in simulator terms: the sphere, and the first new frame it is in the scene."""

    sphere: Sphere
    first_frame: int


@dataclass(frozen=True)
class Interventions:
    """What the rollout applies: a force field and the air velocity it causes (or None), and a
    ball (or None); `controls` is what reaches the simulator each new frame."""

    force: ForceField | None = None
    air: AirField | None = None
    ball: Ball | None = None
    terminal_time: float | None = None  # the wind's (`WindParams.terminal_time`): how it bounds the air it drives

    def controls(self, index: int) -> Controls:
        """The controls of new frame `index` (0 = the first new one): the wind's force and air
        (each knows when it blows), the ball from its first frame on."""
        spheres = () if self.ball is None or index < self.ball.first_frame else (self.ball.sphere,)
        return Controls(self.force, self.air, spheres, self.terminal_time)


def interventions(
    params: InteractionParams, config: PBFConfig, source: Source, up: Sequence[float], start_time: float
) -> Interventions:
    """The physics of `params` in a scene whose new frame 0 is the step starting at `start_time`.

    The wind's strength is given at its reference height (its own base height, or the source's),
    so its growth is measured from there.
    """
    force = air = None
    if params.wind is not None:
        wind = params.wind
        base_height = wind.reference_height(float(np.dot(source.center, up)))
        blowing = lambda time: wind.active(frame_at(time, start_time, config.dt))  # noqa: E731
        force = wind_force(wind, blowing, base_height, tuple(up))
        air = wind_air(wind, seconds_blown(wind, start_time, config.dt), base_height, tuple(up))
    ball = None if params.ball is None else ball_sphere(params.ball, start_time, config.dt)
    return Interventions(force, air, ball, None if params.wind is None else params.wind.terminal_time)


def seconds_blown(wind: WindParams, start_time: float, dt: float) -> Callable[[float], float]:
    """Seconds the wind has blown by simulator time `time` (0 before its first frame, frozen
    after its last): its window [start_frame, end_frame) in new frames from `start_time`."""
    begin = start_time + wind.start_frame * dt
    end = math.inf if wind.end_frame is None else start_time + wind.end_frame * dt
    return lambda time: max(0.0, min(time, end) - begin)


def frame_at(time: float, start_time: float, dt: float) -> int:
    """The new frame whose step starts at `time` (frame f starts at start_time + f dt). Rounding,
    not flooring, keeps a step in its frame despite float error accumulated in the simulator's time."""
    return math.floor((time - start_time) / dt + 0.5)


def ball_sphere(ball: BallParams, start_time: float, dt: float) -> Ball:
    """The sphere of a ball that is at `ball.center` at the end of new frame `ball.start_frame`
    (the step starting at start_time + start_frame dt) and moves at `ball.velocity` after."""
    arrival = start_time + (ball.start_frame + 1) * dt
    center = tuple(c - u * arrival for c, u in zip(ball.center, ball.velocity))
    return Ball(Sphere(center=center, radius=ball.radius, velocity=ball.velocity), ball.start_frame)

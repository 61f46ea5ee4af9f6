"""Interventions: the one place where wind and ball parameters become physics.

The parameters arrive validated (fluidcore.interaction: `WindParams`, `BallParams`, checked
against the run's scene by `InteractionParams.check_scene`) and are counted in new frames from
the first predicted one. Here they meet the run's scene and clock: frame numbers become
simulator seconds, the wind becomes a force field (`fluidcore.physics.wind_force`) and the ball
a moving `Sphere` that enters the scene on its start frame.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from fluidcore.interaction import BallParams, InteractionParams
from fluidcore.physics import ForceField, PBFConfig, Source, Sphere, wind_force


@dataclass(frozen=True)
class Ball:
    """A ball in simulator terms: the sphere, and the first new frame it is in the scene."""

    sphere: Sphere
    first_frame: int


@dataclass(frozen=True)
class Interventions:
    """What the rollout applies: a force field (or None) and a ball (or None)."""

    force: ForceField | None = None
    ball: Ball | None = None


def interventions(
    params: InteractionParams, config: PBFConfig, source: Source, up: Sequence[float], start_time: float
) -> Interventions:
    """The physics of `params` in a scene whose new frame 0 is the step starting at `start_time`.

    The wind's strength is given at the source's height, so its growth is measured from there.
    """
    force = None
    if params.wind is not None:
        base_height = float(np.dot(source.center, up))
        force = wind_force(params.wind, start_time, config.dt, base_height, tuple(up))
    ball = None if params.ball is None else ball_sphere(params.ball, start_time, config.dt)
    return Interventions(force, ball)


def ball_sphere(ball: BallParams, start_time: float, dt: float) -> Ball:
    """The sphere of a ball that is at `ball.center` at the end of new frame `ball.start_frame`
    (the step starting at start_time + start_frame dt) and moves at `ball.velocity` after."""
    arrival = start_time + (ball.start_frame + 1) * dt
    center = tuple(c - u * arrival for c, u in zip(ball.center, ball.velocity))
    return Ball(Sphere(center=center, radius=ball.radius, velocity=ball.velocity), ball.start_frame)

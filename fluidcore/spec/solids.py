"""Solids in a scene: static balls the smoke flows around (issue 48), part of the scene a
reconstruction simulates and every prediction and what-if from it (`fluidcore.spec.scene.Scene.solids`).

A solid is a ball (centre and radius in world units) that never moves and never feels the
smoke: the one-way coupling of a what-if's ball (`fluidcore.physics.coupling`), there from the
first step on. The user places them (`fluidnexus reconstruct --ball`, the API's reconstruct
`params.solids`, the browser's upload form), so they are validated where a request enters and
checked against the scene box once it is known (`check_solids`). The rule of a ball in a box is
one (`ball_box_problem`): a what-if's ball (`fluidcore.spec.controls.BallParams`) follows it too.
Torch-free, like the whole spec.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field

from fluidcore.errors import InputError
from fluidcore.spec.physics import Sphere, Vec3

# Solids a scene holds at most: each is a wall in the air's projection and a push-out of every
# particle each step, so the count bounds what they add to a step; a scene of balls is not a mesh.
MAX_SOLIDS = 8


class SolidError(InputError):
    """A solid that cannot be in this scene; the message names the field (`solids[0].center`)."""


class SolidBall(BaseModel):
    """A static ball in the scene: the smoke never enters it, it never moves."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    center: Vec3 = Field(description="its centre, world units (inside the scene box)")
    radius: float = Field(gt=0.0, description="world units (at most the scene box's size)")

    @property
    def sphere(self) -> Sphere:
        """The ball as the physics takes it (`fluidcore.physics.motion.Controls.spheres`): at rest."""
        return Sphere(center=self.center, radius=self.radius)

    def check_in_box(self, lo: Sequence[float], hi: Sequence[float], field: str) -> None:
        """SolidError (naming `field`) unless the ball lies in the box [lo, hi] (`ball_box_problem`)."""
        problem = ball_box_problem(self.center, self.radius, lo, hi, field)
        if problem is not None:
            raise SolidError(problem)


Solids = Annotated[tuple[SolidBall, ...], Field(
    default=(), max_length=MAX_SOLIDS,
    description=f"static balls in the scene the smoke flows around (at most {MAX_SOLIDS}; world units, inside the scene box)",
)]


def gap_record(index: int) -> str:
    """The name of a reconstruction's per-frame record (a frame's losses) of how far the smoke kept
    from solid `index`: the gap, world units, between the ball's surface and its nearest particle
    (`fluidcore.physics.coupling.surface_gaps`). The one spelling, for the loop that writes it and
    the health report that reads it (`fluidcore.health`)."""
    return f"solid_{index}_gap"


def check_solids(solids: Sequence[SolidBall], lo: Sequence[float], hi: Sequence[float], field: str = "solids") -> None:
    """SolidError naming the first ball of `solids` that does not fit the box [lo, hi], or too many
    of them; `field` names the list in the message (`solids`, `params.solids`, `scene.solids`)."""
    if len(solids) > MAX_SOLIDS:
        raise SolidError(f"{field}: {len(solids)} balls, at most {MAX_SOLIDS}")
    for index, solid in enumerate(solids):
        solid.check_in_box(lo, hi, f"{field}[{index}]")


def ball_box_problem(center: Sequence[float], radius: float, lo: Sequence[float], hi: Sequence[float],
                     field: str) -> str | None:
    """Why a ball at `center` of `radius` cannot be in the scene box [lo, hi] (its centre outside,
    or a radius beyond the box's size: it would swallow the scene), naming `field`; None when it
    can. The one rule of a ball in a box, a scene's solids and a what-if's ball alike."""
    box = f"{[float(v) for v in lo]}..{[float(v) for v in hi]}"
    if not all(a <= c <= b for c, a, b in zip(center, lo, hi, strict=True)):
        return f"{field}.center {[float(v) for v in center]} is outside the scene box {box}"
    if radius > max(b - a for a, b in zip(lo, hi, strict=True)):
        return f"{field}.radius {radius} is larger than the scene box {box}"
    return None

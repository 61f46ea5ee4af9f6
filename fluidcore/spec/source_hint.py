"""Where the smoke comes from, when the user knows it: the one parameter model of a source hint.

One view leaves the source's depth open (`fluidcore.reconstruct.source_estimate.estimate_source` puts it
where the input ray passes closest to the box's vertical axis), and the whole 3D plume inherits
that guess: on the dev scene a source 4 cm off that axis costs 8 dB of novel-view PSNR
(docs/bench_generalise.md). Someone who measured their rig can say where the source is.
Torch-free, so the API validates it before anything is queued; the CLI, the API and the worker
share it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from fluidcore.errors import InputError
from fluidcore.spec.scene import SourcePlace

Vec3 = tuple[float, float, float]
# What of a source the user gave the identification keeps as given (issue 33: D's true radius 0.035,
# given, became 0.028): "place" a whole source, "center" a centre whose radius the input view
# measured (the size is still chosen, around that centre), "nothing" an estimated source or a hint
# the user asked to refine (`SourceHint.refine`).
SourceKept = Literal["nothing", "center", "place"]


class SourceHintError(InputError):
    """A source hint that cannot be used in this scene; the message names the field."""


class SourceHint(BaseModel):
    """The source's centre (world units, the cameras' frame) and, optionally, its radius; without
    a radius it is measured from the input view at that centre's depth. The identification keeps
    what the user gave as given (`fluidcore.reconstruct.identify.SourceKept`), and chooses a
    measured radius around the centre; `refine` lets it move the centre and resize the source
    too, as it does an estimated one."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    center: Vec3
    radius: float | None = Field(default=None, gt=0.0)
    refine: bool = False

    @property
    def kept(self) -> SourceKept:
        """What of it the identification keeps (`SourceKept`)."""
        return "nothing" if self.refine else ("center" if self.radius is None else "place")

    @property
    def place(self) -> SourcePlace | None:
        """The whole place when the radius is given; None when it is to be measured."""
        return None if self.radius is None else SourcePlace(self.center, self.radius)

    def check_in_box(self, lo: Sequence[float], hi: Sequence[float]) -> None:
        """The centre must lie in the scene box (where the reconstruction simulates)."""
        if not all(a <= c <= b for a, c, b in zip(lo, self.center, hi, strict=True)):
            raise SourceHintError(
                f"source.center {list(self.center)} is outside the scene box {[list(lo), list(hi)]} (world units)"
            )
        if self.radius is not None and not self.radius < max(b - a for a, b in zip(lo, hi, strict=True)):
            raise SourceHintError(f"source.radius {self.radius} is larger than the scene box")


def parse_source(text: str, refine: bool = False) -> SourceHint:
    """`X,Y,Z` or `X,Y,Z,R` (world units) from the command line; `refine`: --refine-source."""
    try:
        values = [float(part) for part in text.split(",")]
    except ValueError:
        values = []
    if len(values) not in (3, 4) or not all(math.isfinite(v) for v in values):
        raise SourceHintError(f"--source: expected X,Y,Z or X,Y,Z,R in world units, got {text!r}")
    try:
        return SourceHint(center=tuple(values[:3]), radius=values[3] if len(values) == 4 else None, refine=refine)
    except ValueError as exc:
        raise SourceHintError(f"--source {text}: the radius must be positive") from exc

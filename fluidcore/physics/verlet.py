"""Neighbour lists reused across calls while the particles stay close (a Verlet list with a skin).

An optimiser calls `sim_step` and `incompressibility_loss` hundreds of times on positions that
move a little per iteration; rebuilding the neighbour list every time costs 10-20 % of a
differentiable `sim_step`. A list of all pairs within h + skin of the positions X0 it was built
from still holds every pair within h of positions X as long as no particle moved more than
skin / 2 from X0 (two particles then approach by at most skin). Each call filters that list
down to the pairs closer than h, with the same test as a fresh build, so the solver sees exactly
the pairs it would otherwise (in another order: results agree up to float rounding) and pays
for no extra pair. When a particle moved farther, or the particle count changed, the list is
rebuilt: a cache is never wrong, only sometimes not faster.

One cache per set of positions: the particles' own positions (`incompressibility_loss`) and
their predicted positions inside `sim_step` need one cache each.
"""

from __future__ import annotations

import torch
from torch import Tensor

from fluidcore.physics import fused
from fluidcore.physics.neighbours import NeighbourList, neighbours_torch
from fluidcore.spec.physics import PhysicsInputError


class NeighbourCache:
    """Pairs within h + skin of the positions last built from, rebuilt when they went stale.

    h: the kernel radius the list is used with (`PBFConfig.h`); skin: extra radius, world units
    (default 0.2 h: rebuilt once a particle moved 0.1 h). `builds` counts the lists built so far.
    """

    def __init__(self, h: float, skin: float | None = None) -> None:
        if not (isinstance(h, (int, float)) and 0 < h < float("inf")):
            raise PhysicsInputError(f"h must be a positive finite number, got {h!r}")
        skin = 0.2 * h if skin is None else skin
        if not (isinstance(skin, (int, float)) and 0 <= skin < float("inf")):
            raise PhysicsInputError(f"skin must be a finite number >= 0, got {skin!r}")
        self.h, self.skin = float(h), float(skin)
        self.builds = 0
        self._reference: Tensor | None = None
        self._pairs: tuple[Tensor, Tensor] | None = None

    def neighbours(self, positions: Tensor) -> NeighbourList:
        """The pairs of `positions` closer than h (exactly those of a fresh list), grouped by particle."""
        points = positions.detach()
        if self._pairs is None or self._stale(points):
            self._build(points)
        i, j = self._pairs  # type: ignore[misc]
        d = points.index_select(0, i) - points.index_select(0, j)
        keep = (d * d).sum(dim=1) < self.h * self.h
        i, j = i[keep], j[keep]
        offsets = torch.zeros(points.shape[0] + 1, dtype=torch.long, device=points.device)
        torch.cumsum(torch.bincount(i, minlength=points.shape[0]), 0, out=offsets[1:])
        return NeighbourList(offsets, j)

    def _build(self, points: Tensor) -> None:
        radius = self.h + self.skin
        on_cpu = points.device.type == "cpu" and fused.available()
        wide = fused.neighbours_fused(points, radius) if on_cpu else neighbours_torch(points, radius)
        self._pairs = wide.pairs()
        self._reference = points.clone()
        self.builds += 1

    def _stale(self, points: Tensor) -> bool:
        reference = self._reference
        if reference is None or reference.shape != points.shape or reference.device != points.device:
            return True
        moved = (points - reference).square().sum(dim=1)
        return points.shape[0] > 0 and float(moved.max()) > (0.5 * self.skin) ** 2

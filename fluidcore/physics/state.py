"""Particle state with growable capacity: slots of retired particles are reused by new ones."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from fluidcore.physics import checks

if TYPE_CHECKING:
    from fluidcore.physics.air import AirState

MIN_CAPACITY = 1024


@dataclass
class ParticleState:
    """Physical particles (mass 1 each) in slots 0..C-1; only slots with alive=True exist.

    A particle keeps its slot for life, so slot i is the same particle in every frame (the
    reconstruction and the visual particles rely on that).
    """

    positions: Tensor  # (C, 3) float32, world units
    velocities: Tensor  # (C, 3) float32, world units / s
    alive: Tensor  # (C,) bool
    time: float = 0.0  # seconds; 0 is the first frame after stabilisation
    step: int = 0  # steps taken (drives the source's deterministic seeding)
    air: AirState | None = None  # the air around the particles, when a Simulator with an AirGrid steps them

    @classmethod
    def empty(cls, capacity: int = MIN_CAPACITY, device: torch.device | str = "cpu") -> ParticleState:
        """A state with no particles."""
        return cls(
            torch.zeros(capacity, 3, device=device),
            torch.zeros(capacity, 3, device=device),
            torch.zeros(capacity, dtype=torch.bool, device=device),
        )

    @classmethod
    def from_positions(cls, positions: Tensor, velocities: Tensor | None = None, time: float = 0.0) -> ParticleState:
        """A state holding the given particles, all alive (velocities default to zero)."""
        positions = checks.points(positions, "positions").detach().clone()
        if velocities is None:
            velocities = torch.zeros_like(positions)
        velocities = checks.points(velocities, "velocities", positions.shape[0]).detach().clone().to(positions.device)
        alive = torch.ones(positions.shape[0], dtype=torch.bool, device=positions.device)
        return cls(positions, velocities, alive, time)

    @property
    def capacity(self) -> int:
        return self.alive.shape[0]

    @property
    def n_alive(self) -> int:
        return int(self.alive.sum())

    @property
    def device(self) -> torch.device:
        return self.positions.device

    def clone(self) -> ParticleState:
        air = None if self.air is None else self.air.clone()
        return ParticleState(self.positions.clone(), self.velocities.clone(), self.alive.clone(), self.time, self.step, air)

    def padded(self, capacity: int) -> ParticleState:
        """This state with empty slots appended up to `capacity`: a state from before a step, laid
        out slot for slot like the state after it (a step may have grown the capacity)."""
        grow = lambda t: pad_slots(t, capacity)  # noqa: E731
        return ParticleState(grow(self.positions), grow(self.velocities), grow(self.alive), self.time, self.step,
                             None if self.air is None else self.air.clone())

    def to(self, device: torch.device | str) -> ParticleState:
        air = None if self.air is None else self.air.to(device)
        return ParticleState(self.positions.to(device), self.velocities.to(device), self.alive.to(device),
                             self.time, self.step, air)

    def free_slots(self, count: int) -> Tensor:
        """Indices of `count` dead slots (lowest first), doubling the capacity when too few are free."""
        free = torch.nonzero(~self.alive).flatten()
        if free.shape[0] < count:
            self._grow(max(2 * self.capacity, self.capacity + count - free.shape[0], MIN_CAPACITY))
            free = torch.nonzero(~self.alive).flatten()
        return free[:count]

    def add(self, positions: Tensor, velocities: Tensor) -> Tensor:
        """Insert particles into free slots; returns their slot indices."""
        slots = self.free_slots(positions.shape[0])
        self.positions[slots] = positions
        self.velocities[slots] = velocities
        self.alive[slots] = True
        return slots

    def _grow(self, capacity: int) -> None:
        self.positions = pad_slots(self.positions, capacity)
        self.velocities = pad_slots(self.velocities, capacity)
        self.alive = pad_slots(self.alive, capacity)


def pad_slots(tensor: Tensor, capacity: int) -> Tensor:
    """A per-slot tensor grown to `capacity` rows with empty slots (zeros / False)."""
    extra = capacity - tensor.shape[0]
    return tensor if extra <= 0 else torch.cat([tensor, tensor.new_zeros((extra, *tensor.shape[1:]))])

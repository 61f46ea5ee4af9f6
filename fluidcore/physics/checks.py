"""Input checks shared by the public functions: wrong shapes and NaN/Inf are rejected by name."""

from __future__ import annotations

import torch
from torch import Tensor

from fluidcore.spec.physics import PhysicsInputError


def points(value: object, name: str, n: int | None = None) -> Tensor:
    """A finite float tensor of shape (N, 3) (or (n, 3) when n is given), as float32."""
    if not isinstance(value, Tensor):
        raise PhysicsInputError(f"{name} must be a torch.Tensor of shape (N, 3), got {type(value).__name__}")
    if value.ndim != 2 or value.shape[1] != 3:
        raise PhysicsInputError(f"{name} must have shape (N, 3), got {tuple(value.shape)}")
    if n is not None and value.shape[0] != n:
        raise PhysicsInputError(f"{name} must have {n} rows to match positions, got {value.shape[0]}")
    if not value.is_floating_point():
        raise PhysicsInputError(f"{name} must be a floating-point tensor, got {value.dtype}")
    if value.numel() and not bool(torch.isfinite(value.detach()).all()):
        raise PhysicsInputError(f"{name} contains NaN or Inf")
    return value if value.dtype == torch.float32 else value.float()


def finite_result(value: Tensor, what: str) -> Tensor:
    """Raise instead of returning NaN/Inf silently (a bug or an input far outside the model's range)."""
    if value.numel() and not bool(torch.isfinite(value.detach()).all()):
        raise FloatingPointError(f"{what} became NaN or Inf")
    return value

"""The Gaussians a renderer draws, stored in the unconstrained form an optimiser works on.

Scales live in log space and opacities as logits so that any finite parameter vector is a valid
Gaussian: gradient steps can never produce a negative scale or an opacity outside (0, 1).
Quaternions are normalised at render time for the same reason. What an optimiser *can* still
produce is NaN or inf, or a zero quaternion; `validate` rejects those with a message that names
the field, before they turn into a silent black or NaN image.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from fluidcore.errors import InputError

CHANNELS = (1, 3)  # grey smoke or RGB
MIN_QUAT_NORM = 1e-8  # below this a quaternion has no direction to normalise to


class RenderError(InputError):
    """Input the renderer cannot draw; the message names the offending field."""


@dataclass
class Gaussians:
    """N 3D Gaussians (all tensors on one device, one floating dtype)."""

    means: torch.Tensor  # (N, 3) world positions
    log_scales: torch.Tensor  # (N, 3) log standard deviations along the local axes
    quats: torch.Tensor  # (N, 4) rotation, w x y z; any non-zero length
    opacity_logits: torch.Tensor  # (N,) sigmoid gives the peak opacity
    colors: torch.Tensor  # (N, C), C in {1, 3}, nominally in [0, 1]

    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def channels(self) -> int:
        return int(self.colors.shape[-1])

    @property
    def device(self) -> torch.device:
        return self.means.device

    @property
    def dtype(self) -> torch.dtype:
        return self.means.dtype

    def scales(self) -> torch.Tensor:
        return torch.exp(self.log_scales)

    def opacities(self) -> torch.Tensor:
        return torch.sigmoid(self.opacity_logits)

    def unit_quats(self) -> torch.Tensor:
        return self.quats / self.quats.norm(dim=-1, keepdim=True)

    def validate(self) -> None:
        """Raise RenderError naming the first field with a wrong shape, dtype, device or value."""
        n = len(self)
        expected = {
            "means": (n, 3),
            "log_scales": (n, 3),
            "quats": (n, 4),
            "opacity_logits": (n,),
        }
        for name, shape in expected.items():
            _check_tensor(name, getattr(self, name), shape, self)
        if self.colors.dim() != 2 or self.colors.shape[0] != n or self.colors.shape[1] not in CHANNELS:
            raise RenderError(
                f"colors must have shape (N, 1) or (N, 3) with N = {n}, got {tuple(self.colors.shape)}"
            )
        _check_tensor("colors", self.colors, tuple(self.colors.shape), self)
        if n > 0:
            norms = self.quats.detach().norm(dim=-1)
            if bool((norms < MIN_QUAT_NORM).any()):
                row = int(torch.nonzero(norms < MIN_QUAT_NORM)[0, 0])
                raise RenderError(f"quats: row {row} has (near) zero length and encodes no rotation")


def _check_tensor(name: str, value: object, shape: tuple[int, ...], g: Gaussians) -> None:
    if not isinstance(value, torch.Tensor):
        raise RenderError(f"{name} must be a torch.Tensor, got {type(value).__name__}")
    if tuple(value.shape) != shape:
        raise RenderError(f"{name} must have shape {shape}, got {tuple(value.shape)}")
    if not value.is_floating_point():
        raise RenderError(f"{name} must be a floating-point tensor, got {value.dtype}")
    if value.dtype != g.dtype or value.device != g.device:
        raise RenderError(
            f"{name} is {value.dtype} on {value.device}, but means is {g.dtype} on {g.device}; "
            "all Gaussian tensors must share dtype and device"
        )
    finite = torch.isfinite(value.detach())
    if not bool(finite.all()):
        row = int(torch.nonzero(~finite.reshape(shape[0], -1).all(dim=1))[0, 0])
        raise RenderError(f"{name}: row {row} is not finite (NaN or inf)")

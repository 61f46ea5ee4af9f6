"""EWA projection of 3D Gaussians to screen-space ellipses (differentiable, plain torch).

Each Gaussian becomes a 2D mean (pixels), a conic (the inverse 2D covariance, stored as its three
distinct entries a, b, c with sigma = 0.5 (a dx^2 + c dy^2) + b dx dy), a camera-space depth and a
screen bounding box. The conventions follow gsplat's classic 3DGS mode so that the CPU and CUDA
backends draw the same picture:

* the perspective Jacobian is evaluated at the mean with x/z and y/z clamped to 1.3x the field of
  view (a Gaussian far off to the side would otherwise be smeared across the whole screen);
* `eps2d` (0.3 px^2) is added to the 2D covariance, so a Gaussian with zero scale still covers
  about a pixel instead of becoming a singular conic;
* the bounding box reaches as far as the peak alpha opacity * exp(-sigma) stays >= 1/255, i.e.
  sqrt(2 ln(255 opacity)) standard deviations (at most 3.33 for opacity 1, about 2.5 for a typical
  smoke opacity of 0.1). Beyond it the compositor would skip the Gaussian anyway, so this cut is
  exact; a fixed 3-sigma cut would truncate opaque Gaussians visibly and differ from gsplat.

Gaussians behind the near plane, too faint to ever reach 1/255, or whose box misses the screen are
marked invisible; their other outputs are finite but meaningless.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

ALPHA_MIN = 1.0 / 255.0  # a Gaussian contributes to a pixel only where its alpha reaches this
NEAR_PLANE = 0.01  # camera-space z below which a Gaussian is not drawn (gsplat's default)
EPS2D = 0.3  # px^2 added to every 2D covariance (gsplat's default)
FOV_CLAMP = 0.3  # the Jacobian is evaluated at most 30 % of the half-FOV outside the screen


@dataclass
class Projected:
    """Screen-space Gaussians for one camera; all rows stay aligned with the input Gaussians."""

    means2d: torch.Tensor  # (N, 2) pixel coordinates, pixel (i, j) covers [j, j+1) x [i, i+1)
    conics: torch.Tensor  # (N, 3) a, b, c of the inverse 2D covariance
    depths: torch.Tensor  # (N,) camera-space z
    opacities: torch.Tensor  # (N,) peak alpha in (0, 1)
    bboxes: torch.Tensor  # (N, 4) int32 x0, x1, y0, y1 pixel ranges (half-open), clipped to the image
    visible: torch.Tensor  # (N,) bool


def quat_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """(N, 4) unit quaternions w, x, y, z -> (N, 3, 3) rotation matrices."""
    w, x, y, z = quats.unbind(-1)
    rows = [
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ]  # fmt: skip
    return torch.stack(rows, dim=-1).reshape(quats.shape[:-1] + (3, 3))


def covariance_3d(scales: torch.Tensor, unit_quats: torch.Tensor) -> torch.Tensor:
    """Sigma = R S S R^T for (N, 3) scales (standard deviations) and (N, 4) unit quaternions."""
    rs = quat_to_rotmat(unit_quats) * scales[:, None, :]
    return rs @ rs.transpose(-1, -2)


def project(
    means: torch.Tensor,
    covariances: torch.Tensor,
    opacities: torch.Tensor,
    viewmat: torch.Tensor,
    intrinsics: torch.Tensor,
    width: int,
    height: int,
    near_plane: float = NEAR_PLANE,
    eps2d: float = EPS2D,
) -> Projected:
    """Project (N, 3) means with (N, 3, 3) world covariances through a pinhole camera.

    `viewmat` is the (4, 4) world-to-camera matrix (OpenCV axes), `intrinsics` the (3, 3) K.
    Differentiable with respect to means, covariances and opacities.
    """
    rotation, translation = viewmat[:3, :3], viewmat[:3, 3]
    fx, fy, cx, cy = intrinsics[0, 0], intrinsics[1, 1], intrinsics[0, 2], intrinsics[1, 2]
    cam = means @ rotation.T + translation
    in_front = cam[:, 2] >= near_plane
    # Gaussians behind the camera get a harmless stand-in depth so that no inf or NaN enters
    # the graph (a NaN in a branch torch.where discards still poisons the gradient).
    z = torch.where(in_front, cam[:, 2], torch.ones_like(cam[:, 2]))
    x, y = cam[:, 0], cam[:, 1]

    half_fov_x, half_fov_y = 0.5 * width / fx, 0.5 * height / fy
    tx = z * torch.clamp(x / z, -(cx / fx + FOV_CLAMP * half_fov_x), (width - cx) / fx + FOV_CLAMP * half_fov_x)
    ty = z * torch.clamp(y / z, -(cy / fy + FOV_CLAMP * half_fov_y), (height - cy) / fy + FOV_CLAMP * half_fov_y)
    zeros = torch.zeros_like(z)
    jacobian = torch.stack(
        [fx / z, zeros, -fx * tx / (z * z), zeros, fy / z, -fy * ty / (z * z)], dim=-1
    ).reshape(-1, 2, 3)
    cov_cam = rotation @ covariances @ rotation.T
    cov2d = jacobian @ cov_cam @ jacobian.transpose(-1, -2)
    cov_a = cov2d[:, 0, 0] + eps2d
    cov_b = cov2d[:, 0, 1]
    cov_c = cov2d[:, 1, 1] + eps2d
    det = cov_a * cov_c - cov_b * cov_b  # >= eps2d^2 > 0 since cov2d is positive semi-definite
    conics = torch.stack([cov_c / det, -cov_b / det, cov_a / det], dim=-1)
    means2d = torch.stack([fx * x / z + cx, fy * y / z + cy], dim=-1)

    bboxes, on_screen = _screen_boxes(means2d.detach(), cov_a.detach(), cov_c.detach(), opacities.detach(), width, height)
    visible = in_front & on_screen
    return Projected(means2d, conics, cam[:, 2], opacities, bboxes, visible)


def _screen_boxes(
    means2d: torch.Tensor, var_x: torch.Tensor, var_y: torch.Tensor, opacities: torch.Tensor, width: int, height: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixel ranges whose centres can see the Gaussian at alpha >= 1/255, and whether any exist.

    The ellipse sigma <= r^2 / 2 has half-extent r * sqrt(var) along each axis. One pixel of
    margin on each side absorbs float rounding; the compositor's per-pixel alpha test decides.
    """
    bright = opacities >= ALPHA_MIN
    reach = torch.sqrt(2.0 * torch.log(torch.clamp(opacities, min=ALPHA_MIN) / ALPHA_MIN))
    half_x, half_y = reach * torch.sqrt(var_x), reach * torch.sqrt(var_y)
    limit = float(2 * max(width, height))  # keeps huge boxes inside int32
    x0 = torch.floor(torch.clamp(means2d[:, 0] - half_x - 0.5, -limit, limit))
    x1 = torch.ceil(torch.clamp(means2d[:, 0] + half_x - 0.5, -limit, limit)) + 1
    y0 = torch.floor(torch.clamp(means2d[:, 1] - half_y - 0.5, -limit, limit))
    y1 = torch.ceil(torch.clamp(means2d[:, 1] + half_y - 0.5, -limit, limit)) + 1
    box = torch.stack(
        [x0.clamp(0, width), x1.clamp(0, width), y0.clamp(0, height), y1.clamp(0, height)], dim=-1
    ).to(torch.int32)
    on_screen = bright & (box[:, 0] < box[:, 1]) & (box[:, 2] < box[:, 3])
    return box, on_screen

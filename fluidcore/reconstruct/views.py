"""The images a reconstruction is fitted to: real input views and pseudo-views.

A `ViewTarget` is a camera plus one target image per frame, a background and a loss weight.
Real views come from the input videos. One view leaves depth open, so pseudo-views add
constraints from other directions; the slot is generic (`kind`, `weight`, frames) so that the
generative novel-view model of a later stage plugs in as more ViewTargets of kind "generated".

Until then, `symmetry_views` gives the plume-symmetry prior: the input camera rotated about
the vertical axis through the source, with the input frame itself as its target (at a lower
weight). A plume rising from a round source is roughly axisymmetric, so this asks for a 3D
density that looks the same from every azimuth, instead of a flat billboard that only
explains the input view. It uses nothing but the input view and the estimated source.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from fluidcore.cameras import Camera, rotate_about_axis
from fluidcore.metrics import ssim_tensor


@dataclass(frozen=True)
class ViewTarget:
    """One camera to fit: `frames[k]` is the target of the k-th frame of the run's range."""

    camera: Camera  # at the working (finest) resolution of `frames`
    frames: torch.Tensor  # (T, H, W, C) float32 in [0, 1]
    background: torch.Tensor  # (H, W, C) or (C,)
    noise: torch.Tensor  # (C,) the video's noise per channel (images.Background.noise): the smoke mask's unit
    weight: float = 1.0
    kind: str = "input"  # "input" | "symmetry" | "generated"

    def at(self, index: int, size: tuple[int, int]) -> tuple[Camera, torch.Tensor, torch.Tensor]:
        """Camera, target image and background for frame `index` at size (W, H)."""
        width, height = size
        image = resize(self.frames[index], width, height)
        background = self.background if self.background.ndim == 1 else resize(self.background, width, height)
        return self.camera.scaled(width, height), image, background


def resize(image: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """(H, W, C) image to (height, width, C), antialiased (a coarse level is a blurred fine one)."""
    if image.shape[0] == height and image.shape[1] == width:
        return image
    out = F.interpolate(image.permute(2, 0, 1)[None], size=(height, width), mode="bilinear", antialias=True, align_corners=False)
    return out[0].permute(1, 2, 0)


def symmetry_views(
    inputs: Sequence[ViewTarget], center: np.ndarray, up: np.ndarray, count: int, weight: float
) -> list[ViewTarget]:
    """`count` pseudo-views per input view, evenly spread in azimuth (the input's own excluded),
    each reusing the input's frames, background and noise as its target."""
    views = []
    for view in inputs:
        for i in range(1, count + 1):
            angle = 2.0 * math.pi * i / (count + 1)
            camera = rotate_about_axis(view.camera, center, up, angle, f"{view.camera.name}~sym{i}")
            views.append(ViewTarget(camera, view.frames, view.background, view.noise, weight=weight, kind="symmetry"))
    return views


def generated_targets(
    source: ViewTarget, targets: Sequence[Camera], frames: Mapping[str, torch.Tensor], weight: float
) -> list[ViewTarget]:
    """Views the novel-view model drew from `source` (`fluidcore.generative.stages`, (T, H, W, C)
    per camera name) as fitting targets of kind "generated": `weight` split evenly, and the input's
    background colour (its background image belongs to the input camera's viewpoint) and noise (the
    model draws in the input's colours; the source estimate masks its smoke in those units)."""
    background = source.background
    if background.ndim > 1:
        background = background.reshape(-1, background.shape[-1]).median(dim=0).values
    per_view = weight / max(len(targets), 1)
    return [
        ViewTarget(camera, frames[camera.name].to(source.frames.device), background, source.noise, weight=per_view, kind="generated")
        for camera in targets
    ]


MIRROR_OFF, MIRROR_FULL = 0.3, 0.6  # mirror agreement at which the symmetry prior is off / at full weight


def symmetry_support(agreement: float) -> float:
    """The fraction of the symmetry prior's weight a plume with this `mirror_agreement` gets:
    0 up to MIRROR_OFF, 1 from MIRROR_FULL on, linear between. Measured agreements: 0.68 for the
    dev plume, 0.65 for ScalarFlow, 0.93 for the synthetic one (full weight), 0.32 for the dev
    plume bent by its side wind, frames 75..149 (nearly off)."""
    return float(np.clip((agreement - MIRROR_OFF) / (MIRROR_FULL - MIRROR_OFF), 0.0, 1.0))


def mirror_agreement(view: ViewTarget, center: np.ndarray, up: np.ndarray) -> float:
    """How much the view's smoke looks like its own mirror image about the plume's axis: the
    mean over frames with smoke of IoU(mask, mask mirrored about the image line through the
    source along up); masks are `fluidcore.reconstruct.images.smoke_mask`.

    An axisymmetric plume projects to a mirror-symmetric image from any side, so a low score
    says the symmetry prior is wrong for this plume (a high one cannot prove it right: one view
    never sees the depth). It scales the symmetry pseudo-views' weight (fluidcore.reconstruct.loop).
    """
    from fluidcore.reconstruct.images import smoke_mask
    from fluidcore.reconstruct.rays import image_up

    camera = view.camera
    (origin,), _ = camera.project_numpy(np.asarray(center, dtype=np.float64)[None])
    axis = image_up(camera, np.asarray(center, dtype=np.float64), np.asarray(up, dtype=np.float64))
    height, width = view.frames.shape[1:3]
    v, u = np.mgrid[0:height, 0:width] + 0.5
    offset = np.stack([u - origin[0], v - origin[1]], axis=-1)
    along = offset @ axis
    mirrored = origin + 2.0 * along[..., None] * axis - offset  # reflection of (u, v) across the axis line
    mu, mv = np.floor(mirrored[..., 0]).astype(np.int64), np.floor(mirrored[..., 1]).astype(np.int64)
    inside = (mu >= 0) & (mv >= 0) & (mu < width) & (mv < height)
    masks = smoke_mask(view.frames, view.background, view.noise)
    scores = []
    for mask in masks:
        if not mask.any():
            continue
        reflected = np.zeros_like(mask)
        reflected[inside] = mask[mv[inside], mu[inside]]
        union = (mask | reflected).sum()
        scores.append((mask & reflected).sum() / union)
    return float(np.mean(scores)) if scores else 0.0


def image_loss(
    pred: torch.Tensor, target: torch.Tensor, background: torch.Tensor, l1_weight: float, dssim_weight: float
) -> torch.Tensor:
    """The release's photometric loss: l1_weight * L1 + dssim_weight * (1 - SSIM).

    L1 covers the whole image; SSIM only the box around what differs from the background in
    either image (plus a margin of one SSIM window). Elsewhere both images are background and
    SSIM is 1 with zero gradient, so the crop changes the loss by a constant factor only and
    saves most of the cost on frames where smoke fills a small part of the view.
    """
    loss = l1_weight * (pred - target).abs().mean()
    if dssim_weight <= 0:
        return loss
    rows, cols = _content_box(pred.detach(), target, background, margin=SSIM_WINDOW)
    if rows.stop - rows.start > SSIM_WINDOW and cols.stop - cols.start > SSIM_WINDOW:
        loss = loss + dssim_weight * (1.0 - ssim_tensor(pred[rows, cols], target[rows, cols]))
    return loss


SSIM_WINDOW = 11
# Not a smoke mask: the SSIM crop must hold every pixel where SSIM is not 1 (either image off the
# background at all, the render included), or the crop would change the loss by more than a
# constant; one 8-bit step is the least difference an input can show.
CONTENT_THRESHOLD = 1.0 / 255.0


def _content_box(pred: torch.Tensor, target: torch.Tensor, background: torch.Tensor, margin: int) -> tuple[slice, slice]:
    """Row and column slices around the pixels where pred or target differ from the background."""
    differs = ((pred - background).abs() > CONTENT_THRESHOLD) | ((target - background).abs() > CONTENT_THRESHOLD)
    mask = differs.any(dim=-1)
    rows = torch.nonzero(mask.any(dim=1)).flatten()
    cols = torch.nonzero(mask.any(dim=0)).flatten()
    if len(rows) == 0:
        return slice(0, 0), slice(0, 0)
    height, width = mask.shape
    return (
        slice(max(int(rows[0]) - margin, 0), min(int(rows[-1]) + 1 + margin, height)),
        slice(max(int(cols[0]) - margin, 0), min(int(cols[-1]) + 1 + margin, width)),
    )

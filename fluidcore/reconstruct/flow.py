"""Optical flow of the input video: an observation of the smoke's projected velocity.

The image loss only sees where smoke is; two consecutive frames also say how it moved. Dense
optical flow (OpenCV's DIS) between frames k and k+1 of the input view gives, at every pixel
the smoke covers, the image-plane displacement of what that ray sees, in pixels per frame at
the working resolution. It is computed once, before frame 0, and asked per particle:

    FlowField       flow (T-1, H, W, 2) from frame k to k+1 and a confidence (T-1, H, W) in
                    [0, 1]: 1 where frame k shows smoke and the forward and backward flows
                    agree (a displacement that the backward flow does not undo is an
                    occlusion, a textureless patch or noise), 0 elsewhere;
    FlowObservation one frame's loss term for the position fit: how far each particle's
                    image-plane displacement from t-1 to t falls short of the flow sampled
                    where it was at t-1 (the flow is a lower bound, see there), weighted by
                    the confidence there, in world units at the particle's depth and in
                    kernel radii squared (like L_sim).

Flow is computed on the smoke's contrast (`images.smoke_contrast`, |frame - background| in units of
the video's noise) rather than on the frames, so a textured background (which does not move)
cannot pull the flow towards zero.

What flow cannot see: motion along the view ray (depth) changes nothing in the image, so the
term constrains the two image-plane components of u_t only; the depth component stays what the
simulator and the image loss make it. A ray through several layers of smoke sees their blend,
so the flow is a projection, weighted towards the densest smoke, not the velocity of every
particle on the ray.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from fluidcore.cameras import Camera
from fluidcore.reconstruct.images import is_smoke, smoke_contrast

CONTRAST_PERCENTILE = 99.5  # the smoke contrast mapped to 8-bit white (robust to a few hot pixels)
FB_RELATIVE = 0.01  # forward-backward check (Sundaram et al. 2010): |f + b|^2 <= FB_RELATIVE (|f|^2 + |b|^2) + FB_ABSOLUTE
FB_ABSOLUTE = 0.5  # px^2


@dataclass(frozen=True)
class FlowField:
    """Dense flow of one view's consecutive frames (see the module docstring)."""

    camera: Camera  # at the flow's resolution
    flow: torch.Tensor  # (T-1, H, W, 2) float32, pixels per frame from frame k to k+1 (u right, v down)
    confidence: torch.Tensor  # (T-1, H, W) float32 in [0, 1]

    def sample(self, k: int, uv: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Flow (N, 2) and confidence (N,) of the pair (k, k+1) at continuous pixels uv (N, 2),
        bilinear; outside the image the confidence is 0."""
        height, width = self.confidence.shape[1:]
        grid = torch.stack((2.0 * uv[:, 0] / width - 1.0, 2.0 * uv[:, 1] / height - 1.0), -1).to(self.flow.dtype)
        maps = torch.cat((self.flow[k].permute(2, 0, 1), self.confidence[k][None]))[None]
        values = F.grid_sample(maps, grid[None, :, None], mode="bilinear", padding_mode="zeros", align_corners=False)
        values = values[0, :, :, 0].T  # (N, 3)
        return values[:, :2], values[:, 2]


def contrast_images(contrast: np.ndarray) -> np.ndarray:
    """uint8 (T, H, W) of the smoke's contrast (T, H, W) (`images.smoke_contrast`), its
    CONTRAST_PERCENTILE over the video mapped to 255."""
    top = max(float(np.percentile(contrast, CONTRAST_PERCENTILE)), 1e-6)
    return np.clip(contrast * (255.0 / top), 0, 255).astype(np.uint8)


def _dis(first: np.ndarray, second: np.ndarray) -> np.ndarray:
    import cv2

    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    return dis.calc(first, second, None)


def _warp(image: np.ndarray, flow: np.ndarray) -> np.ndarray:
    """`image` (H, W, C) sampled at x + flow(x) (bilinear, edge-clamped)."""
    import cv2

    h, w = flow.shape[:2]
    cols, rows = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    return cv2.remap(image, cols + flow[..., 0], rows + flow[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def consistent(forward: np.ndarray, backward: np.ndarray) -> np.ndarray:
    """(H, W) bool: the backward flow, read where the forward flow lands, undoes it."""
    back = _warp(backward, forward)
    error = np.square(forward + back).sum(-1)
    return error <= FB_RELATIVE * (np.square(forward).sum(-1) + np.square(back).sum(-1)) + FB_ABSOLUTE


def input_flow(camera: Camera, frames: torch.Tensor, background: torch.Tensor, noise: torch.Tensor) -> FlowField:
    """DIS flow between consecutive `frames` ((T, H, W, C) float in [0, 1], `camera` at their
    resolution, `background` (H, W, C) or (C,), the video's `noise` (C,)), with the confidence of
    the module docstring; a pixel is smoke where `fluidcore.reconstruct.images.smoke_mask` says so."""
    contrast = smoke_contrast(frames, background, noise)
    images, smoke = contrast_images(contrast), is_smoke(contrast)
    flows, confidences = [], []
    for k in range(len(images) - 1):
        forward = _dis(images[k], images[k + 1])
        backward = _dis(images[k + 1], images[k])
        flows.append(forward)
        confidences.append(smoke[k] & consistent(forward, backward))
    device = frames.device
    height, width = images.shape[1:]
    flow = torch.from_numpy(np.stack(flows)) if flows else torch.zeros((0, height, width, 2))
    confidence = torch.from_numpy(np.stack(confidences).astype(np.float32)) if confidences else torch.zeros((0, height, width))
    return FlowField(camera, flow.float().to(device), confidence.to(device))


class FlowObservation:
    """The flow term of one frame's position fit (see the module docstring).

    Flow is a lower bound on the smoke's motion, not the motion itself: it tracks the smoke's
    pattern, and the fluid keeps flowing through a pattern that changes slowly (right above a
    steady source the image hardly changes while the inflow rises through it). Where the
    pattern moves, the fluid moves at least as fast along the flow; where it stands still,
    the fluid may still flow through. The term therefore only penalises a particle whose displacement along the
    flow's direction falls short of the flow's length, never one that moves faster, and says
    nothing across the flow: a zero flow asks nothing.

    Displacements are compared in the camera's image plane at the particle's depth (the
    projection linearised about p_{t-1}): the component along the view ray is not in the term
    at all, so the flow cannot push a particle in depth. The particles' positions at t-1 are
    fixed during the fit, so what they sample from the flow is computed once per frame.
    """

    def __init__(self, field: FlowField, pair: int, p_prev: torch.Tensor, kernel_radius: float) -> None:
        """`pair` k: the flow from frame k to k+1 observes the particles moving from p_prev (at
        frame k) to p_t (frame k+1)."""
        camera = field.camera
        uv_prev, depth = camera.project(p_prev)
        flow, confidence = field.sample(pair, uv_prev)
        focal = torch.tensor([camera.fx, camera.fy], dtype=p_prev.dtype, device=p_prev.device)
        target = flow.to(p_prev.dtype) * depth.clamp_min(1e-6)[:, None] / focal  # world units in the image plane
        self.p_prev = p_prev
        self.weight = confidence * (depth > 0)
        self.length = target.norm(dim=-1)
        self.direction = target / self.length.clamp_min(1e-12)[:, None]
        self.image_axes = torch.tensor(camera.world_to_camera[:2, :3], dtype=p_prev.dtype, device=p_prev.device)
        self.kernel_radius = kernel_radius

    def __call__(self, p: torch.Tensor) -> torch.Tensor:
        """mean over particles of confidence x (how far the image-plane displacement along the
        flow falls short of the flow, world units at the particle's depth)^2 / h^2."""
        along = ((p - self.p_prev) @ self.image_axes.T * self.direction).sum(-1)
        shortfall = (self.length - along).clamp_min(0.0) / self.kernel_radius
        return (self.weight * shortfall.pow(2)).mean()

"""fluidcore.render internals: gradients (gradcheck on the torch reference, fused kernel against
the reference), memory-bounded batching, tile binning against brute force, and the projection
against gsplat's own pure-torch projection."""

from __future__ import annotations

import math
from contextlib import contextmanager
from collections.abc import Iterator

import numpy as np
import pytest
import torch

from fluidcore.cameras import Camera
from fluidcore.render import Gaussians, render
from fluidcore.render.projection import EPS2D, covariance_3d, project
from fluidcore.render.rasterize import _tile_batches, composite_fused, composite_reference, fused_available
from fluidcore.render.tiles import bin_gaussians

PARAMETERS = ("means", "log_scales", "quats", "opacity_logits", "colors")


def _camera(width: int, height: int, focal: float) -> Camera:
    """Slightly rotated and shifted so that no matrix entry is a special value."""
    angle = 0.1
    pose = np.eye(4)
    pose[:3, :3] = [[math.cos(angle), 0, math.sin(angle)], [0, 1, 0], [-math.sin(angle), 0, math.cos(angle)]]
    pose[:3, 3] = [0.05, -0.02, 0.1]
    return Camera("test", focal, focal * 1.05, width / 2 + 0.3, height / 2 - 0.2, width, height, pose)


def _cloud(
    n: int, channels: int, seed: int, dtype=torch.float32, spread: float = 0.5, scale: float = 0.06
) -> Gaussians:
    gen = torch.Generator().manual_seed(seed)
    g = Gaussians(
        means=torch.randn(n, 3, generator=gen, dtype=torch.float64) * spread + torch.tensor([0.0, 0.0, 3.0], dtype=torch.float64),
        log_scales=math.log(scale) + 0.4 * torch.randn(n, 3, generator=gen, dtype=torch.float64),
        quats=torch.randn(n, 4, generator=gen, dtype=torch.float64),
        opacity_logits=torch.randn(n, generator=gen, dtype=torch.float64),
        colors=torch.rand(n, channels, generator=gen, dtype=torch.float64),
    )
    return Gaussians(*(getattr(g, name).to(dtype).requires_grad_(True) for name in PARAMETERS))


@contextmanager
def _threads(n: int) -> Iterator[None]:
    before = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def _loss_and_grads(g: Gaussians, camera: Camera, backend: str, weights: torch.Tensor):
    """A loss that uses image, alpha and depth with pixel-varying weights, and its gradients."""
    out = render(g, camera, background=0.2, backend=backend)
    loss = (out.image * weights[..., : g.channels]).sum() + (out.alpha**2).sum() + 0.1 * (out.depth * out.alpha).sum()
    return out, torch.autograd.grad(loss, [getattr(g, name) for name in PARAMETERS])


# --- gradients -------------------------------------------------------------------------------------
def test_reference_gradients_pass_gradcheck_in_float64() -> None:
    """Every Gaussian parameter and the background, through image, alpha and depth.

    The outputs are reduced by fixed random weights to three scalars, which checks the full
    vector-Jacobian product at the cost of three backward passes instead of one per pixel.
    """
    camera = _camera(20, 18, 14.0)
    g = _cloud(4, 3, seed=7, dtype=torch.float64, spread=0.8, scale=0.4)
    background = torch.tensor([0.3, 0.6, 0.1], dtype=torch.float64, requires_grad=True)
    gen = torch.Generator().manual_seed(1)
    w_image, w_alpha, w_depth = (torch.rand(18, 20, k, generator=gen, dtype=torch.float64) for k in (3, 1, 1))
    reference_out = render(g, camera, background, backend="torch-reference")
    assert reference_out.alpha.max() > 0.5 and (reference_out.alpha > 0).sum() > 100  # the case is not empty

    def reduced(means, log_scales, quats, opacity_logits, colors, bg):
        out = render(Gaussians(means, log_scales, quats, opacity_logits, colors), camera, bg, backend="torch-reference")
        return torch.stack([
            (out.image * w_image).sum(), (out.alpha * w_alpha[..., 0]).sum(), (out.depth * w_depth[..., 0]).sum()
        ])  # fmt: skip

    inputs = tuple(getattr(g, name) for name in PARAMETERS) + (background,)
    assert torch.autograd.gradcheck(reduced, inputs, eps=1e-6, atol=1e-5, rtol=1e-4)


@pytest.mark.parametrize("channels", [1, 3])
@pytest.mark.parametrize("threads", [1, 2])
def test_fused_kernel_matches_reference(channels: int, threads: int) -> None:
    camera = _camera(72, 56, 45.0)
    g = _cloud(400, channels, seed=channels)
    weights = torch.rand(56, 72, 3, generator=torch.Generator().manual_seed(2))
    with _threads(threads):
        fused_out, fused_grads = _loss_and_grads(g, camera, "torch", weights)
    reference_out, reference_grads = _loss_and_grads(g, camera, "torch-reference", weights)
    assert reference_out.alpha.max() > 0.9 and (reference_out.alpha < 0.01).any()  # opaque and empty parts
    for name in ("image", "alpha", "depth"):
        torch.testing.assert_close(getattr(fused_out, name), getattr(reference_out, name), atol=2e-5, rtol=1e-5)
    for name, fused, reference in zip(PARAMETERS, fused_grads, reference_grads):
        scale = reference.abs().max().item()
        assert scale > 0, name
        torch.testing.assert_close(fused, reference, atol=1e-4 * scale, rtol=1e-3, msg=name)


def test_fused_kernel_backward_without_alpha_gradient() -> None:
    """Autograd hands the kernel no transmittance gradient when only colours reach the loss."""
    camera = _camera(40, 32, 30.0)
    g = _cloud(100, 3, seed=5)
    projected = project(g.means, covariance_3d(g.scales(), g.unit_quats()), g.opacities(), camera.viewmat(), camera.intrinsics(), 40, 32)
    bins = bin_gaussians(projected.bboxes, projected.depths, projected.visible, 40, 32)
    assert fused_available(g.colors)
    fused, _ = composite_fused(projected, g.colors, bins)
    reference, _ = composite_reference(projected, g.colors, bins)
    grad_fused = torch.autograd.grad(fused.sum(), g.colors)[0]
    grad_reference = torch.autograd.grad(reference.sum(), g.colors)[0]
    torch.testing.assert_close(grad_fused, grad_reference, atol=1e-5, rtol=1e-4)


# --- memory-bounded reference ------------------------------------------------------------------------
def test_reference_batching_does_not_change_the_picture() -> None:
    camera = _camera(64, 48, 40.0)
    g = _cloud(300, 1, seed=11)
    projected = project(g.means, covariance_3d(g.scales(), g.unit_quats()), g.opacities(), camera.viewmat(), camera.intrinsics(), 64, 48)
    bins = bin_gaussians(projected.bboxes, projected.depths, projected.visible, 64, 48)
    one_batch, t_one = composite_reference(projected, g.colors, bins, batch_elements=1 << 30)
    many_batches, t_many = composite_reference(projected, g.colors, bins, batch_elements=256 * 64)
    torch.testing.assert_close(one_batch, many_batches, atol=1e-6, rtol=0)
    torch.testing.assert_close(t_one, t_many, atol=1e-6, rtol=0)


def test_tile_batches_respect_the_budget_and_cover_every_tile() -> None:
    counts = [0, 3, 9, 1, 0, 0, 40, 2, 2, 5]
    batches = list(_tile_batches(counts, max_padded=12))
    assert [first for first, _, _ in batches][0] == 0 and batches[-1][1] == len(counts)
    for (first, last, longest), (next_first, _, _) in zip(batches, batches[1:] + [(len(counts), 0, 0)]):
        assert last == next_first
        assert longest == max(counts[first:last])
        assert (last - first) * max(longest, 1) <= 12 or last - first == 1  # a lone long tile may exceed it


# --- tile binning ------------------------------------------------------------------------------------
def test_bins_list_every_overlapping_gaussian_front_to_back() -> None:
    gen = torch.Generator().manual_seed(4)
    n, width, height = 60, 70, 50
    x0 = torch.randint(-10, 70, (n,), generator=gen)
    y0 = torch.randint(-10, 50, (n,), generator=gen)
    boxes = torch.stack([x0, x0 + torch.randint(1, 30, (n,), generator=gen), y0, y0 + torch.randint(1, 30, (n,), generator=gen)], 1)
    boxes[:, :2] = boxes[:, :2].clamp(0, width)
    boxes[:, 2:] = boxes[:, 2:].clamp(0, height)
    visible = (boxes[:, 0] < boxes[:, 1]) & (boxes[:, 2] < boxes[:, 3]) & (torch.rand(n, generator=gen) > 0.2)
    depths = torch.rand(n, generator=gen)
    bins = bin_gaussians(boxes.to(torch.int32), depths, visible, width, height)

    assert (bins.tiles_x, bins.tiles_y) == (5, 4)
    for tile in range(bins.n_tiles):
        tx, ty = tile % bins.tiles_x, tile // bins.tiles_x
        expected = [
            i for i in range(n)
            if visible[i] and boxes[i, 0] < (tx + 1) * 16 and boxes[i, 1] > tx * 16
            and boxes[i, 2] < (ty + 1) * 16 and boxes[i, 3] > ty * 16
        ]  # fmt: skip
        expected.sort(key=lambda i: depths[i].item())
        listed = bins.ids[bins.offsets[tile] : bins.offsets[tile + 1]].tolist()
        assert listed == expected, f"tile {tile}"


# --- projection conventions ---------------------------------------------------------------------------
def test_projection_matches_gsplats_pure_torch_projection() -> None:
    """gsplat's private torch reference of its CUDA projection (gsplat is pinned to 1.5.3)."""
    from gsplat.cuda._torch_impl import _fully_fused_projection

    camera = _camera(90, 60, 50.0)
    g = _cloud(200, 3, seed=9, spread=1.0)
    covariances = covariance_3d(g.scales(), g.unit_quats())
    ours = project(g.means, covariances, g.opacities(), camera.viewmat(), camera.intrinsics(), 90, 60)
    _, means2d, depths, conics, _ = _fully_fused_projection(
        g.means, covariances, camera.viewmat()[None], camera.intrinsics()[None], 90, 60, eps2d=EPS2D
    )
    shown = ours.visible
    assert shown.sum() > 100
    torch.testing.assert_close(ours.means2d[shown], means2d[0][shown], atol=1e-4, rtol=1e-5)
    torch.testing.assert_close(ours.depths[shown], depths[0][shown])
    torch.testing.assert_close(ours.conics[shown], conics[0][shown], atol=1e-5, rtol=1e-4)

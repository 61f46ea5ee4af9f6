"""fluidcore.render through its public function: closed-form pictures, compositing rules,
backgrounds, culling, input validation, and the ScalarFlow cameras (the issue's done-when check)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from fluidcore import cameras
from fluidcore.cameras import Camera, box_center, scene_box
from fluidcore.render import Gaussians, RenderError, render

CPU_BACKENDS = ("torch", "torch-reference")
FOCAL = 60.0


def _camera(width: int = 64, height: int = 48) -> Camera:
    """At the origin looking down +z; the optical axis hits the centre of pixel (32, 24)."""
    return Camera("test", FOCAL, FOCAL, 32.5, 24.5, width, height, np.eye(4))


def _gaussians(
    means: list[list[float]], scale: float, opacity: float, colors: list[list[float]], dtype=torch.float32
) -> Gaussians:
    """Isotropic Gaussians with one scale and one peak opacity."""
    n = len(means)
    return Gaussians(
        means=torch.tensor(means, dtype=dtype),
        log_scales=torch.full((n, 3), math.log(scale), dtype=dtype),
        quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]] * n, dtype=dtype),
        opacity_logits=torch.full((n,), math.log(opacity / (1 - opacity)), dtype=dtype),
        colors=torch.tensor(colors, dtype=dtype),
    )


def _random_cloud(n: int, channels: int, seed: int = 0) -> Gaussians:
    gen = torch.Generator().manual_seed(seed)
    return Gaussians(
        means=torch.randn(n, 3, generator=gen) * torch.tensor([0.6, 0.4, 0.3]) + torch.tensor([0.0, 0.0, 3.0]),
        log_scales=math.log(0.05) + 0.4 * torch.randn(n, 3, generator=gen),
        quats=torch.randn(n, 4, generator=gen),
        opacity_logits=torch.randn(n, generator=gen),
        colors=torch.rand(n, channels, generator=gen),
    )


# --- closed-form cases ----------------------------------------------------------------------------
@pytest.mark.parametrize("backend", CPU_BACKENDS)
def test_single_gaussian_is_the_projected_ewa_footprint(backend: str) -> None:
    depth, scale, opacity, colour, bg = 2.0, 0.04, 0.8, 0.7, 0.1
    g = _gaussians([[0.0, 0.0, depth]], scale, opacity, [[colour]])
    out = render(g, _camera(), background=bg, backend=backend)

    variance = (FOCAL * scale / depth) ** 2 + 0.3  # pixels^2, including the 0.3 px^2 blur
    rows, cols = torch.meshgrid(torch.arange(48.0), torch.arange(64.0), indexing="ij")
    distance2 = (cols + 0.5 - 32.5) ** 2 + (rows + 0.5 - 24.5) ** 2
    alpha = opacity * torch.exp(-0.5 * distance2 / variance)
    alpha = torch.where(alpha >= 1 / 255, alpha, torch.zeros_like(alpha))

    torch.testing.assert_close(out.alpha, alpha, atol=2e-6, rtol=0)
    torch.testing.assert_close(out.image[..., 0], colour * alpha + bg * (1 - alpha), atol=2e-6, rtol=0)
    torch.testing.assert_close(out.depth, torch.where(alpha > 0, depth, 0.0), atol=1e-5, rtol=0)


@pytest.mark.parametrize("backend", CPU_BACKENDS)
def test_nearer_gaussian_is_composited_first(backend: str) -> None:
    near, far = 2.0, 3.0
    a_near, a_far = 0.6, 0.5
    g = _gaussians([[0.0, 0.0, far], [0.0, 0.0, near]], 0.2, 0.5, [[0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
    g.opacity_logits = torch.tensor([math.log(a_far / (1 - a_far)), math.log(a_near / (1 - a_near))])
    out = render(g, _camera(), backend=backend)
    centre = (24, 32)  # both Gaussians peak here: alpha equals the opacity

    expected = torch.tensor([a_near, a_far * (1 - a_near), 0.0])
    torch.testing.assert_close(out.image[centre], expected, atol=1e-6, rtol=0)
    coverage = 1 - (1 - a_near) * (1 - a_far)
    torch.testing.assert_close(out.alpha[centre], torch.tensor(coverage), atol=1e-6, rtol=0)
    depth = (near * a_near + far * a_far * (1 - a_near)) / coverage
    torch.testing.assert_close(out.depth[centre], torch.tensor(depth), atol=1e-5, rtol=0)


@pytest.mark.parametrize("backend", CPU_BACKENDS)
def test_an_opaque_pixel_ignores_what_lies_behind(backend: str) -> None:
    """Alpha is capped at 0.999; a second opaque layer would take T to 1e-6 < 1e-4, so it is skipped."""
    g = _gaussians([[0.0, 0.0, 2.0], [0.0, 0.0, 3.0]], 0.2, 0.99999, [[0.2], [1.0]])
    out = render(g, _camera(), background=0.5, backend=backend)
    assert out.image[24, 32, 0].item() == pytest.approx(0.999 * 0.2 + 0.001 * 0.5, abs=1e-6)
    assert out.depth[24, 32].item() == pytest.approx(2.0, abs=1e-5)


@pytest.mark.parametrize("backend", CPU_BACKENDS)
def test_capped_alpha_passes_no_gradient_to_opacity_or_shape(backend: str) -> None:
    """At its centre pixel this Gaussian's alpha is capped at 0.999, so it is flat there."""
    g = _gaussians([[0.0, 0.0, 2.0]], 1e-3, 0.999999, [[1.0]])
    for tensor in (g.means, g.log_scales, g.opacity_logits, g.colors):
        tensor.requires_grad_(True)
    out = render(g, _camera(), background=0.5, backend=backend)
    assert out.alpha[24, 32].item() == pytest.approx(0.999, abs=1e-6)
    out.image[24, 32, 0].backward()
    assert g.opacity_logits.grad.item() == 0 and torch.all(g.means.grad == 0) and torch.all(g.log_scales.grad == 0)
    assert g.colors.grad.item() == pytest.approx(0.999, abs=1e-6)


@pytest.mark.parametrize("backend", CPU_BACKENDS)
def test_grey_path_equals_rgb_with_equal_channels(backend: str) -> None:
    grey = _random_cloud(300, 1, seed=3)
    rgb = Gaussians(grey.means, grey.log_scales, grey.quats, grey.opacity_logits, grey.colors.expand(-1, 3).clone())
    out_grey = render(grey, _camera(), background=0.25, backend=backend)
    out_rgb = render(rgb, _camera(), background=0.25, backend=backend)
    assert out_grey.image.shape == (48, 64, 1)
    assert out_grey.alpha.max() > 0.5
    for c in range(3):
        torch.testing.assert_close(out_rgb.image[..., c], out_grey.image[..., 0], atol=1e-6, rtol=0)
    torch.testing.assert_close(out_rgb.alpha, out_grey.alpha)


@pytest.mark.parametrize("channels", [1, 3])
@pytest.mark.parametrize("backend", CPU_BACKENDS)
def test_skipping_depth_changes_neither_picture_nor_gradients(backend: str, channels: int) -> None:
    """depth=False drops one composited channel; what is drawn, and what an image loss
    sends back to every Gaussian parameter, stays the same."""
    results = []
    for depth in (True, False):
        g = _random_cloud(300, channels, seed=4)
        params = [t.requires_grad_(True) for t in (g.means, g.log_scales, g.quats, g.opacity_logits, g.colors)]
        out = render(g, _camera(), background=0.25, backend=backend, depth=depth)
        (out.image.square().sum() + out.alpha.sum()).backward()
        results.append((out, [p.grad for p in params]))
    (with_depth, grads_with), (without, grads_without) = results
    assert with_depth.depth is not None and without.depth is None
    assert with_depth.alpha.max() > 0.5
    torch.testing.assert_close(without.image, with_depth.image, atol=1e-6, rtol=0)
    torch.testing.assert_close(without.alpha, with_depth.alpha, atol=1e-6, rtol=0)
    for a, b in zip(grads_without, grads_with):
        assert bool(a.abs().sum() > 0)
        torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-4)


def test_auto_backend_on_cpu_is_the_torch_backend() -> None:
    g = _random_cloud(200, 3)
    auto, explicit = render(g, _camera()), render(g, _camera(), backend="torch")
    assert torch.equal(auto.image, explicit.image)


# --- backgrounds ----------------------------------------------------------------------------------
def test_background_colour_image_and_gradient() -> None:
    g = _random_cloud(200, 3, seed=1)
    colour = torch.tensor([0.1, 0.5, 0.9])
    image = torch.rand(48, 64, 3, requires_grad=True)
    on_colour = render(g, _camera(), background=colour)
    on_image = render(g, _camera(), background=image)
    alpha = on_colour.alpha[..., None]
    foreground = on_colour.image - (1 - alpha) * colour
    torch.testing.assert_close(on_image.image, foreground + (1 - alpha) * image, atol=1e-6, rtol=0)
    on_image.image.sum().backward()
    torch.testing.assert_close(image.grad, (1 - alpha).expand(-1, -1, 3).detach())


@pytest.mark.parametrize("background", [torch.zeros(2), torch.zeros(48, 64, 1), torch.tensor([float("nan")] * 3), "black"])
def test_bad_background_is_rejected(background: object) -> None:
    with pytest.raises(RenderError, match="background"):
        render(_random_cloud(10, 3), _camera(), background=background)  # type: ignore[arg-type]


# --- culling and degenerate Gaussians ---------------------------------------------------------------
@pytest.mark.parametrize("backend", CPU_BACKENDS)
@pytest.mark.parametrize("z", [-1.0, 0.0, 0.005])
def test_gaussians_at_or_behind_the_near_plane_are_not_drawn(z: float, backend: str) -> None:
    """Nothing visible: the background comes back, and backward still runs (zero gradients)."""
    g = _gaussians([[0.0, 0.0, z]], 0.1, 0.9, [[1.0]])
    for tensor in (g.means, g.log_scales, g.quats, g.opacity_logits, g.colors):
        tensor.requires_grad_(True)
    out = render(g, _camera(), background=0.3, backend=backend)
    assert torch.all(out.image == 0.3) and torch.all(out.alpha == 0)
    out.image.sum().backward()
    assert torch.isfinite(g.means.grad).all() and torch.all(g.means.grad == 0)


def test_zero_scale_gaussian_still_covers_a_pixel() -> None:
    """exp(-200) underflows to a zero scale; the 0.3 px^2 blur keeps the conic finite."""
    g = _gaussians([[0.0, 0.0, 2.0]], 1.0, 0.9, [[1.0]])
    g.log_scales = torch.full((1, 3), -200.0, requires_grad=True)
    g.means.requires_grad_(True)
    out = render(g, _camera())
    assert out.alpha[24, 32].item() == pytest.approx(0.9, abs=1e-6)
    out.image.sum().backward()
    assert torch.isfinite(g.means.grad).all() and torch.isfinite(g.log_scales.grad).all()


def _broken(field: str) -> Gaussians:
    g = _random_cloud(5, 3)
    if field == "means":
        g.means[2, 1] = float("nan")
    elif field == "opacity_logits":
        g.opacity_logits[0] = float("inf")
    elif field == "quats":
        g.quats[4] = 0.0
    elif field == "colors":
        g.colors = torch.rand(5, 2)
    elif field == "log_scales":
        g.log_scales = torch.zeros(4, 3)
    return g


@pytest.mark.parametrize("field", ["means", "opacity_logits", "quats", "colors", "log_scales"])
def test_invalid_gaussians_name_the_field(field: str) -> None:
    with pytest.raises(RenderError, match=field):
        render(_broken(field), _camera())


def test_mixed_dtypes_are_rejected() -> None:
    g = _random_cloud(5, 1)
    g.colors = g.colors.double()
    with pytest.raises(RenderError, match="colors"):
        render(g, _camera())


def test_unknown_backend_and_gsplat_without_cuda_are_rejected() -> None:
    g = _random_cloud(5, 3)
    with pytest.raises(RenderError, match="backend"):
        render(g, _camera(), backend="opengl")
    with pytest.raises(RenderError, match="CUDA"):
        render(g, _camera(), backend="gsplat")


# --- the ScalarFlow cameras -----------------------------------------------------------------------
def test_blob_at_scalarflow_box_centre_appears_in_every_view(realdata: Path) -> None:
    path = realdata / "scalarflow" / "transforms.json"
    loaded = cameras.load(path)
    box = scene_box(path)
    assert box is not None and len(loaded) == 5
    centre = box_center(box)
    size = 0.05 * float(np.min(box[1] - box[0]))
    g = _gaussians([centre.tolist()], size, 0.95, [[1.0]])
    for name, full in loaded.items():
        camera = full.scaled(full.width // 4, full.height // 4)
        out = render(g, camera)
        uv, depth = camera.project(torch.tensor(centre[None], dtype=torch.float64))
        u, v = uv[0].tolist()
        assert depth.item() > 0 and 0 <= u < camera.width and 0 <= v < camera.height, name

        alpha = out.alpha.double()
        assert alpha.max() > 0.9, name
        border = torch.cat([alpha[0], alpha[-1], alpha[:, 0], alpha[:, -1]])
        assert torch.all(border == 0), f"{name}: the blob is cut by the frame"
        rows, cols = torch.meshgrid(
            torch.arange(camera.height, dtype=torch.float64), torch.arange(camera.width, dtype=torch.float64), indexing="ij"
        )
        centroid_u = ((cols + 0.5) * alpha).sum() / alpha.sum()
        centroid_v = ((rows + 0.5) * alpha).sum() / alpha.sum()
        assert abs(centroid_u.item() - u) < 1.0 and abs(centroid_v.item() - v) < 1.0, name

"""Optical flow of the input view (fluidcore.reconstruct.flow) and its term in the position fit.

* a textured blob translated by a known shift: DIS recovers the shift where the blob is (the
  median over confident pixels within 0.25 px: DIS is sub-pixel on textured patches) and the
  confidence is 0 on the empty background;
* the loss: particles that moved against the flow are pushed along it (gradient descent on
  the term alone brings their projected displacement along the flow up to the flow's length),
  never along the view ray; particles faster than the flow, anywhere the flow is zero, or
  where the confidence is 0 feel nothing (the flow is a lower bound on the smoke's motion);
* with the weight at 0 no flow is computed and the fit has no flow term (the path before the
  term existed); with it on, the term is fitted and its weight is in the manifest; a manifest
  without the weight (runs from before it) reads back.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy import ndimage

from fluidcore.cameras import Camera, look_at
from fluidcore.reconstruct import Reconstructor, prepare, read_inputs
from fluidcore.reconstruct.flow import FlowField, FlowObservation, input_flow
from fluidcore.reconstruct.images import NOISE_FLOOR
from fluidcore.spec.reconstruct import ReconstructConfig, get
from fluidcore import synth

SHIFT = (3.0, -2.0)  # px per frame (u right, v down)
BACKGROUND = 0.1


def _blob_frames(frames: int = 3, width: int = 96, height: int = 64) -> torch.Tensor:
    """A smoke-like blob (Gaussian envelope times a smoothed random texture) moving by SHIFT."""
    rng = np.random.default_rng(0)
    texture = ndimage.gaussian_filter(rng.random((height * 2, width * 2)), 2.0)
    texture = (texture - texture.min()) / np.ptp(texture)
    rows, cols = np.mgrid[0:height, 0:width]
    out = []
    for k in range(frames):
        dx, dy = SHIFT[0] * k, SHIFT[1] * k
        envelope = np.exp(-(((cols - 40 - dx) / 14.0) ** 2 + ((rows - 34 - dy) / 12.0) ** 2))
        moved = ndimage.shift(texture, (dy, dx), order=3, mode="wrap")[height // 2 : height // 2 + height, width // 2 : width // 2 + width]
        smoke = envelope * (0.4 + 0.6 * moved)
        out.append(BACKGROUND + 0.8 * smoke)
    return torch.from_numpy(np.stack(out).astype(np.float32))[..., None].expand(-1, -1, -1, 3).contiguous()


def _camera(width: int = 96, height: int = 64) -> Camera:
    like = Camera("c", 80.0, 80.0, width / 2, height / 2, width, height, np.eye(4))
    return look_at((0.0, 0.5, 2.0), (0.0, 0.5, 0.0), (0.0, 1.0, 0.0), like, "c")


def test_flow_recovers_a_known_shift():
    frames = _blob_frames()
    field = input_flow(_camera(), frames, torch.full((3,), BACKGROUND), torch.full((3,), NOISE_FLOOR))
    assert field.flow.shape == (2, 64, 96, 2) and field.confidence.shape == (2, 64, 96)
    for k in range(2):
        confident = field.confidence[k] > 0.5
        assert confident.sum() > 300, "the blob's core must be confident"
        median = field.flow[k][confident].median(dim=0).values.numpy()
        np.testing.assert_allclose(median, SHIFT, atol=0.25)
        assert float(field.confidence[k][:, 85:].max()) == 0.0  # background, far from the blob


def _uniform_field(camera: Camera, flow: tuple[float, float], confidence: float) -> FlowField:
    shape = (1, camera.height, camera.width)
    return FlowField(camera, torch.tensor(flow).expand(*shape, 2).contiguous(), torch.full(shape, confidence))


def test_particles_moving_against_the_flow_are_pushed_along_it():
    camera = _camera()
    field = _uniform_field(camera, SHIFT, 1.0)
    p_prev = torch.tensor([[0.0, 0.5, 0.0], [0.05, 0.45, 0.1], [-0.1, 0.55, -0.1]], dtype=torch.float64)
    uv_prev, _ = camera.project(p_prev)
    wrong = p_prev + torch.tensor([-0.02, 0.0, 0.0], dtype=torch.float64)  # left, the flow goes right and up
    observation = FlowObservation(field, 0, p_prev, 0.05)
    p = wrong.clone().requires_grad_(True)
    observation(p).backward()
    moved_uv, _ = camera.project(p.detach() - 1e-3 * p.grad)
    before_uv, _ = camera.project(wrong)
    assert bool(((moved_uv - before_uv)[:, 0] > 0).all()), "a descent step moves them towards the flow (right)"
    along_ray = p.grad @ torch.tensor(camera.world_to_camera[2, :3])
    np.testing.assert_allclose(along_ray.numpy(), 0.0, atol=1e-12)  # flow says nothing about depth
    optimiser = torch.optim.Adam([p], lr=1e-3)
    for _ in range(400):
        optimiser.zero_grad()
        observation(p).backward()
        optimiser.step()
    uv, _ = camera.project(p.detach())
    direction = torch.tensor(SHIFT, dtype=torch.float64) / np.hypot(*SHIFT)
    along = (uv - uv_prev) @ direction
    assert bool((along > np.hypot(*SHIFT) - 0.1).all()), f"they now keep up with the flow: {along}"


def test_the_flow_is_a_lower_bound():
    """Faster than the flow along it, or any motion where the flow is zero: no pull."""
    camera = _camera()
    p_prev = torch.tensor([[0.0, 0.5, 0.0]], dtype=torch.float64)
    right = torch.tensor([[0.05, 0.0, 0.0]], dtype=torch.float64)  # ~2 px right: faster than a 1 px flow
    for flow, moved in (((1.0, 0.0), p_prev + right), ((0.0, 0.0), p_prev - right), ((0.0, 0.0), p_prev + right)):
        p = moved.clone().requires_grad_(True)
        loss = FlowObservation(_uniform_field(camera, flow, 1.0), 0, p_prev, 0.05)(p)
        loss.backward()
        assert float(loss.detach()) == 0.0 and float(p.grad.abs().max()) == 0.0, flow


def test_no_confidence_no_pull():
    camera = _camera()
    p_prev = torch.tensor([[0.0, 0.5, 0.0]], dtype=torch.float64)
    p = (p_prev - 0.01).requires_grad_(True)
    loss = FlowObservation(_uniform_field(camera, SHIFT, 0.0), 0, p_prev, 0.05)(p)
    loss.backward()
    assert float(loss.detach()) == 0.0 and float(p.grad.abs().max()) == 0.0
    outside = torch.tensor([[5.0, 0.5, 0.0]], dtype=torch.float64)  # projects far outside the image
    assert float(FlowObservation(_uniform_field(camera, SHIFT, 1.0), 0, outside, 0.05).weight[0]) == 0.0


@pytest.fixture(scope="module")
def scene() -> synth.SynthScene:
    return synth.generate(synth.SynthSpec(frames=3, width=48, height=64, views=3, fps=10.0))


def _tiny(scene: synth.SynthScene, flow: float):
    spec = scene.spec
    quality = get("preview").with_overrides(long_side=64, particles_per_frame=spec.particles_per_step, position_iterations=4,
                                            appearance_iterations=2, first_frame_factor=1)
    quality = quality.with_overrides(weights={"flow": flow})
    box = spec.box()
    inputs = read_inputs(scene.cameras, {"view_01": scene.videos["view_01"]}, frame_range=(0, 3), quality=quality)
    return prepare(scene.cameras, inputs, fps=spec.fps, quality=quality, box=(np.array(box.lo), np.array(box.hi)))


def test_flow_weight_zero_is_the_path_without_flow(scene, tmp_path):
    off = _tiny(scene, 0.0)
    assert off.flow is None
    run = Reconstructor(off).run(tmp_path / "off")
    assert all("flow" not in entry["losses"] for entry in run.manifest["frames"])
    on = _tiny(scene, 1.0)
    assert on.flow is not None and on.flow.flow.shape[0] == 2
    run_on = Reconstructor(on).run(tmp_path / "on")
    assert "flow" in run_on.manifest["frames"][-1]["losses"]
    assert run_on.manifest["settings"]["quality"]["weights"]["flow"] == 1.0


def test_runs_from_before_the_flow_term_refit_without_it():
    manifest = get("preview").model_dump(mode="json")
    del manifest["weights"]["flow"]
    assert ReconstructConfig.model_validate(manifest).weights.flow == 0.0

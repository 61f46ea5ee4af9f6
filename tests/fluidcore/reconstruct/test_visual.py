"""The visual layer's ties to the physics (fluidcore.reconstruct.visual).

The image loss here is a stand-in that rewards exactly what a free per-Gaussian fit would do to
paint one view: some Gaussians pulled to needles or sheets, each Gaussian towards its own
colour. The tied fit must keep every scale within its bounds and one colour for all.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from fluidcore.cameras import Camera
from fluidcore.physics import Box, ParticleState, PBFConfig, Source
from fluidcore.predict.rollout import Rollout
from fluidcore.reconstruct.visual import OpacityTie, ScaleBounds, fit_appearance
from fluidcore.render import Gaussians, render
from fluidcore.smoke import Appearance, SmokeState, concentration
from fluidcore.spec.reconstruct import LossWeights, PresetError, ReconstructConfig, VisualSettings, get, quality_fields
from tests.support.simulators import paper

RATES = {"color": 0.05, "scale": 0.2, "opacity": 0.05, "rotation": 0.01}


def _appearance(n: int, scale: float, generator: torch.Generator) -> Appearance:
    return Appearance(
        log_scales=torch.full((n, 3), math.log(scale)),
        quats=torch.tensor([1.0, 0.0, 0.0, 0.0]).repeat(n, 1),
        opacity_logits=torch.zeros(n),
        colors=torch.rand((n, 3), generator=generator),
    )


def test_scales_stay_in_bounds_and_the_colour_is_shared():
    g = torch.Generator().manual_seed(0)
    n = 12
    pull = torch.where(torch.arange(n)[:, None] % 2 == 0, 1.0, -1.0).repeat(1, 3)  # half grow, half shrink
    wanted = torch.rand((n, 3), generator=g)  # a different colour for every Gaussian

    def painter(gaussians: Gaussians, k: int) -> torch.Tensor:
        return -(pull * gaussians.log_scales).mean() + (gaussians.colors - wanted).pow(2).mean()

    bounds = ScaleBounds(0.005, 0.02)
    start = _appearance(n, 0.01, g)
    first_frame = start.select(torch.zeros(n, dtype=torch.bool))  # nothing to regularise towards
    fitted, loss = fit_appearance(torch.zeros((n, 3)), start, first_frame, painter, 300, RATES, LossWeights(), bounds, OpacityTie(None))

    scales = fitted.log_scales.exp()
    assert math.isfinite(loss)
    assert float(scales.min()) >= bounds.low * (1 - 1e-5) and float(scales.max()) <= bounds.high * (1 + 1e-5)
    assert float(scales[0::2].min()) > 0.9 * bounds.high  # the pull did act, up to the bound
    assert float(scales[1::2].max()) < 1.1 * bounds.low
    assert torch.allclose(fitted.colors, fitted.colors[:1].expand(n, -1))
    assert torch.allclose(fitted.colors[0], wanted.mean(0), atol=0.05)  # the one colour that fits them all best


def test_scale_bounds_round_trip_and_refuse_an_empty_range():
    bounds = ScaleBounds(0.5, 2.0)
    inside = torch.log(torch.tensor([[0.6, 1.0, 1.9]]))
    assert torch.allclose(bounds.log_scales(bounds.free(inside)), inside, atol=1e-5)
    outside = torch.log(torch.tensor([[0.01, 100.0, 1.0]]))
    assert bool((bounds.log_scales(bounds.free(outside)).exp() <= 2.0).all())
    with pytest.raises(ValueError):
        ScaleBounds(1.0, 1.0)


@pytest.mark.parametrize("spread", [0.0, 0.5])
def test_opacities_stay_within_the_spread_of_the_shared_one(spread):
    g = torch.Generator().manual_seed(1)
    n = 10
    wanted = torch.linspace(-4.0, 4.0, n)  # a painter wants every opacity different

    def painter(gaussians: Gaussians, k: int) -> torch.Tensor:
        return (gaussians.opacity_logits - wanted).pow(2).mean()

    start = _appearance(n, 0.01, g)
    first_frame = start.select(torch.zeros(n, dtype=torch.bool))
    tie = OpacityTie(spread)
    fitted, _ = fit_appearance(torch.zeros((n, 3)), start, first_frame, painter, 200, RATES, LossWeights(),
                               ScaleBounds(0.005, 0.02), tie)
    logits = fitted.opacity_logits
    assert float(logits.max() - logits.min()) <= 2 * spread + 1e-5
    if spread > 0:
        assert float(logits.max() - logits.min()) > spread  # the deviations were used, up to the tie


def test_the_ties_are_quality_fields_that_round_trip_and_take_partial_weight_overrides():
    quality = get("preview").with_overrides(opacity_spread=None, weights={"scale": 8.0})
    assert quality.weights.scale == 8.0 and quality.weights.opacity == LossWeights().opacity
    assert ReconstructConfig.model_validate(json.loads(json.dumps(quality.model_dump(mode="json"), allow_nan=False))) == quality
    with pytest.raises(PresetError, match="weights.colour"):
        get("preview").with_overrides(weights={"colour": 1.0})


# -- opacity that follows the smoke's concentration (issue 23, item 5) -------------------------

H = 0.02  # kernel radius of the small clouds below
CONFIG = PBFConfig(h=H, alpha=0.0, drag=0.0)  # no gravity, buoyancy or drag: only the motion given moves them


def _cloud(n: int, spread: float, seed: int = 0) -> torch.Tensor:
    return torch.randn((n, 3), generator=torch.Generator().manual_seed(seed)) * spread


def _one_gaussian(opacity: float) -> Appearance:
    return Appearance(torch.full((1, 3), math.log(0.5 * H)), torch.tensor([[1.0, 0.0, 0.0, 0.0]]),
                      torch.logit(torch.tensor([opacity])), torch.zeros((1, 1)))


def _expanding_rollout(opacity_concentration: bool) -> tuple[SmokeState, SmokeState]:
    """A cloud of smoke particles flying apart (the source seeds nothing) with one visual
    Gaussian at its centre: the start and the state 10 frames later."""
    positions = _cloud(300, H)
    state = ParticleState.from_positions(positions, 0.5 * positions / H)  # each moves away from the centre
    simulator = paper(CONFIG, Box((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0)), Source((0.0, -0.9, 0.0), 0.01, rate=0))
    one = _one_gaussian(0.6)
    rollout = Rollout(simulator, one.select(torch.zeros(0, dtype=torch.long)), velocity_radius=2 * H, per_physical=0,
                      seed=0, opacity_concentration=opacity_concentration)
    start = SmokeState(state.clone(), torch.zeros((1, 3)), one)
    smoke = SmokeState(state, torch.zeros((1, 3)), one)
    for index in range(10):
        smoke, _ = rollout.advance(smoke, index, index + 1)
    return start, smoke


def _darkness(appearance: Appearance, means: torch.Tensor) -> float:
    """How much a black Gaussian darkens the white background at its centre's pixel."""
    pose = np.eye(4)
    pose[2, 3] = 0.5  # the Gaussian 0.5 in front of the camera
    camera = Camera("test", 200.0, 200.0, 16.0, 16.0, 32, 32, pose)
    image = render(appearance.gaussians(means), camera, torch.ones(1), depth=False).image
    return 1.0 - float(image[16, 16, 0])


def _live(smoke: SmokeState) -> torch.Tensor:
    return smoke.particles.positions[smoke.particles.alive]


def test_a_gaussian_whose_particles_spread_out_renders_lighter():
    start, diluted = _expanding_rollout(opacity_concentration=True)
    _, frozen = _expanding_rollout(opacity_concentration=False)
    before = concentration(start.means, _live(start), 2 * H, CONFIG)
    after = concentration(diluted.means, _live(diluted), 2 * H, CONFIG)
    assert float(after) < 0.5 * float(before)  # the cloud did spread around the Gaussian
    assert torch.equal(frozen.appearance.opacity_logits, start.appearance.opacity_logits)  # off: as before
    # a parcel of fixed mass: extent x (before / after)^(1/3), optical depth x (after / before)^(2/3)
    ratio = float(after / before)
    expected = 1.0 - (1.0 - 0.6) ** (ratio ** (2.0 / 3.0))
    assert float(torch.sigmoid(diluted.appearance.opacity_logits)) == pytest.approx(expected, rel=1e-3)
    grown = diluted.appearance.log_scales - start.appearance.log_scales
    assert torch.allclose(grown, torch.full_like(grown, -math.log(ratio) / 3.0), atol=1e-4)
    assert _darkness(diluted.appearance, diluted.means) < 0.8 * _darkness(start.appearance, start.means)


def test_concentration_is_one_at_the_rest_density_and_falls_as_particles_spread():
    # particles on a cubic lattice at the rest number density 8 rho0 / h^3
    spacing = H / (8.0 * CONFIG.rho0) ** (1.0 / 3.0)
    axis = torch.arange(-12, 13, dtype=torch.float32) * spacing
    lattice = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    centre = torch.zeros((1, 3))
    assert float(concentration(centre, lattice, 2 * H, CONFIG)) == pytest.approx(1.0, rel=0.05)
    assert float(concentration(centre, 2.0 * lattice, 2 * H, CONFIG)) == pytest.approx(1.0 / 8.0, rel=0.1)
    alone = concentration(torch.tensor([[5.0, 5.0, 5.0]]), lattice, 2 * H, CONFIG)  # no particle within reach
    assert math.isfinite(float(alone)) and 0.0 < float(alone) < 0.05


@pytest.mark.parametrize("ratio", [0.0, 1e-30, 1e-3, 1.0, 1e3, 1e30, float("inf")])
def test_diluted_opacity_stays_in_0_1_and_finite(ratio):
    logits = torch.tensor([-30.0, -5.0, 0.0, 5.0, 30.0])
    n = len(logits)
    appearance = Appearance(torch.zeros((n, 3)), torch.zeros((n, 4)), logits, torch.zeros((n, 1)))
    diluted = appearance.diluted(torch.ones(n), torch.full((n,), ratio))
    out = diluted.opacity_logits
    opacity = torch.sigmoid(out)
    assert bool(torch.isfinite(out).all()) and bool(torch.isfinite(diluted.log_scales).all())
    assert bool((opacity > 0).all()) and bool((opacity < 1).all())
    if 1e-3 <= ratio <= 1e3:  # within the clamps, the order of the opacities is kept
        assert bool((out[1:] >= out[:-1]).all())


def test_runs_recorded_before_the_concentration_tie_load_and_continue_without_it():
    old = {"velocity_radius": 2.0, "per_physical": 1, "seed": 0}  # what a prediction reads of its parent
    assert VisualSettings.model_validate(old).opacity_concentration is False
    recorded = get("preview").model_dump(mode="json")
    del recorded["visual"]["opacity_concentration"]
    assert ReconstructConfig.model_validate(quality_fields(recorded)).name == "preview"  # an older quality record still loads
    for flag in (True, False):
        quality = get("preview").with_overrides(opacity_concentration=flag)
        assert quality.visual_settings().opacity_concentration is flag

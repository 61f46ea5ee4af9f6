"""The visual layer's ties to the physics (fluidcore.reconstruct.visual).

The image loss here is a stand-in that rewards exactly what a free per-Gaussian fit would do to
paint one view: some Gaussians pulled to needles or sheets, each Gaussian towards its own
colour. The tied fit must keep every scale within its bounds and one colour for all.
"""

from __future__ import annotations

import json
import math

import pytest
import torch

from fluidcore.reconstruct.presets import LossWeights, PresetError, Quality, get
from fluidcore.reconstruct.visual import OpacityTie, ScaleBounds, fit_appearance
from fluidcore.render import Gaussians
from fluidcore.smoke import Appearance

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
    assert Quality.from_json(json.loads(json.dumps(quality.to_json(), allow_nan=False))) == quality
    with pytest.raises(PresetError, match="loss weights"):
        get("preview").with_overrides(weights={"colour": 1.0})

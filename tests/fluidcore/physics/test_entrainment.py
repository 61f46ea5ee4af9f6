"""fluidcore.physics.entrainment: a plume's spreading by the air it entrains (MTT's db/dz)."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from fluidcore.physics import PRESETS, Box, PBFConfig, PhysicsInputError, Source
from fluidcore.physics.entrainment import spread
from tests.support.simulators import paper, run

CFG = replace(PRESETS["scalarflow"], h=0.02)


def column(n: int = 4000, radius: float = 0.02, height: float = 0.4, seed: int = 0) -> torch.Tensor:
    """Particles spread in a vertical column of Gaussian cross-section (rms radius `radius`)."""
    g = torch.Generator().manual_seed(seed)
    across = torch.randn(n, 2, generator=g) * radius / 2**0.5
    up = torch.rand(n, generator=g) * height
    return torch.stack([across[:, 0] + 0.3, up, across[:, 1] - 0.2], dim=1)


def rms_radius(points: torch.Tensor) -> float:
    across = points[:, [0, 2]]
    return float(((across - across.mean(0)) ** 2).sum(1).mean().sqrt())


def test_a_rising_column_widens_by_the_rate_per_unit_of_height_risen() -> None:
    """MTT: db/dz = rate, so after rising dz the rms radius has grown by rate x dz."""
    rate, w = 0.12, 0.3
    config = replace(CFG, entrainment=rate)
    x = column()
    v = torch.zeros_like(x)
    v[:, 1] = w
    before = rms_radius(x)
    for _ in range(30):  # one second: the column rises 0.3 (the displacement here is the spread only)
        x = spread(x, v, config)
    assert rms_radius(x) - before == pytest.approx(rate * w * 1.0, rel=0.05)


def test_the_spread_keeps_each_slabs_centre_and_height() -> None:
    config = replace(CFG, entrainment=0.12)
    x = column()
    v = torch.zeros_like(x)
    v[:, 1] = 0.3
    moved = spread(x, v, config)
    assert torch.equal(moved[:, 1], x[:, 1])  # only across, never along up
    slab = ((x[:, 1] - x[:, 1].min()) / config.h).long()  # the slabs start at the lowest particle
    for k in (0, 5, 10):
        inside = slab == k
        assert torch.allclose(moved[inside][:, [0, 2]].mean(0), x[inside][:, [0, 2]].mean(0), atol=1e-6)


def test_nothing_spreads_when_off_sinking_or_alone() -> None:
    x = column(n=500)
    v = torch.zeros_like(x)
    v[:, 1] = 0.3
    assert torch.equal(spread(x, v, CFG), x)  # entrainment 0: the paper's model
    on = replace(CFG, entrainment=0.12)
    assert torch.equal(spread(x, -v, on), x)  # smoke that sinks does not rise into new air
    assert torch.equal(spread(x[:1], v[:1], on), x[:1])


def test_spread_is_differentiable_and_finite_for_coincident_particles() -> None:
    config = replace(CFG, entrainment=0.12)
    x = torch.full((50, 3), 0.1, requires_grad=True)  # all in one point: size 0
    v = torch.zeros(50, 3)
    v[:, 1] = 0.3
    out = spread(x, v, config)
    assert bool(torch.isfinite(out).all())
    out.sum().backward()
    assert x.grad is not None and bool(torch.isfinite(x.grad).all())


def test_a_simulated_plume_is_wider_high_up_with_entrainment() -> None:
    box = Box((0.0, 0.0, -0.4), (0.6, 0.8, 0.0))
    source = Source((0.3, 0.06, -0.2), 0.03, 20, (0.0, 0.12, 0.0))
    widths = {}
    for rate in (0.0, 0.12):
        sim = paper(replace(CFG, alpha=-3.6, entrainment=rate), box, source)
        state, _ = run(sim, sim.new_state(), 90)
        p = state.positions[state.alive]
        high = p[p[:, 1] > 0.35]
        assert len(high) > 100
        widths[rate] = rms_radius(high)
    assert widths[0.12] > 1.3 * widths[0.0]


def test_a_negative_rate_is_refused_by_name() -> None:
    with pytest.raises(PhysicsInputError, match="entrainment"):
        PBFConfig(entrainment=-0.1)

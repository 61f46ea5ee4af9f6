"""fluidcore.physics: units, neighbour search, solver, forces, coupling, seeding, gradients, and
agreement of the fused C++ path with the torch reference."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch

from fluidcore.spec.controls import WindParams
from fluidcore.physics import (
    PRESETS,
    Box,
    Controls,
    NeighbourCache,
    ParticleState,
    PBFConfig,
    PhysicsInputError,
    Simulator,
    Source,
    Sphere,
    density,
    density_residual,
    incompressibility_loss,
    interpolate_velocity,
    sim_step,
    wind_force,
)
from fluidcore.physics import coupling, forces, fused
from fluidcore.physics import step as step_module
from fluidcore.physics.neighbours import cell_table, neighbours_torch
from fluidcore.physics.solver import residual, solve_torch
from fluidcore.physics.source import emit, from_y
from tests.support.simulators import paper, run

needs_fused = pytest.mark.skipif(not fused.available(), reason="fused PBF kernel cannot be built here")
CFG = PRESETS["scalarflow"]


def lattice(n_side: int, spacing: float, origin: float = 0.0) -> torch.Tensor:
    axis = torch.arange(n_side, dtype=torch.float32) * spacing + origin
    return torch.cartesian_prod(axis, axis, axis)


def random_block(n: int, density_per_h3: float, h: float, seed: int = 0) -> torch.Tensor:
    side = (n / density_per_h3) ** (1 / 3) * h
    return torch.rand(n, 3, generator=torch.Generator().manual_seed(seed)) * side


def brute_force_pairs(p: torch.Tensor, h: float) -> set[tuple[int, int]]:
    d = torch.cdist(p.double(), p.double())
    i, j = torch.nonzero((d < h) & ~torch.eye(len(p), dtype=torch.bool), as_tuple=True)
    return set(zip(i.tolist(), j.tolist()))


def list_pairs(nl) -> set[tuple[int, int]]:
    i, j = nl.pairs()
    return set(zip(i.tolist(), j.tolist()))


# -- units ---------------------------------------------------------------------------------

@pytest.mark.parametrize("h", [0.02, 1.0])
def test_density_is_one_for_a_lattice_of_spacing_half_h(h: float) -> None:
    p = lattice(9, h / 2)
    centre = int(torch.argmin(((p - p.mean(0)) ** 2).sum(1)))
    assert density(p, h)[centre].item() == pytest.approx(1.0, abs=0.05)


def test_presets_follow_the_paper() -> None:
    assert (CFG.alpha, CFG.rho0, CFG.dt, CFG.drag, CFG.iterations) == (-3.0, 2.0, 1 / 30, 3.0, 10)
    for name in ("fluidnexus_smoke", "fluidnexus_ball"):
        assert (PRESETS[name].alpha, PRESETS[name].rho0) == (-6.0, 1.5)
    # buoyancy points up, scaled from the release's units (x100) to world units
    assert CFG.body_acceleration[1] == pytest.approx(3.0 * 9.8 / 100.0)


# -- neighbours ----------------------------------------------------------------------------

@pytest.mark.parametrize("builder", ["torch", pytest.param("fused", marks=needs_fused)])
def test_neighbour_list_matches_brute_force(builder: str) -> None:
    h = 0.05
    p = torch.cat([random_block(400, 20.0, h), lattice(4, h, origin=0.3), torch.zeros(5, 3)])
    nl = neighbours_torch(p, h) if builder == "torch" else fused.neighbours_fused(p, h)
    assert list_pairs(nl) == brute_force_pairs(p, h)
    i, _ = nl.pairs()
    assert bool((i[1:] >= i[:-1]).all()), "rows must be grouped by particle"


def test_grid_holds_occupied_cells_only() -> None:
    p = torch.tensor([[0.0, 0.0, 0.0], [1.0e4, 0.0, 0.0], [1.0e4, 0.001, 0.0]])
    table = cell_table(p, 0.02)
    assert table.keys.shape[0] == 2  # two occupied cells, not the 5e5 cells between them


def test_unused_features_cost_nothing(monkeypatch: pytest.MonkeyPatch) -> None:
    def forbidden(*args, **kwargs):
        raise AssertionError("a feature the scene does not use was evaluated")

    for module, name in ((coupling, "push_out"), (coupling, "slide"), (forces, "xsph"),
                         (forces, "vorticity_confinement")):
        monkeypatch.setattr(module, name, forbidden)
    monkeypatch.setattr(step_module, "external_force", forbidden)
    sim = plume_simulator("auto")
    assert sim.step(sim.new_state())[1].n_alive > 0


# -- solver --------------------------------------------------------------------------------

def compressed_block(n: int = 1500) -> torch.Tensor:
    return random_block(n, 8 * CFG.rho0 * 1.6, CFG.h)


def test_residual_falls_monotonically_with_iterations() -> None:
    p = compressed_block()
    nl = neighbours_torch(p, CFG.h)
    errors = [float(residual(solve_torch(p, nl, replace(CFG, iterations=k)).density, CFG.rho0).mean())
              for k in (0, 1, 2, 5, 10, 20)]
    assert errors[0] > 0.2
    assert all(b < a for a, b in zip(errors, errors[1:])), errors


def test_tolerance_stops_early_and_calm_needs_fewer_iterations() -> None:
    tol = replace(CFG, tolerance=0.01, max_iterations=40)
    calm = random_block(1500, 8 * CFG.rho0 * 1.05, CFG.h)
    violent = compressed_block()
    used = {}
    for name, p in (("calm", calm), ("violent", violent)):
        solution = solve_torch(p, neighbours_torch(p, CFG.h), tol)
        used[name] = solution.iterations
        if solution.iterations < tol.max_iterations:
            assert float(residual(solution.density, CFG.rho0).mean()) < 0.01
    assert 0 < used["calm"] < used["violent"] <= 40


@needs_fused
@pytest.mark.parametrize("config", [CFG, replace(CFG, s_corr_k=0.1), replace(CFG, tolerance=0.02)])
def test_fused_solver_agrees_with_torch(config: PBFConfig) -> None:
    p = compressed_block()
    nl = neighbours_torch(p, config.h)
    reference = solve_torch(p, nl, config)
    fast = fused.solve_fused(p, fused.neighbours_fused(p, config.h), config)
    assert fast.iterations == reference.iterations
    torch.testing.assert_close(fast.positions, reference.positions, atol=1e-5 * config.h, rtol=0)
    torch.testing.assert_close(fast.density, reference.density, atol=1e-4, rtol=1e-4)


def plume_simulator(backend: str, **kw) -> Simulator:
    source = Source((0.1, 0.02, 0.1), 0.03, 60, (0.0, 0.05, 0.0), seed=3)
    return paper(CFG, Box((0, 0, 0), (0.2, 0.3, 0.2)), source, backend=backend, **kw)


@needs_fused
def test_fused_and_torch_simulators_agree() -> None:
    states, stats = [], []
    for backend in ("torch", "fused"):
        sim = plume_simulator(backend)
        state, steps = run(sim, sim.new_state(), 8)
        stats.append(steps)
        states.append(state)
    assert torch.equal(states[0].alive, states[1].alive)
    # float rounding differs (summation order), and eight steps of fresh, overlapping seeds amplify it
    torch.testing.assert_close(states[0].positions, states[1].positions, atol=1e-3 * CFG.h, rtol=0)
    assert [s.iterations for s in stats[0]] == [s.iterations for s in stats[1]]
    assert stats[0][-1].mean_density_error == pytest.approx(stats[1][-1].mean_density_error, abs=1e-4)


# -- forces ---------------------------------------------------------------------------------

def test_lone_particle_rises_with_buoyancy_and_drag() -> None:
    x, v = torch.tensor([[0.0, 0.0, 0.0]]), torch.zeros(1, 3)
    p, u = sim_step(x, v, CFG)
    a = CFG.body_acceleration[1]
    lone_density = 315 / (512 * math.pi)  # W(0): only the particle itself
    expected = a * CFG.dt * math.exp(-CFG.drag * CFG.dt * (1 - lone_density / CFG.rho0))
    assert u[0, 1].item() == pytest.approx(expected, rel=1e-4)
    assert p[0, 1].item() == pytest.approx(a * CFG.dt**2, rel=1e-4)
    assert u[0, 0].item() == 0.0 and u[0, 2].item() == 0.0


def test_drag_relaxes_towards_the_environment_velocity() -> None:
    config = replace(CFG, alpha=0.0, env_velocity=(0.1, 0.0, 0.0))
    x, v = torch.zeros(1, 3), torch.zeros(1, 3)
    for _ in range(200):
        x, v = sim_step(x, v, config)
    assert v[0, 0].item() == pytest.approx(0.1, rel=1e-3)


def test_wind_force_grows_with_height_inside_its_window() -> None:
    params = WindParams(direction=(2.0, 0.0, 0.0), strength=0.5, growth=3.0)
    wind = wind_force(params, blowing=lambda time: 1.0 <= time < 2.0, base_height=0.1)
    p = torch.tensor([[0.0, 0.1, 0.0], [0.0, 0.6, 0.0]])
    assert torch.equal(wind(p, 0.5), torch.zeros(2, 3))
    assert torch.equal(wind(p, 2.0), torch.zeros(2, 3))
    f = wind(p, 1.5)
    assert f[0].tolist() == pytest.approx([0.5, 0.0, 0.0])
    assert f[1, 0].item() == pytest.approx(0.5 * math.exp(1.5), rel=1e-5)


def test_wind_pushes_the_smoke() -> None:
    x, v = random_block(200, 8.0, CFG.h), torch.zeros(200, 3)
    pushed, _ = sim_step(x, v, CFG, force=wind_force(WindParams(direction=(1, 0, 0), strength=1.0), lambda time: True))
    calm, _ = sim_step(x, v, CFG)
    assert bool((pushed[:, 0] > calm[:, 0]).all())


def test_xsph_smooths_the_velocity_field() -> None:
    config = replace(CFG, alpha=0.0, drag=0.0)
    x = random_block(800, 8.0, CFG.h)
    v = 0.05 * torch.randn(800, 3, generator=torch.Generator().manual_seed(2))
    _, plain = sim_step(x, v, config)
    _, smooth = sim_step(x, v, replace(config, xsph=0.5))
    assert float(smooth.var(0).sum()) < 0.9 * float(plain.var(0).sum())


def test_vorticity_confinement_strengthens_a_swirl() -> None:
    config = replace(CFG, alpha=0.0, drag=0.0)
    x = random_block(800, 8.0, CFG.h)
    r = x - x.mean(0)
    v = torch.stack([-r[:, 2], torch.zeros(800), r[:, 0]], dim=1)  # rigid rotation about y

    def spin(u: torch.Tensor) -> float:
        return float((r[:, 0] * u[:, 2] - r[:, 2] * u[:, 0]).sum())
    _, plain = sim_step(x, v, config)
    _, confined = sim_step(x, v, replace(config, vorticity=5.0))
    assert spin(confined) > spin(plain) > 0


def test_interpolated_velocity_reproduces_a_uniform_flow() -> None:
    p = random_block(500, 10.0, CFG.h)
    u = torch.tensor([0.3, -0.1, 0.2]).expand(500, 3)
    query = torch.cat([p[:20] + 0.001, torch.full((1, 3), 10.0)])
    field = interpolate_velocity(query, p, u, CFG.h)
    torch.testing.assert_close(field[:20], u[:20])
    assert field[20].tolist() == [0.0, 0.0, 0.0]


@needs_fused
def test_fused_interpolation_agrees_with_torch() -> None:
    h = 2 * CFG.h
    p = torch.cat([random_block(3000, 10.0, CFG.h), torch.full((2, 3), 5.0)])
    u = torch.randn(p.shape[0], 3, generator=torch.Generator().manual_seed(4))
    side = float(p[:3000].max())
    g = torch.Generator().manual_seed(5)
    query = torch.cat([torch.rand(700, 3, generator=g) * (side + 2 * h) - h,  # inside, on the edges and beyond
                       p[:50], torch.tensor([[5.0 + 0.5 * h, 5.0, 5.0], [-1.0e5, 3.0, 0.0]])])
    reference = interpolate_velocity(query, p, u, h, backend="torch")
    fast = interpolate_velocity(query, p, u, h, backend="fused")
    torch.testing.assert_close(fast, reference, atol=1e-5, rtol=1e-4)
    assert fast[-1].tolist() == [0.0, 0.0, 0.0] and bool((fast[-2] != 0).any())
    assert int((reference.abs().sum(1) == 0).sum()) > 0  # some queries had no particle within h


@needs_fused
def test_interpolation_uses_the_fused_kernel_only_without_gradients(monkeypatch: pytest.MonkeyPatch) -> None:
    calls = []
    original = fused.interpolate_fused
    monkeypatch.setattr(fused, "interpolate_fused", lambda *a: calls.append(1) or original(*a))
    p = random_block(300, 10.0, CFG.h)
    u = torch.randn(300, 3, generator=torch.Generator().manual_seed(6)).requires_grad_(True)
    field = interpolate_velocity(p[:40], p, u, CFG.h)
    assert calls == [] and field.requires_grad
    field.sum().backward()
    assert u.grad is not None and float(u.grad.abs().sum()) > 0
    with torch.no_grad():
        again = interpolate_velocity(p[:40], p, u, CFG.h)
    assert calls == [1]
    torch.testing.assert_close(again, field.detach(), atol=1e-5, rtol=1e-4)


# -- coupling, seeding, open domain ------------------------------------------------------

def test_sphere_pushes_particles_to_its_surface_and_removes_normal_velocity() -> None:
    sphere = Sphere((0.0, 0.0, 0.0), 0.05)
    state = ParticleState.from_positions(torch.tensor([[0.04, 0.0, 0.0], [0.0, 0.2, 0.0]]),
                                         torch.tensor([[0.0, 0.2, 0.0], [0.0, 0.0, 0.0]]))
    sim = paper(replace(CFG, alpha=0.0, drag=0.0), Box((-1, -1, -1), (1, 1, 1)))
    state, stats = sim.step(state, Controls(spheres=(sphere,)))
    assert stats.substeps == 1  # in one part: contact at its end (in two it would slide off the surface)
    r = state.positions[0].norm().item()
    assert r == pytest.approx(0.05, rel=1e-5)
    normal = state.positions[0] / r
    assert (state.velocities[0] @ normal).item() == pytest.approx(0.0, abs=1e-6)
    assert state.velocities[0, 1].item() > 0.1  # the tangential part survives


def test_source_is_deterministic_and_seeds_inside_its_ball() -> None:
    def births(seed: int) -> torch.Tensor:
        source = Source((0.1, 0.2, 0.3), 0.04, 50, velocity=(0.0, 0.2, 0.0), seed=seed)
        return torch.cat([emit(source, step, "cpu")[0] for step in range(3)])

    a, b, c = births(7), births(7), births(8)
    assert torch.equal(a, b) and not torch.equal(a, c)
    assert not torch.equal(a[:50], a[50:100])  # each step seeds new positions
    assert float((a - torch.tensor([0.1, 0.2, 0.3])).norm(dim=1).max()) <= 0.04 + 1e-6


def test_source_seeds_a_turned_world_the_same_particles_turned() -> None:
    """A world turned so that up is +z (y -> z, z -> -y) gets the +y world's draw, turned; -y and
    a tilted up are rotations too (the draw stays inside the ball)."""
    turn = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    plain = emit(Source((0.0, 0.0, 0.0), 0.05, 40, seed=3), 2, "cpu")[0]
    turned = emit(Source((0.0, 0.0, 0.0), 0.05, 40, seed=3), 2, "cpu", up=(0.0, 0.0, 1.0))[0]
    torch.testing.assert_close(turned, plain @ turn.T, atol=1e-6, rtol=0)
    for up in ((0.0, -1.0, 0.0), (0.3, 0.8, -0.2), (-1.0, 0.0, 0.0)):
        rotation = from_y(up)
        torch.testing.assert_close(rotation @ rotation.T, torch.eye(3), atol=1e-6, rtol=0)
        unit = torch.tensor(up) / torch.linalg.vector_norm(torch.tensor(up))
        torch.testing.assert_close(rotation @ torch.tensor([0.0, 1.0, 0.0]), unit, atol=1e-6, rtol=0)
        assert float(torch.linalg.det(rotation)) == pytest.approx(1.0, abs=1e-6)


def test_simulator_seeds_the_same_particles_on_every_run() -> None:
    runs = []
    for _ in range(2):
        sim = plume_simulator("auto")
        state, stats = run(sim, sim.new_state(), 3)
        runs.append(state.positions[state.alive])
        assert [s.seeded for s in stats] == [60, 60, 60]
    assert torch.equal(runs[0], runs[1])


def test_particles_leaving_the_box_are_retired_and_slots_reused() -> None:
    box = Box((0, 0, 0), (0.2, 0.2, 0.2))
    sim = paper(replace(CFG, alpha=-30.0), box, Source((0.1, 0.15, 0.1), 0.02, 40, (0, 0.5, 0)))
    state, stats = run(sim, sim.new_state(), 30)
    retired = sum(s.retired for s in stats)
    assert retired > 0
    alive = state.positions[state.alive]
    assert bool(((alive >= 0) & (alive <= 0.2)).all())
    assert state.capacity < 30 * 40  # retired slots were reused instead of growing forever


def test_capacity_grows_geometrically() -> None:
    state = ParticleState.empty(capacity=4)
    state.add(torch.zeros(3, 3), torch.zeros(3, 3))
    state.add(torch.ones(1500, 3), torch.zeros(1500, 3))
    assert state.n_alive == 1503 and state.capacity >= 1503
    assert torch.equal(state.positions[:3], torch.zeros(3, 3))


def test_stabilize_runs_twenty_steps_and_ends_at_time_zero() -> None:
    sim = plume_simulator("auto")
    state = sim.stabilize(sim.new_state())
    assert state.time == 0.0 and state.step == 20 and state.n_alive > 0


# -- gradients -----------------------------------------------------------------------------

def directional_check(f, p: torch.Tensor, eps: float) -> tuple[float, float]:
    p = p.clone().requires_grad_(True)
    f(p).backward()
    d = torch.randn(p.shape, generator=torch.Generator().manual_seed(1))
    analytic = float((p.grad * d).sum())
    with torch.no_grad():
        numeric = (float(f(p + eps * d)) - float(f(p - eps * d))) / (2 * eps)
    return analytic, numeric


def test_incompressibility_loss_gradient_matches_finite_differences() -> None:
    p = random_block(300, 8 * CFG.rho0 * 1.5, CFG.h)
    analytic, numeric = directional_check(lambda q: incompressibility_loss(q, CFG), p, 1e-5)
    assert analytic != 0.0
    assert analytic == pytest.approx(numeric, rel=0.05)


def test_sim_step_is_differentiable_with_respect_to_positions() -> None:
    p = random_block(300, 8 * CFG.rho0 * 1.5, CFG.h)
    v = torch.zeros_like(p)
    target = p + 0.001

    def loss(q: torch.Tensor) -> torch.Tensor:
        return ((sim_step(q, v, replace(CFG, iterations=3))[0] - target) ** 2).sum()

    analytic, numeric = directional_check(loss, p, 1e-6)  # small: the one-sided residual has kinks
    assert math.isfinite(analytic) and analytic != 0.0
    assert analytic == pytest.approx(numeric, rel=0.05)


def test_density_residual_is_one_sided() -> None:
    sparse = random_block(200, 2.0, CFG.h)
    assert float(density_residual(sparse, CFG).max()) == 0.0
    dense = compressed_block(500)
    assert float(density_residual(dense, CFG).mean()) > 0.0


def test_neighbour_cache_gives_fresh_results_and_is_reused_until_stale() -> None:
    config = replace(CFG, iterations=3)
    p0 = compressed_block(600)
    v = 0.05 * torch.randn(600, 3, generator=torch.Generator().manual_seed(7))
    step_cache, loss_cache = NeighbourCache(config.h), NeighbourCache(config.h)
    drift = torch.randn(600, 3, generator=torch.Generator().manual_seed(8))
    drift = drift / drift.norm(dim=1, keepdim=True)  # unit length: particle k moves 0.02 h per call
    for k in range(6):  # an optimiser's iterations, then a jump past skin / 2 = 0.1 h
        p = (p0 + (0.02 * k + (0.3 if k == 5 else 0.0)) * config.h * drift).requires_grad_(True)
        fresh, fresh_v = sim_step(p, v, config)
        fresh_loss = incompressibility_loss(p, config)
        (grad_fresh,) = torch.autograd.grad(fresh.square().sum() + fresh_loss, p)
        cached, cached_v = sim_step(p, v, config, neighbour_cache=step_cache)
        cached_loss = incompressibility_loss(p, config, neighbour_cache=loss_cache)
        (grad_cached,) = torch.autograd.grad(cached.square().sum() + cached_loss, p)
        torch.testing.assert_close(cached, fresh, atol=1e-5 * config.h, rtol=0)
        torch.testing.assert_close(cached_v, fresh_v, atol=1e-5, rtol=1e-5)
        torch.testing.assert_close(cached_loss, fresh_loss, atol=1e-7, rtol=1e-5)
        torch.testing.assert_close(grad_cached, grad_fresh, atol=1e-4, rtol=1e-4)
    assert step_cache.builds == 2 and loss_cache.builds == 2  # reused for k = 1..4, rebuilt after the jump


def test_neighbour_cache_rejects_another_kernel_radius() -> None:
    with pytest.raises(PhysicsInputError, match="neighbour_cache was made for h"):
        sim_step(torch.zeros(2, 3), torch.zeros(2, 3), CFG, neighbour_cache=NeighbourCache(2 * CFG.h))
    with pytest.raises(PhysicsInputError, match="skin"):
        NeighbourCache(CFG.h, skin=-1.0)


# -- input validation ---------------------------------------------------------------------

@pytest.mark.parametrize(
    ("positions", "message"),
    [
        (torch.tensor([[0.0, float("nan"), 0.0]]), "positions contains NaN"),
        (torch.tensor([[0.0, float("inf"), 0.0]]), "positions contains NaN or Inf"),
        (torch.zeros(4, 2), r"positions must have shape \(N, 3\)"),
        (torch.zeros(4, 3, dtype=torch.long), "positions must be a floating-point"),
        ([[0.0, 0.0, 0.0]], "positions must be a torch.Tensor"),
    ],
)
def test_bad_positions_are_rejected_by_name(positions, message: str) -> None:
    with pytest.raises(PhysicsInputError, match=message):
        sim_step(positions, torch.zeros(1, 3), CFG)


def test_bad_velocities_and_forces_are_rejected_by_name() -> None:
    with pytest.raises(PhysicsInputError, match="velocities must have 2 rows"):
        sim_step(torch.zeros(2, 3), torch.zeros(3, 3), CFG)
    with pytest.raises(PhysicsInputError, match="force must return a tensor of shape"):
        sim_step(torch.zeros(2, 3), torch.zeros(2, 3), CFG, force=lambda p, t: torch.zeros(2))
    with pytest.raises(PhysicsInputError, match="force.*NaN"):
        sim_step(torch.zeros(2, 3), torch.zeros(2, 3), CFG, force=lambda p, t: torch.full_like(p, float("nan")))


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [({"rho0": 0.0}, "rho0"), ({"dt": float("nan")}, "dt"), ({"h": -1.0}, "h"), ({"iterations": -1}, "iterations"),
     ({"gravity": (0.0, 1.0)}, "gravity"), ({"tolerance": 0.0}, "tolerance"), ({"drag": -1.0}, "drag")],
)
def test_bad_config_values_are_rejected_by_name(kwargs: dict, field: str) -> None:
    with pytest.raises(PhysicsInputError, match=field):
        PBFConfig(**kwargs)


def test_bad_scene_parts_are_rejected_by_name() -> None:
    with pytest.raises(PhysicsInputError, match="box.lo must be below box.hi"):
        Box((0, 0, 0), (1, 0, 1))
    with pytest.raises(PhysicsInputError, match="source.radius"):
        Source((0, 0, 0), -1.0, 10)
    with pytest.raises(PhysicsInputError, match="sphere.center"):
        Sphere((0, float("nan"), 0), 1.0)
    with pytest.raises(PhysicsInputError, match="backend"):
        paper(CFG, Box((0, 0, 0), (1, 1, 1)), backend="warp")


# -- CUDA (skipped without a GPU) ----------------------------------------------------------

@pytest.mark.gpu
def test_cuda_simulation_matches_cpu() -> None:
    results = []
    for device in ("cpu", "cuda"):
        sim = plume_simulator("torch", device=device)
        state, stats = run(sim, sim.new_state(), 8)
        results.append((state.to("cpu"), stats))
    (cpu, cpu_stats), (gpu, gpu_stats) = results
    assert torch.equal(cpu.alive, gpu.alive)
    torch.testing.assert_close(gpu.positions, cpu.positions, atol=1e-3 * CFG.h, rtol=0)
    assert [s.iterations for s in gpu_stats] == [s.iterations for s in cpu_stats]


@pytest.mark.gpu
def test_sim_step_gradients_on_cuda() -> None:
    p = compressed_block(500).cuda().requires_grad_(True)
    q, _ = sim_step(p, torch.zeros_like(p), CFG)
    (q.sum() + incompressibility_loss(p, CFG)).backward()
    assert p.grad is not None and bool(torch.isfinite(p.grad).all())

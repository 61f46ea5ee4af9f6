"""PBF physics benchmark: speed and density error against particle count and solver iterations.

    python bench/physics.py                      # sweep: table + JSON + speed-vs-error PNG
    python bench/physics.py --particles 50000 --iterations 10 --json
    python bench/physics.py --particles 50000 --tolerance 0.002 --steps 20
    python bench/physics.py --air --threads 1        # the air grid's rows (fluidcore.physics.air)

Scene ("calm"): a steady plume. N particles fill a vertical column (height 4 x radius), at the
rest density at the bottom thinning linearly to 40 % of it at the top, as a rising plume
stretches; random packing leaves many of the lower particles over-dense at the start. Buoyancy
lifts them and particles leaving the top of the box are re-seeded in a ball at the bottom, so N
stays constant. "violent": the same column packed 1.6x denser throughout, a strong side wind
growing with height, a ball rising through the column, and retired particles re-seeded into a
ball a third as wide (a dense jet): compression that the solver must undo every step. Each run
warms up (untimed) before the timed steps.

Air rows (--air): on the same two scenes, the air grid (`AirGrid`, 32, 48 and 64 cells on the
box's long side) is stepped from the particles of every timed PBF step; each row gives the
seconds per air step, the PBF step's, and their ratio (CPU time, the steadier measure on a shared
machine; wall time beside it). In "violent" the wind also pushes the air and the ball is a wall
of it, so the pressure solve needs more than its one direct iteration.

Density error: the one-sided residual max(0, rho/rho0 - 1) that the solver drives to zero,
over alive particles after each step; "mean" averages it over particles and timed steps,
"max" is the largest over particles and timed steps.
"""

from __future__ import annotations

import json
import math
import os
import platform
import sys
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Optional

import typer

import fluidcore  # noqa: F401  first, before torch: sets OpenMP's passive wait policy (see fluidcore/__init__.py)

SIZES = (10_000, 50_000, 200_000)
ITERATIONS = (1, 2, 5, 10, 20)
SWEEP_TOLERANCE = 1e-4
SCENES = ("calm", "violent")
AIR_CELLS = (32, 48, 64)
AIR_PARTICLES = 50_000


@dataclass
class Result:
    scene: str
    particles: int
    iterations: int | None
    tolerance: float | None
    iterations_used: float
    steps: int
    steps_per_s: float
    cpu_s_per_step: float  # process CPU time (all threads): less sensitive than wall time to other load
    mean_density_error: float
    max_density_error: float


@dataclass
class AirResult:
    scene: str
    particles: int
    cells: int  # on the box's long side
    grid: tuple[int, int, int]
    steps: int
    air_s_per_step: float  # wall
    air_cpu_s_per_step: float
    pbf_s_per_step: float  # wall, the simulator's step without air (10 solver iterations)
    pbf_cpu_s_per_step: float
    ratio: float  # air CPU s / PBF CPU s
    pressure_iterations: float  # mean per air step
    max_divergence_ratio: float  # largest |div| after / before the projection over the timed steps


def log(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def plume(n: int, scene: str, config, device: str, backend: str):
    """Simulator, controls and state of the benchmark plume with n particles, plus a re-seeding
    function (it puts `count` particles back into the state it is given)."""
    import torch

    from fluidcore.physics import ParticleState, Source, Sphere, wind_force
    from fluidcore.physics.build import build_simulator
    from fluidcore.physics.motion import Controls
    from fluidcore.spec.controls import WindParams
    from fluidcore.physics.source import emit
    from fluidcore.spec.scene import Scene

    packing, thinning = (1.6, 0.0) if scene == "violent" else (1.0, 0.6)  # density at the bottom; its fall to the top
    volume = n / (8.0 * config.rho0 * packing * (1.0 - thinning / 2.0)) * config.h**3
    radius = (volume / (4.0 * math.pi)) ** (1.0 / 3.0)
    height = 4.0 * radius
    g = torch.Generator().manual_seed(0)
    u = torch.rand(n, 3, generator=g)
    angle, r = 2.0 * math.pi * u[:, 0], radius * u[:, 1].sqrt()
    y = height * u[:, 2] if thinning == 0.0 else height / thinning * (
        1.0 - torch.sqrt(1.0 - 2.0 * thinning * (1.0 - thinning / 2.0) * u[:, 2]))  # inverse CDF of the linear profile
    positions = torch.stack([r * angle.cos(), y, r * angle.sin()], dim=1)
    velocities = torch.zeros(n, 3)
    velocities[:, 1] = 0.1
    state = ParticleState.from_positions(positions.to(device), velocities.to(device))
    violent = scene == "violent"
    jet = radius / 3.0 if violent else radius
    # the jet seeds nothing by itself: `reseed` puts back what left the box, keeping the count fixed
    plume_scene = Scene((-3 * radius, -radius, -3 * radius), (3 * radius, height, 3 * radius), (0.0, 1.0, 0.0), config,
                        Source((0.0, jet, 0.0), jet, 0, (0.0, 0.1, 0.0), seed=1))
    wind = WindParams(direction=(1.0, 0.0, 0.0), strength=3.0, growth=2.0 / height)
    force = wind_force(wind, blowing=lambda time: True) if violent else None
    spheres = [Sphere((0.0, 0.3 * height, 0.0), 0.5 * radius, velocity=(0.0, 0.3, 0.0))] if violent else []
    sim = build_simulator(plume_scene, device=device, backend=backend)

    def reseed(into: ParticleState, count: int) -> None:
        if count:
            into.add(*emit(replace(plume_scene.source, rate=count), into.step, device))

    return sim, Controls(force=force, spheres=tuple(spheres)), state, reseed


def run(n: int, iterations: int | None, tolerance: float | None, steps: int, warmup: int, scene: str,
        device: str, backend: str) -> Result:
    """Warm up, then time `steps` steps of the plume."""
    import torch

    from fluidcore.physics import PRESETS

    base = PRESETS["scalarflow"]
    config = replace(base, iterations=iterations if iterations is not None else base.iterations, tolerance=tolerance)
    sim, controls, state, reseed = plume(n, scene, config, device, backend)
    for _ in range(warmup):
        state, step = sim.step(state, controls)
        reseed(state, step.retired)
    stats = []
    if device == "cuda":
        torch.cuda.synchronize()
    start, cpu_start = time.perf_counter(), time.process_time()
    for _ in range(steps):
        state, step = sim.step(state, controls)
        stats.append(step)
        reseed(state, step.retired)
    if device == "cuda":
        torch.cuda.synchronize()
    elapsed, cpu = time.perf_counter() - start, time.process_time() - cpu_start
    return Result(
        scene=scene, particles=n, iterations=None if tolerance is not None else config.iterations, tolerance=tolerance,
        iterations_used=sum(s.iterations for s in stats) / steps, steps=steps, steps_per_s=steps / elapsed,
        cpu_s_per_step=cpu / steps,
        mean_density_error=sum(s.mean_density_error for s in stats) / steps,
        max_density_error=max(s.max_density_error for s in stats),
    )


def run_air(n: int, steps: int, warmup: int, scene: str, device: str, backend: str) -> list[AirResult]:
    """Time the PBF step of the plume and, on the same particles each step, an air step at each of AIR_CELLS."""
    import torch

    from fluidcore.physics import PRESETS
    from fluidcore.physics.air import AirGrid

    config = PRESETS["scalarflow"]
    sim, controls, state, reseed = plume(n, scene, config, device, backend)
    grids = [AirGrid(sim.box, cells) for cells in AIR_CELLS]
    airs = [grid.still(device) for grid in grids]
    timing = {key: [0.0, 0.0] for key in ("pbf", *AIR_CELLS)}
    iterations = {cells: 0 for cells in AIR_CELLS}
    divergence = {cells: 0.0 for cells in AIR_CELLS}

    def timed(key: object, work):
        if device == "cuda":
            torch.cuda.synchronize()
        start, cpu_start = time.perf_counter(), time.process_time()
        out = work()
        if device == "cuda":
            torch.cuda.synchronize()
        if key is not None:
            timing[key][0] += time.perf_counter() - start
            timing[key][1] += time.process_time() - cpu_start
        return out

    for step in range(warmup + steps):
        key = "pbf" if step >= warmup else None
        smoke = state.positions[state.alive]
        for grid, air in zip(grids, airs):
            stats = timed(grid.cells if key else None,
                          lambda: grid.step(air, smoke, config, state.time, controls.spheres, controls.force))  # noqa: B023
            if key:
                iterations[grid.cells] += stats.iterations
                divergence[grid.cells] = max(divergence[grid.cells], stats.divergence_after
                                             / max(stats.divergence_before, 1e-30))
        state, stepped = timed(key, lambda: sim.step(state, controls))  # noqa: B023
        reseed(state, stepped.retired)
    pbf_wall, pbf_cpu = (t / steps for t in timing["pbf"])
    return [AirResult(scene=scene, particles=n, cells=grid.cells, grid=grid.shape, steps=steps,
                      air_s_per_step=timing[grid.cells][0] / steps, air_cpu_s_per_step=timing[grid.cells][1] / steps,
                      pbf_s_per_step=pbf_wall, pbf_cpu_s_per_step=pbf_cpu,
                      ratio=timing[grid.cells][1] / steps / pbf_cpu, pressure_iterations=iterations[grid.cells] / steps,
                      max_divergence_ratio=divergence[grid.cells]) for grid in grids]


def air_table(results: list[AirResult]) -> str:
    """Markdown table of the air rows."""
    lines = ["| scene | particles | cells (long side) | grid | air s/step (CPU) | PBF s/step (CPU) | air / PBF "
             "| air s/step (wall) | PBF s/step (wall) | pressure iterations | max div after / before |",
             "|---|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|"]
    for r in results:
        lines.append(f"| {r.scene} | {r.particles:,} | {r.cells} | {'x'.join(map(str, r.grid))} | "
                     f"{r.air_cpu_s_per_step:.3f} | {r.pbf_cpu_s_per_step:.3f} | {r.ratio:.2f} | {r.air_s_per_step:.3f} | "
                     f"{r.pbf_s_per_step:.3f} | {r.pressure_iterations:.1f} | {r.max_divergence_ratio:.1e} |")
    return "\n".join(lines)


def machine(device: str, threads: int, backend: str) -> dict:
    import torch

    info = {"device": device, "threads": threads, "backend": backend, "cpu_cores": os.cpu_count(),
            "platform": platform.platform(), "torch": torch.__version__,
            "load_average": os.getloadavg() if hasattr(os, "getloadavg") else None}
    if device == "cuda":
        info["gpu"] = torch.cuda.get_device_name()
    return info


def table(results: list[Result]) -> str:
    """Markdown table of a sweep."""
    lines = ["| scene | particles | iterations | tolerance | iterations used | steps/s | CPU s/step | mean density error "
             "| max density error |", "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in results:
        lines.append(f"| {r.scene} | {r.particles:,} | {r.iterations if r.iterations is not None else '-'} | "
                     f"{r.tolerance if r.tolerance is not None else '-'} | {r.iterations_used:.1f} | "
                     f"{r.steps_per_s:.2f} | {r.cpu_s_per_step:.3f} | {r.mean_density_error:.2e} | {r.max_density_error:.2e} |")
    return "\n".join(lines)


def plot(results: list[Result], path: Path) -> None:
    """Speed (steps/s) against mean density error, one line per scene and particle count."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4.5))
    floor = 1e-9  # an error of exactly 0 still gets a point on the log axis
    for scene, style in (("calm", "o-"), ("violent", "s--")):
        for n in sorted({r.particles for r in results}):
            rows = [r for r in results if r.particles == n and r.iterations is not None and r.scene == scene]
            if not rows:
                continue
            errors = [max(r.mean_density_error, floor) for r in rows]
            ax.plot([r.steps_per_s for r in rows], errors, style, label=f"{scene} {n:,}")
            for r, e in zip(rows, errors):
                ax.annotate(str(r.iterations), (r.steps_per_s, e), fontsize=7)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("steps per second")
    ax.set_ylabel("mean density error  max(0, rho/rho0 - 1)")
    ax.set_title("PBF: speed vs error (labels: solver iterations)")
    ax.legend(title="scene, particles", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def command(
    particles: Optional[int] = typer.Option(None, help="Particle count (single run); default: the sweep."),
    iterations: Optional[int] = typer.Option(None, help="Fixed solver iterations (single run; default 10)."),
    tolerance: Optional[float] = typer.Option(None, help="Stop iterating when the mean residual is below this."),
    steps: int = typer.Option(10, help="Timed steps per run."),
    warmup: int = typer.Option(5, help="Untimed steps before timing."),
    scene: str = typer.Option("calm", help="calm | violent (single run)."),
    device: str = typer.Option("cpu", help="cpu | cuda."),
    backend: str = typer.Option("auto", help="auto | torch | fused."),
    threads: Optional[int] = typer.Option(None, help="torch/OpenMP threads (default: all cores)."),
    out: Path = typer.Option(Path("bench/results"), help="Folder for physics.json and physics.png (sweep)."),
    as_json: bool = typer.Option(False, "--json", help="Print one JSON object on stdout, nothing else."),
    air: bool = typer.Option(False, "--air", help="The air grid's rows: s/step at 32, 48, 64 cells vs the PBF step "
                                                   f"(both scenes, --particles, default {AIR_PARTICLES:,}); writes physics_air.json."),
) -> None:
    import torch

    if device not in ("cpu", "cuda"):
        raise typer.BadParameter("device must be cpu or cuda", param_hint="--device")
    if device == "cuda" and not torch.cuda.is_available():
        raise typer.BadParameter("CUDA is not available on this machine", param_hint="--device")
    if scene not in SCENES:
        raise typer.BadParameter(f"scene must be one of {SCENES}", param_hint="--scene")
    if iterations is not None and tolerance is not None:
        raise typer.BadParameter("give --iterations or --tolerance, not both", param_hint="--tolerance")
    if steps < 1 or warmup < 0:
        raise typer.BadParameter("steps must be >= 1 and warmup >= 0", param_hint="--steps")
    torch.set_num_threads(threads or os.cpu_count() or 1)
    info = machine(device, torch.get_num_threads(), backend)
    log(f"physics bench: {info}")

    if air:
        n = particles or AIR_PARTICLES
        air_results = []
        for name in SCENES:
            log(f"  air rows: {name} n={n} ...")
            air_results += run_air(n, steps, warmup, name, device, backend)
        out.mkdir(parents=True, exist_ok=True)
        payload = {"machine": info, "steps": steps, "warmup": warmup, "air": [asdict(r) for r in air_results]}
        (out / "physics_air.json").write_text(json.dumps(payload, indent=2))
        log(f"wrote {out / 'physics_air.json'}")
        print(json.dumps(payload, indent=2) if as_json else air_table(air_results))
        return

    if particles is not None or iterations is not None or tolerance is not None:
        result = run(particles or 50_000, iterations, tolerance, steps, warmup, scene, device, backend)
        payload = {**asdict(result), "machine": info}
        if as_json:
            print(json.dumps(payload, indent=2))
        else:
            print(table([result]))
        return

    results = []
    plan = [(n, k, None, "calm") for n in SIZES for k in ITERATIONS]
    plan += [(n, k, None, "violent") for n in SIZES[:2] for k in ITERATIONS]
    plan += [(n, None, SWEEP_TOLERANCE, s) for n in SIZES[:2] for s in SCENES]
    for n, k, tol, name in plan:
        log(f"  {name} n={n} iterations={k} tolerance={tol} ...")
        results.append(run(n, k, tol, steps, warmup, name, device, backend))
        log(f"    {results[-1].steps_per_s:.2f} steps/s, mean error {results[-1].mean_density_error:.2e}")
    out.mkdir(parents=True, exist_ok=True)
    payload = {"machine": info, "steps": steps, "warmup": warmup, "results": [asdict(r) for r in results]}
    (out / "physics.json").write_text(json.dumps(payload, indent=2))
    plot(results, out / "physics.png")
    log(f"wrote {out / 'physics.json'} and {out / 'physics.png'}")
    if as_json:
        print(json.dumps(payload, indent=2))
    else:
        print(f"threads: {info['threads']}, load average: {info['load_average']}")
        print(table(results))


if __name__ == "__main__":
    from bench.registry import run_script

    run_script("physics", command)

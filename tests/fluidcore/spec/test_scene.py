"""The scene spec (`fluidcore.spec.scene`) and the one builder of a simulator from it
(`fluidcore.physics.build.build_simulator`): validation where a scene is made, the manifest's
scene record read back (an old one as still air), and every simulation of a scene simulating
its air when it has one, the identification's rollouts and the buoyancy calibration included."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from tests.support.predict_scenes import SPEC, plume_run, scene_of
from tests.support.run_folder import _create, _scene
from tests.support.simulators import paper, run

from fluidcore.physics.air import AirGrid
from fluidcore.physics.build import build_simulator
from fluidcore.physics.carrier import BuoyantAirCarrier
from fluidcore.physics.motion import NO_CONTROLS, Controls
from fluidcore.physics.paper import PositionBasedFluid
from fluidcore.physics.simulator import Simulator
from fluidcore.predict.identification import calibrate_buoyancy
from fluidcore.reconstruct.identify import Candidate, Observation, ScenePrior, _Search
from fluidcore.runs import ContinuationSettings, ReconstructSettings, Run
from fluidcore.spec.reconstruct import VisualSettings, get
from fluidcore.spec.physics import Sphere
from fluidcore.spec.scene import Air, Scene, SceneError, SourcePlace
from fluidcore.spec.solids import MAX_SOLIDS, SolidBall
from fluidcore.spec.simulation import AIR_CELLS

OLD_RUNS = Path(__file__).parents[1] / "fixtures" / "runs_v1"


def _steps_seen(monkeypatch: pytest.MonkeyPatch) -> list[object]:
    """The air of every simulator that steps from now on, however it was built."""
    seen: list[object] = []
    step = Simulator.step

    def recording(self: Simulator, state, controls=NO_CONTROLS):  # noqa: ANN001, ANN202 - the patched method's own signature
        seen.append(self.integrator.air)
        return step(self, state, controls)

    monkeypatch.setattr(Simulator, "step", recording)
    return seen


def test_a_scene_is_checked_where_it_is_made() -> None:
    scene = _scene()
    with pytest.raises(SceneError, match="scene.box_lo must be below"):
        replace(scene, box_lo=(0.0, 3.0, 0.0))
    with pytest.raises(SceneError, match="scene.up"):
        replace(scene, up=(0.0, float("nan"), 0.0))
    with pytest.raises(SceneError, match="scene.up must not be 0"):
        replace(scene, up=(0.0, 0.0, 0.0))
    with pytest.raises(SceneError, match="scene.source must be a Source"):
        replace(scene, source=SourcePlace((0.0, 0.1, 0.0), 0.1))
    for cells in (2, 300, 8.0, True):
        with pytest.raises(SceneError, match="air.cells"):
            Air(cells)
    with pytest.raises(SceneError, match="air.vorticity"):
        Air(16, -0.1)
    for viscosity in (-1e-3, float("inf"), True):
        with pytest.raises(SceneError, match="air.viscosity"):
            Air(16, 0.0, viscosity)
    with pytest.raises(SceneError, match="source.radius"):
        SourcePlace((0.0, 0.0, 0.0), 0.0)
    assert Air(AIR_CELLS[0]).simulated and not Air().simulated
    assert scene.box.lo == scene.box_lo and scene.box.hi == scene.box_hi


def test_the_scene_record_round_trips_and_keeps_its_layout() -> None:
    scene = replace(_scene(), air=Air(16, 0.3))
    record = scene.to_json()
    assert sorted(record) == ["air", "box", "motion", "physics", "solids", "source", "up"]  # the manifest's layout
    assert record["air"] == {"cells": 16, "vorticity": 0.3, "viscosity": 0.0, "diffusivity": 0.0} and record["motion"] == "paper"
    assert Scene.from_json(json.loads(json.dumps(record))) == scene
    assert Scene.from_json({k: v for k, v in record.items() if k != "air"}).air == Air()  # no air recorded: still air
    assert Scene.from_json({k: v for k, v in record.items() if k != "motion"}).motion == "paper"  # written before the carrier
    carried = replace(scene, motion="carrier", air=Air(16, 0.0, 0.002))
    assert Scene.from_json(json.loads(json.dumps(carried.to_json()))) == carried
    with pytest.raises(SceneError, match="scene: malformed"):
        Scene.from_json({**record, "up": [0.0, 0.0]})
    with pytest.raises(SceneError, match="air.cells must be 0"):
        Scene.from_json({**record, "air": {"cells": 4, "vorticity": 0.0}})


def test_a_scenes_solids_round_trip_are_checked_and_an_old_record_has_none() -> None:
    balls = (SolidBall(center=(0.0, 1.0, 0.0), radius=0.2), SolidBall(center=(0.5, 1.5, -0.5), radius=0.1))
    scene = replace(_scene(), solids=balls)
    record = scene.to_json()
    assert record["solids"] == [{"center": [0.0, 1.0, 0.0], "radius": 0.2}, {"center": [0.5, 1.5, -0.5], "radius": 0.1}]
    assert Scene.from_json(json.loads(json.dumps(record))) == scene
    assert Scene.from_json({k: v for k, v in record.items() if k != "solids"}).solids == ()  # written before solids
    assert _scene().to_json()["solids"] == []
    with pytest.raises(SceneError, match=r"scene.solids\[1\].center \[0.5, 3.0, -0.5\] is outside the scene box"):
        replace(scene, solids=(balls[0], SolidBall(center=(0.5, 3.0, -0.5), radius=0.1)))
    with pytest.raises(SceneError, match=r"scene.solids\[0\].radius 5.0 is larger than the scene box"):
        replace(scene, solids=(SolidBall(center=(0.0, 1.0, 0.0), radius=5.0),))
    with pytest.raises(SceneError, match=f"scene.solids: 9 balls, at most {MAX_SOLIDS}"):
        replace(scene, solids=balls[:1] * 9)
    with pytest.raises(SceneError, match="scene: malformed"):
        Scene.from_json({**record, "solids": [{"center": [0.0, 1.0, 0.0], "radius": -1.0}]})
    for kind in ("reconstruct", "predict", "interact"):  # runs written before solids: none
        assert Run.open(OLD_RUNS / kind).scene.solids == ()


def test_every_step_of_a_scene_with_solids_keeps_the_smoke_out_of_them_and_adds_a_what_ifs_ball() -> None:
    """The simulator built from a scene puts its solids in the way of every step, with the balls a
    step's controls bring (a what-if's); the same scene without them lets the smoke through."""
    ball = SolidBall(center=(0.0, 0.35, 0.0), radius=0.12)
    scene = replace(_scene(), source=replace(_scene().source, rate=40, velocity=(0.0, 1.5, 0.0)), solids=(ball,))
    moving = Sphere(center=(1.0, 1.0, 1.0), radius=0.1)
    simulator = build_simulator(scene)
    assert simulator.with_solids(Controls(spheres=(moving,))).spheres == (ball.sphere, moving)

    def nearest(simulator: Simulator) -> float:
        state = simulator.new_state()
        closest = np.inf
        for _ in range(12):
            state, _ = simulator.step(state)
            positions = state.positions[state.alive]
            if len(positions):
                closest = min(closest, float(torch.linalg.vector_norm(positions - torch.tensor(ball.center), dim=1).min()))
        return closest

    assert nearest(simulator) >= ball.radius * (1 - 1e-5)
    assert nearest(build_simulator(replace(scene, solids=()))) < 0.5 * ball.radius


def test_a_runs_scene_is_the_air_it_records(tmp_path: Path) -> None:
    """The manifest's scene record is the one home of the run's air: read back as written, whatever
    the settings say (a reconstruction's quality asked for it; a continuation has no field of it)."""
    quality = get("preview").with_overrides(air_cells=16, air_vorticity=0.3)
    reconstruction = _create(tmp_path / "r", scene=replace(_scene(), air=Air(16, 0.3)),
                             settings=ReconstructSettings(quality=quality))
    assert reconstruction.manifest["scene"]["air"] == {"cells": 16, "vorticity": 0.3, "viscosity": 0.0, "diffusivity": 0.0}
    assert Run.open(reconstruction.path).scene.air == Air(16, 0.3)
    visual = VisualSettings(velocity_radius=2.0, per_physical=1, seed=0)
    continuation = _create(tmp_path / "c", kind="predict", scene=replace(_scene(), air=Air(24)), settings=ContinuationSettings(
        branch_frame=0, visual=visual, parent_source_rate=3))
    assert Run.open(continuation.path).scene.air == Air(24)
    assert "air_cells" not in continuation.manifest["settings"]
    for kind in ("reconstruct", "predict", "interact"):  # written before the air was simulated: still air
        assert Run.open(OLD_RUNS / kind).scene.air == Air()


def test_the_builder_gives_each_motion_model_its_integrator_and_a_scene_with_air_its_grid() -> None:
    scene = replace(_scene(), air=Air(8, 0.2, 0.001))
    simulator = build_simulator(scene)
    grid = simulator.integrator.air
    assert isinstance(simulator.integrator, PositionBasedFluid) and simulator.motion == "paper"
    assert isinstance(grid, AirGrid) and grid.cells == 8 and grid.vorticity == 0.2
    assert simulator.config == scene.physics and simulator.source == scene.source and simulator.box == scene.box
    assert build_simulator(_scene()).integrator.air is None  # still air
    carried = build_simulator(replace(scene, motion="carrier"))
    assert isinstance(carried.integrator, BuoyantAirCarrier) and carried.motion == "carrier"
    assert carried.integrator.air.cells == 8 and carried.integrator.viscosity == 0.001
    with pytest.raises(SceneError, match="air.cells"):  # the carrier is its air: still air cannot carry smoke
        replace(_scene(), motion="carrier")
    with pytest.raises(SceneError, match="scene.motion"):
        replace(_scene(), motion="lagrangian")


def test_the_identifications_rollouts_simulate_the_scenes_air(monkeypatch: pytest.MonkeyPatch) -> None:
    """The search's rollouts simulate the physics the reconstruction runs: with the scene's air
    grid when it has one, with none when it is still."""
    spec = SPEC
    source = spec.source()
    camera = next(iter(spec.cameras().values()))
    cells = np.zeros((2, camera.height // 2, camera.width // 2), dtype=bool)
    cells[:, 10:14, 5:7] = True
    observation = Observation(camera, cells, 2, np.zeros(cells.shape[1:]))
    candidate = Candidate(float(spec.config().body_acceleration[1]), source.radius, source.center[1], 0.0)
    for air in (Air(8), Air()):
        seen = _steps_seen(monkeypatch)
        prior = ScenePrior(spec.box(), (0.0, 1.0, 0.0), air, "auto", spec.config(), SourcePlace.of(source), source.seed)
        _Search(observation, prior, spec.particles_per_step, "cpu").misfit(candidate)
        assert seen and all(isinstance(a, AirGrid) == air.simulated for a in seen)
        if air.simulated:
            assert {a.cells for a in seen} == {air.cells}


def test_the_buoyancy_calibration_simulates_the_runs_air(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    parent = Run.open(plume_run(tmp_path / "air", frames=4, warmup=20, quality={"air_cells": 8}))
    assert parent.scene.air == Air(8)
    seen = _steps_seen(monkeypatch)
    scale, errors = calibrate_buoyancy(parent, parent.scene, parent.frames()[-1], "cpu", scales=(0.5, 1.0))
    assert len(errors) == 2 and scale in (0.5, 1.0)
    assert seen and all(isinstance(a, AirGrid) and a.cells == 8 for a in seen)


def test_a_built_simulator_steps_as_one_made_by_hand() -> None:
    """The builder adds nothing to a still-air scene: the same particles, bit for bit."""
    scene = scene_of()
    built, by_hand = build_simulator(scene), paper(scene.physics, scene.box, scene.source)
    states = [run(built, built.new_state(), 5)[0], run(by_hand, by_hand.new_state(), 5)[0]]
    assert states[0].n_alive > 0
    assert torch.equal(states[0].positions, states[1].positions) and torch.equal(states[0].alive, states[1].alive)


def test_the_spec_layer_imports_nothing_of_fluidcore_above_it() -> None:
    """`fluidcore.spec` sits at the bottom: of fluidcore it imports `errors`, `names` and itself only."""
    import ast

    import fluidcore.spec

    allowed = ("fluidcore.errors", "fluidcore.names", "fluidcore.spec")
    for path in Path(fluidcore.spec.__file__).parent.glob("*.py"):
        tree = ast.parse(path.read_text())
        imported = [n.module or "" for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)]
        imported += [a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names]
        above = [m for m in imported if m.startswith("fluidcore") and not m.startswith(allowed)]
        assert above == [], (path.name, above)

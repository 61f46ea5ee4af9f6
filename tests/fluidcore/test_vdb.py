"""OpenVDB files (fluidcore.vdb, `fluidnexus export --format vdb`) read back by OpenVDB itself.

The reader is OpenVDB's own Python binding, Debian's python3-openvdb, which binds only the
system Python: it runs in a /usr/bin/python3 subprocess and the tests skip, saying so, where it
is not installed (.ci/run installs it). Values, grid names and classes, and the transform (voxel
size, the world position of voxel [0, 0, 0] and of another voxel) are checked against the arrays
written.
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from fluidcore.runs import Run
from fluidcore.vdb import write_vdb
from fluidnexus.cli import app

SYSTEM_PYTHON = "/usr/bin/python3"
READER = """
import json, sys
import numpy as np
import pyopenvdb as vdb

path, shapes = sys.argv[1], json.loads(sys.argv[2])
grids, file_meta = vdb.readAll(path)
report = {}
for grid in grids:
    shape = shapes[grid.name]
    dense = np.zeros(shape, dtype=np.float32)
    grid.copyToArray(dense)
    np.save(f"{path}.{grid.name}.npy", dense)
    report[grid.name] = {
        "type": grid.valueTypeName, "class": str(grid.gridClass), "active": grid.activeVoxelCount(),
        "voxel_size": list(grid.transform.voxelSize()), "origin": list(grid.transform.indexToWorld((0, 0, 0))),
        "at_1_2_3": list(grid.transform.indexToWorld((1, 2, 3))), "vector_type": str(grid.vectorType),
    }
print(json.dumps(report))
"""


def _openvdb_available() -> str | None:
    """Why OpenVDB's binding cannot run here, or None when it can."""
    if not Path(SYSTEM_PYTHON).is_file():
        return f"no {SYSTEM_PYTHON} for OpenVDB's Python binding"
    probe = subprocess.run([SYSTEM_PYTHON, "-c", "import pyopenvdb, numpy"], capture_output=True, text=True)
    if probe.returncode != 0:
        return f"OpenVDB's Python binding is not installed for {SYSTEM_PYTHON} (apt-get install python3-openvdb)"
    return None


needs_openvdb = pytest.mark.skipif(_openvdb_available() is not None, reason=_openvdb_available() or "")


def read_with_openvdb(path: Path, shapes: dict[str, tuple[int, ...]]) -> tuple[dict, dict[str, np.ndarray]]:
    """Each grid's description and its values in a dense array of the given shape, as OpenVDB reads them."""
    done = subprocess.run([SYSTEM_PYTHON, "-c", READER, str(path), json.dumps(shapes)], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    report = json.loads(done.stdout)
    return report, {name: np.load(f"{path}.{name}.npy") for name in report}


@needs_openvdb
def test_openvdb_reads_scalar_and_vector_grids_across_several_nodes(tmp_path):
    rng = np.random.default_rng(0)
    density = np.zeros((140, 140, 30), dtype=np.float32)  # 2 x 2 internal nodes of 128 voxels across x and y
    hit = rng.random(density.shape) < 0.02
    density[hit] = rng.uniform(0.01, 3.0, hit.sum())
    velocity = np.zeros((*density.shape, 3), dtype=np.float32)
    velocity[hit] = rng.normal(size=(hit.sum(), 3))
    origin = np.array([0.25, -1.5, 3.0])
    write_vdb(tmp_path / "g.vdb", {"density": density, "velocity": velocity}, origin, 0.04)

    report, grids = read_with_openvdb(tmp_path / "g.vdb", {"density": density.shape, "velocity": velocity.shape})
    assert list(report) == ["density", "velocity"]
    assert report["density"]["type"] == "float" and report["density"]["class"] == "fog volume"
    assert report["velocity"]["type"] == "vec3s" and report["velocity"]["vector_type"] == "contravariant relative"
    for name, values in (("density", density), ("velocity", velocity)):
        np.testing.assert_array_equal(grids[name], values)
        assert report[name]["active"] == hit.sum()
        np.testing.assert_allclose(report[name]["voxel_size"], [0.04] * 3)
        np.testing.assert_allclose(report[name]["origin"], origin)
        np.testing.assert_allclose(report[name]["at_1_2_3"], origin + 0.04 * np.array([1, 2, 3]))


@needs_openvdb
def test_openvdb_reads_voxels_in_different_top_nodes_and_an_empty_grid(tmp_path):
    far = np.zeros((9000, 2, 3), dtype=np.float32)  # a top-level node spans 4096 voxels: three of them
    far[0, 0, 0], far[4500, 1, 2], far[8999, 0, 1] = 1.0, 2.0, 3.0
    write_vdb(tmp_path / "e.vdb", {"far": far, "empty": np.zeros((5, 6, 7))}, np.zeros(3), 1.0)
    report, grids = read_with_openvdb(tmp_path / "e.vdb", {"far": far.shape, "empty": (5, 6, 7)})
    assert report["far"]["active"] == 3 and np.array_equal(grids["far"], far)
    assert report["empty"]["active"] == 0 and not grids["empty"].any()


def test_non_finite_values_and_bad_shapes_are_refused(tmp_path):
    with pytest.raises(ValueError, match="non-finite"):
        write_vdb(tmp_path / "n.vdb", {"density": np.full((2, 2, 2), np.nan)}, np.zeros(3), 1.0)
    with pytest.raises(ValueError, match=r"\(X, Y, Z\) or \(X, Y, Z, 3\)"):
        write_vdb(tmp_path / "s.vdb", {"velocity": np.zeros((2, 2, 2, 2))}, np.zeros(3), 1.0)
    assert not list(tmp_path.iterdir())


@needs_openvdb
@pytest.mark.parametrize("air_cells", [0, 12])  # velocity from the particles / from the saved air
def test_exported_vdb_sequence_is_the_density_grid_in_world_units(tmp_path, air_cells):
    from tests.support.predict_scenes import plume_run

    run_dir = plume_run(tmp_path / "run", frames=3, quality={"air_cells": air_cells})
    runner = CliRunner()
    done = runner.invoke(app, ["export", str(run_dir), "--frames", "1:3", "--format", "vdb", "--out", str(tmp_path / "vdb")])
    assert done.exit_code == 0, done.output
    assert sorted(p.name for p in (tmp_path / "vdb").iterdir()) == ["smoke_000001.vdb", "smoke_000002.vdb"]
    for t in (1, 2):
        done = runner.invoke(app, ["export", str(run_dir), "--frame", str(t), "--format", "density", "--out", str(tmp_path / "d.npz")])
        assert done.exit_code == 0, done.output
        with np.load(tmp_path / "d.npz") as expected:
            density, origin, spacing = expected["density"], expected["origin"], float(expected["spacing"])
            velocity = expected["velocity"]
        report, grids = read_with_openvdb(tmp_path / "vdb" / f"smoke_{t:06d}.vdb",
                                          {"density": density.shape, "velocity": velocity.shape})
        assert list(report) == ["density", "velocity"] and report["density"]["class"] == "fog volume"
        assert density.any() and np.array_equal(grids["density"], density)
        # the velocity (world units/s) where there is smoke, the npz's velocity there
        assert report["velocity"]["type"] == "vec3s" and report["velocity"]["vector_type"] == "contravariant relative"
        np.testing.assert_array_equal(grids["velocity"], np.where(density[..., None] > 0, velocity, 0.0))
        assert np.abs(grids["velocity"]).max() > 0
        np.testing.assert_allclose(report["velocity"]["origin"], origin)
        assert report["density"]["active"] == np.count_nonzero(density)
        np.testing.assert_allclose(report["density"]["voxel_size"], [spacing] * 3)
        np.testing.assert_allclose(report["density"]["origin"], origin)
        h = Run.open(run_dir).scene.physics.h
        assert spacing == pytest.approx(h / 2)  # world units: the scene's kernel radius sets the voxel


@pytest.mark.parametrize("shape", [(1, 1, 1), (9, 9, 9), (17, 3, 40), (64, 64, 64), (4100, 3, 3)])
def test_the_size_bound_holds_for_every_voxel_filled(tmp_path, shape):
    """What a VDB bundle declares before it is made (issue 49, fluidcore.exports.frame_bytes):
    no grid of that shape writes more, and a full one comes within 6 % of it."""
    from fluidcore.vdb import max_file_bytes

    rng = np.random.default_rng(0)
    density = rng.random(shape, dtype=np.float32) + 0.1
    velocity = rng.random((*shape, 3), dtype=np.float32) + 0.1
    write_vdb(tmp_path / "full.vdb", {"density": density, "velocity": velocity}, np.zeros(3), 0.01)
    bound = max_file_bytes(shape, {"density": 4, "velocity": 12})
    assert (tmp_path / "full.vdb").stat().st_size <= bound < 1.06 * (tmp_path / "full.vdb").stat().st_size

"""fluidcore.exports and `fluidnexus export --format`: the 3DGS PLY read back with plyfile,
density volumes (npz, NRRD) whose mass is the particles' mass, the default (last) frame, and
numbered sequences with `--frames` (tests/fluidcore/test_vdb.py reads the OpenVDB files back)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from plyfile import PlyData
from typer.testing import CliRunner

from fluidcore.exports import EXPORTERS, MAX_SEQUENCE_FRAMES, SH_C0, ExportError, density_grid
from fluidcore.runs import Run
from fluidnexus.cli import app

runner = CliRunner()
TOO_MANY = MAX_SEQUENCE_FRAMES + 1


def _ok(args: list[str]) -> str:
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    return result.stdout


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    folder = tmp_path_factory.mktemp("scene")
    _ok(["synth", "--out", str(folder), "--frames", "2", "--width", "32", "--height", "48", "--views", "2"])
    out = tmp_path_factory.mktemp("runs") / "run"
    # the paper model in still air (the synthetic plume's own physics): a run whose velocity is its particles'
    _ok(["reconstruct", "--cameras", str(folder / "transforms.json"), "--video", f"view_00={folder / 'videos' / 'view_00.mp4'}",
         "--frames", "0:2", "--out", str(out), "--threads", "1", "--motion", "paper"])
    return out


def test_ply_is_the_gaussian_splatting_layout(run_dir, tmp_path):
    report = json.loads(_ok(["export", str(run_dir), "--frame", "1", "--format", "ply", "--out", str(tmp_path / "f.ply"), "--json"]))
    assert report["format"] == "ply" and report["out"] == str(tmp_path / "f.ply")
    vertex = PlyData.read(str(tmp_path / "f.ply"))["vertex"]
    names = [p.name for p in vertex.properties]
    assert names == ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
                     "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    g = Run.open(run_dir).read_frame(1).gaussians
    assert vertex.count == len(g["means"]) > 0
    np.testing.assert_allclose(np.stack([vertex["x"], vertex["y"], vertex["z"]], 1), g["means"], atol=1e-6)
    colors = np.stack([vertex[f"f_dc_{i}"] for i in range(3)], 1) * SH_C0 + 0.5
    np.testing.assert_allclose(colors, np.broadcast_to(g["colors"], colors.shape), atol=1e-5)
    np.testing.assert_allclose(vertex["opacity"], g["opacity_logits"], atol=1e-6)
    np.testing.assert_allclose(np.stack([vertex[f"scale_{i}"] for i in range(3)], 1), g["log_scales"], atol=1e-6)
    quats = np.stack([vertex[f"rot_{i}"] for i in range(4)], 1)
    np.testing.assert_allclose(np.linalg.norm(quats, axis=1), 1.0, atol=1e-5)
    np.testing.assert_allclose(np.abs(np.sum(quats * g["quats"], 1)) / np.linalg.norm(g["quats"], axis=1), 1.0, atol=1e-5)


def test_density_volume_holds_the_particles_mass(run_dir, tmp_path):
    _ok(["export", str(run_dir), "--frame", "1", "--format", "density", "--out", str(tmp_path / "d.npz")])
    run = Run.open(run_dir)
    state = run.read_frame(1)
    positions = state.positions[state.alive]
    h = run.scene.physics.h
    with np.load(tmp_path / "d.npz") as data:
        density, origin, spacing = data["density"], data["origin"], float(data["spacing"])
        assert float(data["particle_mass"]) == pytest.approx((h / 2) ** 3)
    mass = density.sum(dtype=np.float64) * spacing**3
    assert mass == pytest.approx(len(positions) * (h / 2) ** 3, rel=1e-5)
    # the mass sits where the particles are: same centre of mass within a voxel
    axes = [origin[i] + spacing * np.arange(density.shape[i]) for i in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1)
    centre = (grid * density[..., None]).sum(axis=(0, 1, 2)) / density.sum()
    np.testing.assert_allclose(centre, positions.mean(axis=0), atol=spacing)
    # a particle at the rest spacing of the simulator sees density ~ its own kernel's share: finite, >= 0
    assert np.all(np.isfinite(density)) and density.min() >= 0


def test_nrrd_holds_the_same_grid(run_dir, tmp_path):
    _ok(["export", str(run_dir), "--frame", "0", "--format", "density", "--out", str(tmp_path / "d.npz")])
    _ok(["export", str(run_dir), "--frame", "0", "--format", "nrrd", "--out", str(tmp_path / "d.nrrd")])
    raw = (tmp_path / "d.nrrd").read_bytes()
    header, body = raw.split(b"\n\n", 1)
    fields = dict(line.split(": ", 1) for line in header.decode().splitlines()[1:])
    sizes = tuple(int(v) for v in fields["sizes"].split())
    volume = np.frombuffer(body, dtype="<f4").reshape(sizes, order="F")
    with np.load(tmp_path / "d.npz") as data:
        np.testing.assert_array_equal(volume, data["density"])
        origin = [float(v) for v in fields["space origin"].strip("()").split(",")]
        np.testing.assert_allclose(origin, data["origin"])


def test_density_grid_is_mass_conserving_anywhere_in_a_voxel(monkeypatch):
    rng = np.random.default_rng(0)
    points = rng.uniform(0.0, 1.0, (200, 3))
    grid = density_grid(points, h=0.1, lo=np.zeros(3), hi=np.ones(3), spacing=0.05)
    assert grid.total_mass() == pytest.approx(200 * 0.05**3, rel=1e-9)
    monkeypatch.setattr("fluidcore.exports.PARTICLE_CHUNK", 7)  # splatted 7 particles at a time: the same grid
    np.testing.assert_allclose(density_grid(points, 0.1, np.zeros(3), np.ones(3), 0.05).density, grid.density, rtol=1e-6)
    with pytest.raises(ExportError, match="voxel size must be in"):
        density_grid(points, h=0.1, lo=np.zeros(3), hi=np.ones(3), spacing=0.2)


def read_nrrd(path) -> tuple[dict[str, str], np.ndarray]:
    """A raw NRRD's header fields and its values, the first axis fastest (what NRRD readers do)."""
    header, body = path.read_bytes().split(b"\n\n", 1)
    fields = dict(line.split(": ", 1) for line in header.decode().splitlines()[1:])
    sizes = tuple(int(v) for v in fields["sizes"].split())
    return fields, np.frombuffer(body, dtype="<f4").reshape(sizes, order="F")


def test_a_run_without_air_exports_the_particles_velocity(run_dir, tmp_path):
    """Density npz and velocity NRRD: the particles' velocities, mass-weighted on the density's voxels."""
    _ok(["export", str(run_dir), "--frame", "1", "--format", "density", "--out", str(tmp_path / "d.npz")])
    _ok(["export", str(run_dir), "--frame", "1", "--format", "velocity", "--out", str(tmp_path / "v.nrrd")])
    state = Run.open(run_dir).read_frame(1)
    alive = state.alive.astype(bool)
    with np.load(tmp_path / "d.npz") as data:
        density, velocity, spacing = data["density"], data["velocity"], float(data["spacing"])
        assert str(data["velocity_source"]) == "particles" and state.air is None
    assert velocity.shape == (*density.shape, 3) and np.abs(velocity).max() > 0
    assert not velocity[density == 0].any()  # no smoke, no velocity
    # momentum is conserved as mass is: sum(density x velocity) dV = sum(mass x v)
    h = Run.open(run_dir).scene.physics.h
    np.testing.assert_allclose((density[..., None] * velocity).sum(axis=(0, 1, 2), dtype=np.float64) * spacing**3,
                               (h / 2) ** 3 * state.velocities[alive].sum(0, dtype=np.float64), rtol=1e-4, atol=1e-9)
    fields, volume = read_nrrd(tmp_path / "v.nrrd")
    assert fields["kinds"] == "3-vector domain domain domain" and fields["space directions"].startswith("none ")
    np.testing.assert_array_equal(np.moveaxis(volume, 0, 3), velocity)


def test_one_velocity_everywhere_is_that_velocity_wherever_there_is_smoke():
    rng = np.random.default_rng(1)
    points = rng.uniform(0.2, 0.8, (300, 3))
    grid = density_grid(points, 0.1, np.zeros(3), np.ones(3), 0.05, np.tile([0.5, -1.0, 2.0], (300, 1)))
    assert grid.velocity_source == "particles"
    np.testing.assert_allclose(grid.velocity[grid.density > 0], np.tile([0.5, -1.0, 2.0], ((grid.density > 0).sum(), 1)), rtol=1e-5)


def test_a_run_with_air_exports_the_airs_velocity(tmp_path):
    from tests.support.predict_scenes import plume_run

    run_dir = plume_run(tmp_path / "run", frames=2, warmup=20, quality={"air_cells": 12})
    _ok(["export", str(run_dir), "--frame", "1", "--format", "density", "--out", str(tmp_path / "d.npz")])
    _ok(["export", str(run_dir), "--frame", "1", "--format", "velocity", "--out", str(tmp_path / "v.nrrd")])
    state = Run.open(run_dir).read_frame(1)
    with np.load(tmp_path / "d.npz") as data:
        assert str(data["velocity_source"]) == "air"
        origin, spacing, velocity, density = data["origin"], float(data["spacing"]), data["velocity"], data["density"]
    # the voxel [i, j, k] holds the air's velocity at its centre: check a few against the saved air
    for index in [(0, 0, 0), tuple(np.array(density.shape) // 2), tuple(np.array(density.shape) - 1)]:
        centre = origin + spacing * np.asarray(index)
        np.testing.assert_allclose(velocity[index], state.air.velocity_at(centre[None])[0], rtol=1e-6, atol=1e-7)
    assert np.abs(velocity[density == 0]).max() > 0  # the air moves beyond the smoke too
    _, volume = read_nrrd(tmp_path / "v.nrrd")
    np.testing.assert_array_equal(np.moveaxis(volume, 0, 3), velocity)


def test_bad_format_and_frame_are_one_line_errors(run_dir, tmp_path):
    result = runner.invoke(app, ["export", str(run_dir), "--frame", "1", "--format", "obj", "--out", str(tmp_path / "x")])
    assert result.exit_code == 2 and f"format must be one of {', '.join(EXPORTERS)}" in result.output
    result = runner.invoke(app, ["export", str(run_dir), "--frame", "9", "--format", "ply", "--out", str(tmp_path / "x.ply")])
    assert result.exit_code == 2 and "frame 9 is not a finished frame" in result.output
    assert not (tmp_path / "x.ply").exists()


def test_export_artifacts_hold_the_last_frame_in_every_format_and_every_frame_as_vdb(run_dir, tmp_path):
    from fluidcore.exports import export_artifacts

    files = export_artifacts(run_dir, tmp_path / "exports")
    assert sorted(p.name for p in files) == sorted(
        ["state_000001.npz", "splats_000001.ply", "density_000001.npz", "density_000001.nrrd",
         "velocity_000001.nrrd", "smoke_000000.vdb", "smoke_000001.vdb"]
    )
    assert all(p.stat().st_size > 0 for p in files)


def test_export_writes_the_last_frame_unless_told(run_dir, tmp_path):
    report = json.loads(_ok(["export", str(run_dir), "--format", "npz", "--out", str(tmp_path / "last.npz"), "--json"]))
    assert report["frame"] == 1 == Run.open(run_dir).frames()[-1]
    with np.load(tmp_path / "last.npz") as data:
        np.testing.assert_array_equal(data["positions"], Run.open(run_dir).read_frame(1).export()["positions"])


@pytest.mark.parametrize(("fmt", "names"), [
    ("ply", ["splats_000000.ply", "splats_000001.ply"]),
    ("nrrd", ["density_000000.nrrd", "density_000001.nrrd"]),
    ("density", ["density_000000.npz", "density_000001.npz"]),
])
def test_frames_write_a_numbered_sequence(run_dir, tmp_path, fmt, names):
    out = tmp_path / "seq"
    report = json.loads(_ok(["export", str(run_dir), "--frames", "0:2", "--format", fmt, "--out", str(out), "--json"]))
    assert report["files"] == names and sorted(p.name for p in out.iterdir()) == names
    one = tmp_path / f"one{EXPORTERS[fmt].suffix}"
    _ok(["export", str(run_dir), "--frame", "1", "--format", fmt, "--out", str(one)])
    if fmt == "density":  # a zip archive: its members carry the time they were written
        with np.load(out / names[1]) as seq, np.load(one) as single:
            assert seq["density"].any() and np.array_equal(seq["density"], single["density"])
    else:
        assert (out / names[1]).read_bytes() == one.read_bytes()  # the sequence's frame 1 is frame 1


@pytest.mark.parametrize(("args", "message"), [
    (["--frames", "0:3"], "frames 0:3: frame 2 is not a finished frame"),
    (["--frames", "1:1"], "frames must satisfy 0 <= START < END"),
    (["--frames", "a:b"], "frames must look like START:END"),
    (["--frames", f"0:{TOO_MANY}"], f"frames 0:{TOO_MANY} is {TOO_MANY} frames; a sequence holds at most {MAX_SEQUENCE_FRAMES}"),
    (["--frames", "0:1", "--frame", "0"], "give --frame (one file) or --frames START:END (a sequence), not both"),
])
def test_bad_frame_ranges_are_refused_before_writing(run_dir, tmp_path, args, message):
    result = runner.invoke(app, ["export", str(run_dir), "--format", "ply", "--out", str(tmp_path / "seq"), *args])
    assert result.exit_code == 2 and f"error: {message}" in result.output, result.output
    assert not (tmp_path / "seq").exists()


def test_a_sequence_into_a_file_is_refused(run_dir, tmp_path):
    (tmp_path / "taken").write_text("mine")
    result = runner.invoke(app, ["export", str(run_dir), "--frames", "0:1", "--format", "ply", "--out", str(tmp_path / "taken")])
    assert result.exit_code == 2 and "is a file; a sequence goes into a folder" in result.output
    assert (tmp_path / "taken").read_text() == "mine"


def test_a_finer_voxel_size_keeps_the_mass_on_more_voxels(run_dir, tmp_path):
    h = Run.open(run_dir).scene.physics.h
    coarse, fine = tmp_path / "coarse.npz", tmp_path / "fine.npz"
    _ok(["export", str(run_dir), "--frame", "1", "--format", "density", "--out", str(coarse)])
    _ok(["export", str(run_dir), "--frame", "1", "--format", "density", "--voxel-size", str(h / 4), "--out", str(fine)])
    with np.load(coarse) as a, np.load(fine) as b:
        assert float(a["spacing"]) == pytest.approx(h / 2) and float(b["spacing"]) == pytest.approx(h / 4)
        assert all(nb >= 2 * na - 2 for na, nb in zip(a["density"].shape, b["density"].shape, strict=True))
        mass = lambda d: float(d["density"].sum(dtype=np.float64) * float(d["spacing"]) ** 3)  # noqa: E731
        assert mass(b) == pytest.approx(mass(a), rel=1e-4) and mass(a) > 0


@pytest.mark.parametrize(("fmt", "voxel", "message"), [
    ("ply", "0.01", "voxel size: ply holds particles, not a grid; a voxel size applies to density, nrrd, velocity, vdb"),
    ("vdb", "0", "voxel size must be in (0, "),
    ("vdb", "5", "voxel size must be in (0, "),
])
def test_a_voxel_size_that_cannot_be_used_is_refused(run_dir, tmp_path, fmt, voxel, message):
    result = runner.invoke(app, ["export", str(run_dir), "--format", fmt, "--voxel-size", voxel, "--out", str(tmp_path / "x")])
    assert result.exit_code == 2 and message in result.output, result.output
    assert not (tmp_path / "x").exists()


def test_a_grid_over_the_voxel_cap_names_the_smallest_voxel_that_fits():
    from fluidcore.exports import MAX_VOXELS, grid_shape

    lo, hi, h = np.zeros(3), np.ones(3), 0.04
    with pytest.raises(ExportError, match=r"exceeds 16777216 voxels \(256\^3\); the smallest that fits this box is ") as caught:
        grid_shape(h, lo, hi, 0.002)
    fits = float(str(caught.value).rsplit(" ", 1)[-1])
    assert np.prod(grid_shape(h, lo, hi, fits)) <= MAX_VOXELS
    with pytest.raises(ExportError, match="exceeds"):  # and it is the smallest, to its 3 digits
        grid_shape(h, lo, hi, fits * 0.98)


@pytest.mark.parametrize("voxel", [1e-9, 1e-300, 5e-324])
def test_a_voxel_far_too_small_is_refused_not_overflowed(voxel):
    """Issue 49 item 4: at 1e-9 numpy's int64 product of the shape wrapped to a negative count,
    which passed the cap; the bundle job then failed with an internal error."""
    from fluidcore.exports import grid_shape

    with pytest.raises(ExportError, match=r"exceeds 16777216 voxels|not a finite number of voxels"):
        grid_shape(0.04, np.zeros(3), np.array([1.0, 1.5, 1.0]), voxel)


def _bundle(run_dir, out, *args):
    return json.loads(_ok(["export", str(run_dir), "--bundle", "--out", str(out), "--json", *args]))


def test_a_vdb_bundle_holds_every_frame_and_says_what_it_holds(run_dir, tmp_path):
    import zipfile

    from fluidcore.exports import BUNDLE_MANIFEST, BUNDLE_SPACING

    run = Run.open(run_dir)
    report = _bundle(run_dir, tmp_path / "b.zip", "--format", "vdb")
    assert report["frames"] == [0, 2] and report["bytes"] == (tmp_path / "b.zip").stat().st_size
    with zipfile.ZipFile(tmp_path / "b.zip") as bundle:
        assert bundle.namelist() == ["smoke_000000.vdb", "smoke_000001.vdb", BUNDLE_MANIFEST]
        about = json.loads(bundle.read(BUNDLE_MANIFEST))
        single = tmp_path / "one.vdb"
        _ok(["export", str(run_dir), "--frame", "1", "--format", "vdb", "--voxel-size", repr(about["voxel_size"]),
             "--out", str(single)])
        zipped, alone = bundle.read("smoke_000001.vdb"), single.read_bytes()
        uuid_at = 8 + 4 + 4 + 4 + 1  # magic, file version, library version, offsets flag; then a 36-character uuid
        assert len(zipped) == len(alone) and zipped[:uuid_at] == alone[:uuid_at]
        assert zipped[uuid_at + 36 :] == alone[uuid_at + 36 :]  # frame 1 at the bundle's voxel size
    assert about["voxel_size"] == pytest.approx(BUNDLE_SPACING * run.scene.physics.h, rel=1e-3)  # to the 4 digits its name states
    assert about["fps"] == run.fps and about["up"] == list(run.scene.up) and about["format"] == "vdb"
    assert about["files"] == ["smoke_000000.vdb", "smoke_000001.vdb"] and about["frames"] == [0, 2]


def test_a_ply_bundle_of_chosen_frames_has_no_voxel_size(run_dir, tmp_path):
    import zipfile

    report = _bundle(run_dir, tmp_path / "p.zip", "--format", "ply", "--frames", "1:2")
    assert report["voxel_size"] is None and report["frames"] == [1, 2]
    with zipfile.ZipFile(tmp_path / "p.zip") as bundle:
        assert bundle.namelist() == ["splats_000001.ply", "bundle.json"]
        assert bundle.read("splats_000001.ply")[:3] == b"ply"


@pytest.mark.parametrize(("args", "message"), [
    (["--format", "nrrd"], "format must be one of vdb, ply, density, got 'nrrd'"),
    (["--format", "vdb", "--frames", "0:3"], "frames 0:3: frame 2 is not a finished frame"),
    (["--format", "vdb", "--frame", "1"], "a bundle holds a sequence"),
])
def test_a_bundle_that_cannot_be_made_is_refused_before_writing(run_dir, tmp_path, args, message):
    result = runner.invoke(app, ["export", str(run_dir), "--bundle", "--out", str(tmp_path / "b.zip"), *args])
    assert result.exit_code == 2 and message in result.output, result.output
    assert not (tmp_path / "b.zip").exists()


def test_a_bundle_over_the_byte_budget_is_refused_from_the_manifest_alone(run_dir, monkeypatch):
    from fluidcore import exports

    monkeypatch.setattr(exports, "MAX_BUNDLE_BYTES", 1_000_000)
    with pytest.raises(ExportError, match=r"2 frames of \d+x\d+x\d+ voxels as density may take .* GiB, more than a "
                                          r"bundle's 0.000931 GiB; choose fewer frames or a larger voxel size"):
        exports.plan_bundle(Run.open(run_dir), "density")
    assert exports.plan_bundle(Run.open(run_dir), "ply").name == "ply_f000000-000002.zip"


@pytest.mark.parametrize(("fmt", "voxel"), [("density", None), ("vdb", None), ("ply", None), ("density", 0.02)])
def test_a_bundles_declared_bytes_bound_the_zip_it_writes(run_dir, tmp_path, fmt, voxel):
    """Issue 49 item 5: the size is declared before work (what the owner's quota reserves), so
    it must hold for what is then written."""
    from fluidcore.exports import export_bundle, plan_bundle

    plan = plan_bundle(Run.open(run_dir), fmt, voxel_size=voxel)
    written = export_bundle(run_dir, plan, tmp_path / plan.name).stat().st_size
    assert 0 < written <= plan.bytes


@pytest.mark.parametrize("plan", [("vdb", (0, 30), 0.01), ("ply", (12, 600), None), ("density", (0, 1), 1.25e-05)])
def test_a_bundles_name_states_its_plan(plan):
    from fluidcore.exports import BundlePlan

    made = BundlePlan(*plan, None)
    assert BundlePlan.from_name(made.name) == made
    with pytest.raises(ExportError, match="is not a bundle's name"):
        BundlePlan.from_name(made.name.replace(".zip", ".tar"))

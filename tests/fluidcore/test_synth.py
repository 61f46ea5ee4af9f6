"""The synthetic scene: a rising plume, rendered from several cameras, written as an ordinary input scene."""

from __future__ import annotations

import numpy as np
import pytest

from fluidcore import cameras as camera_io
from fluidcore import synth, video


@pytest.fixture(scope="module")
def scene() -> synth.SynthScene:
    return synth.generate(synth.SynthSpec(frames=4, width=32, height=48, views=3, fps=10.0))


def test_plume_rises_from_the_source(scene):
    spec = scene.spec
    assert len(scene.positions) == spec.frames
    counts = [len(p) for p in scene.positions]
    assert counts == sorted(counts) and counts[-1] > counts[0]  # the source keeps seeding
    up_velocity = np.concatenate(scene.velocities)[:, 1]
    assert np.mean(up_velocity > 0) > 0.9
    first_height = scene.positions[0][:, 1].mean()
    assert scene.positions[-1][: len(scene.positions[0]), 1].mean() > first_height
    lo, hi = spec.box().lo, spec.box().hi
    for p in scene.positions:
        assert np.all(p >= lo) and np.all(p <= hi)


def test_every_view_sees_dark_smoke_on_white(scene):
    for name, frames in scene.videos.items():
        assert frames.shape == (4, 48, 32, 3), name
        assert frames.max() == 255  # background
        assert frames.min() < 200  # smoke is visible
        assert np.array_equal(frames[..., 0], frames[..., 2])  # grey


def test_written_scene_reads_back_through_the_public_loaders(scene, tmp_path):
    path = synth.write(scene, tmp_path / "scene")
    loaded = camera_io.load(path)
    assert sorted(loaded) == sorted(scene.cameras)
    for name, camera in scene.cameras.items():
        np.testing.assert_allclose(loaded[name].world_to_camera, camera.world_to_camera, atol=1e-9)
        assert loaded[name].file_path == f"videos/{name}.mp4"
        frames = video.read_frames(tmp_path / "scene" / loaded[name].file_path)
        assert frames.shape == scene.videos[name].shape
        assert np.abs(frames.astype(int) - scene.videos[name]).mean() < 4  # H.264 at default quality
    lo, hi = camera_io.scene_box(path)
    np.testing.assert_allclose(lo, scene.spec.box().lo)
    np.testing.assert_allclose(hi, scene.spec.box().hi)
    truth = np.load(tmp_path / "scene" / "truth" / "frame_000003.npz")
    np.testing.assert_array_equal(truth["velocities"], scene.velocities[3])


@pytest.mark.parametrize("field, value", [("frames", 0), ("source_radius", -1.0), ("smoke_opacity", 1.0)])
def test_bad_specs_name_the_field(field, value):
    with pytest.raises(synth.SynthError, match=field):
        synth.SynthSpec(**{field: value})

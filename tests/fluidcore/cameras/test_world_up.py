"""Which way is up (`fluidcore.cameras.world_up`): the user's axis, else the camera file's `up`,
else the cameras' mean image up when it names an axis, else +y; and a scene turned to +z up (its
cameras and box rotated, as a Blender export writes them) reconstructs the same smoke, turned."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from fluidcore import synth
from fluidcore.cameras import Camera, CameraError, look_at, scene_box, write_transforms
from fluidcore.cameras.world_up import cameras_up, declared_up, parse_axis, world_up

# +90 degrees about x: y (up) goes to z, z to -y
TURN = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


def _rig(up: tuple[float, float, float] = (0.0, 1.0, 0.0), tilt: float = 0.2) -> dict[str, Camera]:
    like = Camera("like", 50.0, 50.0, 16.0, 16.0, 32, 32, np.eye(4))
    up_v = np.asarray(up)
    side = np.array([1.0, 0.0, 0.0]) if abs(up_v[0]) < 0.5 else np.array([0.0, 0.0, 1.0])
    other = np.cross(up_v, side)
    eyes = [2.0 * (np.cos(a) * side + np.sin(a) * other) + tilt * up_v for a in np.linspace(0.0, np.pi, 5)]
    return {f"c{i}": look_at(eye, np.zeros(3), up, like, f"c{i}") for i, eye in enumerate(eyes)}


def test_parse_axis_takes_names_and_axis_vectors_only() -> None:
    assert parse_axis("+z", "f") == "+z" and parse_axis("z", "f") == "+z" and parse_axis(" -Y ", "f") == "-y"
    assert parse_axis([0, 0, 2], "f") == "+z" and parse_axis((0.0, -1.0, 0.001), "f") == "-y"
    for bad, message in (("up", "is not an axis"), ([0, 1, 1], "degrees off the nearest axis"), ([0, 0, 0], "three numbers"),
                         ([1, 2], "three numbers"), (None, "three numbers"), ([float("nan"), 1, 0], "three numbers")):
        with pytest.raises(CameraError, match=message):
            parse_axis(bad, "cameras.json: up")


def test_the_cameras_name_their_up_when_they_agree_on_an_axis() -> None:
    assert cameras_up(_rig()) == "+y"
    assert cameras_up(_rig((0.0, 0.0, 1.0))) == "+z"  # Blender's world
    assert cameras_up(_rig((0.0, -1.0, 0.0))) == "-y"  # a raw COLMAP frame, image y down
    # one camera looking down at the smoke by 45 degrees is as near a horizontal axis as up: no axis
    like = Camera("like", 50.0, 50.0, 16.0, 16.0, 32, 32, np.eye(4))
    assert cameras_up([look_at((0.0, 2.0, 2.0), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0), like, "steep")]) is None
    # phones rolled every which way agree on nothing
    rolled = [look_at((2 * np.cos(a), 0.0, 2 * np.sin(a)), (0, 0, 0),
                      np.cos(roll) * np.array([0.0, 1.0, 0.0]) + np.sin(roll) * np.array([-np.sin(a), 0.0, np.cos(a)]), like, f"r{i}")
              for i, (a, roll) in enumerate(zip(np.linspace(0, np.pi, 6), np.linspace(0, 2 * np.pi, 6, endpoint=False)))]
    assert cameras_up(rolled) is None


def test_world_up_in_order_given_file_cameras_default(tmp_path: Path) -> None:
    cameras = _rig((0.0, 0.0, 1.0))
    plain = write_transforms(tmp_path / "plain.json", cameras)
    stated = write_transforms(tmp_path / "stated.json", cameras, up=[0, 0, -1])
    assert world_up(plain, cameras) .axis == "+z" and world_up(plain, cameras).found == "cameras"
    assert world_up(stated, cameras).axis == "-z" and world_up(stated, cameras).found == "camera file"
    assert world_up(stated, cameras, "+x").axis == "+x" and world_up(stated, cameras, "+x").found == "given"
    assert declared_up(plain) is None and world_up(plain, {}).axis == "+y" and world_up(plain, {}).found == "default"
    bad = write_transforms(tmp_path / "bad.json", cameras, up="sky")
    with pytest.raises(CameraError, match="bad.json: up: 'sky' is not an axis"):
        world_up(bad, cameras)


def _turned(folder: Path) -> Path:
    """The synth scene's camera file with the world turned by TURN: y up becomes z up."""
    data = json.loads((folder / "transforms.json").read_text())
    for frame in data["frames"]:
        matrix = np.asarray(frame["transform_matrix"])
        matrix[:3, :3], matrix[:3, 3] = TURN @ matrix[:3, :3], TURN @ matrix[:3, 3]
        frame["transform_matrix"] = matrix.tolist()
    corners = TURN @ np.array(scene_box(folder / "transforms.json")).T  # the synth's voxel box, as min/max
    data.pop("voxel_scale"), data.pop("voxel_matrix")
    data["scene_box"] = {"min": corners.min(1).tolist(), "max": corners.max(1).tolist()}
    out = folder / "turned.json"
    out.write_text(json.dumps(data))
    return out


def test_a_scene_turned_to_z_up_reconstructs_the_same_smoke_turned(tmp_path: Path) -> None:
    from fluidcore.health import report
    from fluidcore.reconstruct.job import run_reconstruct
    from fluidcore.runs import Run
    from fluidcore.spec.reconstruct import get

    folder = synth.write(synth.generate(synth.SynthSpec(frames=3, width=32, height=48, views=3)), tmp_path / "scene").parent
    quick = get("preview").with_overrides(position_iterations=2, appearance_iterations=2, first_frame_factor=1)
    video = {"view_01": folder / "videos" / "view_01.mp4"}
    runs = {name: Run.open(run_reconstruct(path, video, tmp_path / name, quality=quick, frames=(0, 3)))
            for name, path in (("plain", folder / "transforms.json"), ("turned", _turned(folder)))}
    plain, turned = runs["plain"], runs["turned"]
    assert plain.scene.up == (0.0, 1.0, 0.0) and turned.scene.up == (0.0, 0.0, 1.0)
    assert turned.settings.capture.up_axis == "+z" and turned.settings.capture.up_found == "cameras"
    np.testing.assert_allclose(turned.scene.source.center, TURN @ np.asarray(plain.scene.source.center), atol=2e-3)
    assert turned.scene.source.radius == pytest.approx(plain.scene.source.radius, rel=0.02)
    assert turned.scene.physics.gravity == pytest.approx(tuple(TURN @ np.asarray(plain.scene.physics.gravity)), abs=1e-9)
    fit = {name: np.mean([frame["losses"]["input_psnr"] for frame in run.manifest["frames"]]) for name, run in runs.items()}
    assert fit["turned"] == pytest.approx(fit["plain"], abs=0.3), fit
    last = {name: run.read_frame(2) for name, run in runs.items()}
    assert len(last["turned"].positions) == len(last["plain"].positions)
    # particle by particle, to float rounding (the source seeds the turned draw, fluidcore.physics.source)
    np.testing.assert_allclose(last["turned"].positions, last["plain"].positions @ TURN.T, atol=5e-3)
    checks = {check["name"]: check for check in report(turned, audience="cli")["checks"]}
    assert checks["world up"]["level"] == "note" and "+z from the cameras" in checks["world up"]["message"]

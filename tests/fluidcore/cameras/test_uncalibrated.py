"""Clips without calibration: `fluidnexus cameras single` (field of view + declared box),
`fluidnexus cameras colmap` (a rig calibrated from its static background) and lens
undistortion with OpenCV."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from fluidcore import cameras, video
from fluidcore.cameras import Camera, CameraError, check_box_visible, look_at, scene_box, undistort_frames
from fluidcore.cameras.single import single_camera
from fluidnexus.cli import app

runner = CliRunner()


# --- one camera from its field of view -----------------------------------------------------------------
def test_single_camera_on_the_fluidnexus_smoke_clip(realdata: Path, tmp_path: Path) -> None:
    clip = realdata / "fluidnexus_smoke_blue" / "videos" / "input_view_02.mp4"
    out = tmp_path / "transforms.json"
    result = runner.invoke(app, ["cameras", "single", "--video", str(clip), "--fov", "40", "--distance", "2", "--out", str(out), "--json"])
    assert result.exit_code == 0, result.output
    report = json.loads(result.stdout)
    loaded = cameras.load(out)
    camera = loaded["input_view_02"]
    info = video.probe(clip)
    assert (camera.width, camera.height) == (info.width, info.height) == (324, 580)
    assert camera.fx == pytest.approx(0.5 * 324 / math.tan(math.radians(20)))
    np.testing.assert_allclose(camera.center(), [0, 0, 2], atol=1e-12)
    assert (out.parent / json.loads(out.read_text())["frames"][0]["file_path"]).resolve() == clip.resolve()
    lo, hi = scene_box(out)
    assert report["scene_box"] == {"min": lo.tolist(), "max": hi.tolist()}
    # the box is the frame's cross-section at the scene centre: its corners there project to the image corners
    corners = np.array([[lo[0], lo[1], 0.0], [hi[0], hi[1], 0.0]])
    uv, depth = camera.project_numpy(corners)
    np.testing.assert_allclose(uv, [[0, info.height], [info.width, 0]], atol=1e-9)
    assert hi[1] - lo[1] > hi[0] - lo[0]  # a portrait clip: taller than wide
    check_box_visible(loaded, (lo, hi))


@pytest.mark.parametrize(("up", "image_direction"), [("up", (0, -1)), ("down", (0, 1)), ("left", (-1, 0)), ("right", (1, 0))])
def test_single_camera_up_says_where_world_up_points_in_the_image(up: str, image_direction) -> None:
    camera, (lo, hi) = single_camera("c", 200, 100, 60.0, 1.0, up)
    uv, _ = camera.project_numpy(np.array([[0.0, 0.0, 0.0], [0.0, 0.1, 0.0]]))
    step = (uv[1] - uv[0]) / np.linalg.norm(uv[1] - uv[0])
    np.testing.assert_allclose(step, image_direction, atol=1e-9)
    across = 100 if up in ("left", "right") else 200  # the image side that spans world x
    assert hi[0] - lo[0] == pytest.approx(across / camera.fx)


def test_single_camera_rejects_bad_parameters(tmp_path: Path) -> None:
    for kwargs, message in (({"fov_deg": 0.0}, "fov"), ({"fov_deg": 50, "distance": -1}, "distance"), ({"fov_deg": 50, "up": "north"}, "up")):
        with pytest.raises(CameraError, match=message):
            single_camera("c", 64, 48, **kwargs)
    clip = tmp_path / "clip.mp4"
    video.write_mp4(clip, np.zeros((2, 16, 16, 3), np.uint8))
    result = runner.invoke(app, ["cameras", "single", "--video", str(clip), "--fov", "200", "--out", str(tmp_path / "t.json")])
    assert result.exit_code == 2 and "error: fov must be between" in result.output
    assert not (tmp_path / "t.json").exists()


def test_scene_box_field_is_validated(tmp_path: Path) -> None:
    camera, _ = single_camera("c", 64, 48, 50.0)
    path = cameras.write_transforms(tmp_path / "t.json", {"c": camera}, scene_box={"min": [0, 0, 0], "max": [1, -1, 1]})
    with pytest.raises(CameraError, match="scene_box: min .* must be below max"):
        scene_box(path)


# --- lens distortion ------------------------------------------------------------------------------------
def _texture(height: int, width: int, seed: int = 0) -> np.ndarray:
    """Smooth random texture (uint8 RGB): interpolation errors stay small, structure is everywhere."""
    import cv2

    rng = np.random.default_rng(seed)
    coarse = rng.uniform(0, 255, (height // 8, width // 8, 3)).astype(np.float32)
    return np.clip(cv2.resize(coarse, (width, height), interpolation=cv2.INTER_CUBIC), 0, 255).astype(np.uint8)


def test_undistortion_round_trip() -> None:
    """Distort a pinhole image through the lens model, undistort it: the pinhole image comes back."""
    import cv2

    from fluidcore.cameras.undistort import opencv_matrix

    lens = Camera("lens", 150.0, 150.0, 80.0, 60.0, 160, 120, np.eye(4), distortion=(-0.25, 0.08, 0.001, -0.001))
    pinhole = _texture(120, 160)
    # Each pixel of the distorted frame shows the pinhole pixel its ray undistorts to.
    grid = np.stack(np.meshgrid(np.arange(160.0), np.arange(120.0)), -1).reshape(-1, 1, 2)
    k = opencv_matrix(lens)
    source = cv2.undistortPoints(grid, k, np.asarray(lens.distortion), P=k).reshape(120, 160, 2).astype(np.float32)
    distorted = cv2.remap(pinhole, source[..., 0], source[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    restored = undistort_frames(lens, distorted[None])[0]
    inner = (slice(15, -15), slice(20, -20))
    error = np.abs(restored[inner].astype(float) - pinhole[inner]).mean()
    untouched = np.abs(distorted[inner].astype(float) - pinhole[inner]).mean()
    assert error < 2.0 < 4 * error < untouched, (error, untouched)
    assert undistort_frames(lens.pinhole(), distorted) is distorted  # a pinhole passes frames through
    half = undistort_frames(lens, cv2.resize(distorted, (80, 60), interpolation=cv2.INTER_AREA))  # any size
    assert half.shape == (60, 80, 3)


def test_distorted_camera_files_load_and_round_trip(tmp_path: Path) -> None:
    camera = Camera("cam", 100.0, 100.0, 32.0, 24.0, 64, 48, np.eye(4), distortion=(-0.1, 0.02, 0.0, 0.0, 0.003))
    path = cameras.write_transforms(tmp_path / "t.json", {"cam": camera})
    assert json.loads(path.read_text())["camera_model"] == "OPENCV"
    assert cameras.load(path)["cam"] == camera
    assert cameras.load(path)["cam"].pinhole().distortion == ()
    data = json.loads(path.read_text())
    data["frames"][0]["k4"] = 0.1
    (tmp_path / "fisheye.json").write_text(json.dumps(data))
    with pytest.raises(CameraError, match="k4 = 0.1: a fisheye coefficient"):
        cameras.load(tmp_path / "fisheye.json")


# --- a rig calibrated by COLMAP -------------------------------------------------------------------------
ROOM = 1.2  # half-size of the textured room around the rig's target (world units)


def _room_view(camera: Camera, texture: np.ndarray) -> np.ndarray:
    """Ray-cast a camera's view of a closed box room whose walls carry a texture (one per wall)."""
    v, u = np.mgrid[0 : camera.height, 0 : camera.width] + 0.5
    rays_cam = np.stack([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, np.ones_like(u)], -1)
    rays = rays_cam @ camera.world_to_camera[:3, :3]  # rotate to world: R^T d (row vectors)
    origin = camera.center()
    with np.errstate(divide="ignore", invalid="ignore"):
        hits = [np.where(rays[..., a:a + 1] != 0, (np.sign(rays[..., a:a + 1]) * ROOM - origin[a]) / rays[..., a:a + 1], np.inf) for a in range(3)]
    t = np.concatenate(hits, -1)
    wall = np.argmin(t, -1)
    point = origin + np.take_along_axis(t, wall[..., None], -1) * rays
    size = texture.shape[1]
    image = np.zeros((camera.height, camera.width, 3), np.uint8)
    for a in range(3):
        s, r = [b for b in range(3) if b != a]
        side = (rays[..., a] > 0).astype(int)
        i = np.clip(((point[..., s] + ROOM) / (2 * ROOM) * (size - 1)).astype(int), 0, size - 1)
        j = np.clip(((point[..., r] + ROOM) / (2 * ROOM) * (size - 1)).astype(int), 0, size - 1)
        mask = wall == a
        image[mask] = texture[2 * a + side[mask], i[mask], j[mask]]
    return image


def test_colmap_calibrates_a_synthetic_rig(tmp_path: Path) -> None:
    like = Camera("like", 220.0, 220.0, 160.0, 120.0, 320, 240, np.eye(4))
    rig = [look_at([0.8 * math.sin(a), 0.15 * i - 0.2, 0.8 * math.cos(a)], [0, 0, 0], [0, 1, 0], like, f"cam{i}")
           for i, a in enumerate(np.radians([-40, -20, 0, 20, 40]))]
    textures = np.stack([_texture(512, 512, seed) for seed in range(6)])
    rng = np.random.default_rng(1)
    videos = {}
    for camera in rig:
        background = _room_view(camera, textures)
        frames = np.repeat(background[None], 4, axis=0)
        frames[1, 100:140, 140:180] = rng.integers(0, 255, (40, 40, 3))  # a passing disturbance the median drops
        videos[camera.name] = video.write_mp4(tmp_path / f"{camera.name}.mp4", frames)
    out = tmp_path / "transforms.json"
    args = ["cameras", "colmap", "--out", str(out), "--distance", "0.8", "--camera-model", "PINHOLE", "--json"]
    result = runner.invoke(app, [*args, *(a for name, path in videos.items() for a in ("--video", f"{name}={path}"))])
    assert result.exit_code == 0, result.output
    loaded = cameras.load(out)
    assert sorted(loaded) == [c.name for c in rig]
    # Up to the similarity COLMAP cannot know, the recovered rig is the true one: compare shapes.
    truth = np.array([c.center() for c in rig])
    found = np.array([loaded[c.name].center() for c in rig])
    truth_shape = (truth - truth.mean(0)) / np.linalg.norm(truth - truth.mean(0))
    found_shape = (found - found.mean(0)) / np.linalg.norm(found - found.mean(0))
    u, _, vt = np.linalg.svd(found_shape.T @ truth_shape)
    aligned = found_shape @ (u @ vt)
    assert np.abs(aligned - truth_shape).max() < 0.02
    # our world convention: up is +y, cameras 0.8 from the origin on average, looking towards it
    for camera in loaded.values():
        assert -camera.world_to_camera[1, :3] @ [0, 1, 0] > 0.95
        assert camera.forward() @ -camera.center() / np.linalg.norm(camera.center()) > 0.95
    assert np.mean(np.linalg.norm(found, axis=1)) == pytest.approx(0.8, rel=1e-6)
    relative = [np.degrees(np.arccos(np.clip((np.trace(loaded[a.name].world_to_camera[:3, :3] @ loaded[b.name].world_to_camera[:3, :3].T) - 1) / 2, -1, 1)))
                for a, b in zip(rig, rig[1:])]
    expected = [np.degrees(np.arccos(np.clip((np.trace(a.world_to_camera[:3, :3] @ b.world_to_camera[:3, :3].T) - 1) / 2, -1, 1)))
                for a, b in zip(rig, rig[1:])]
    np.testing.assert_allclose(relative, expected, atol=1.0)
    assert json.loads(result.stdout)["scene_box"] is not None


def test_colmap_needs_two_views(tmp_path: Path) -> None:
    clip = video.write_mp4(tmp_path / "a.mp4", np.zeros((2, 16, 16, 3), np.uint8))
    result = runner.invoke(app, ["cameras", "colmap", "--video", f"a={clip}", "--out", str(tmp_path / "t.json")])
    assert result.exit_code == 2 and "needs 2 to" in result.output


def test_devdata_scene_box_is_read(tmp_path: Path) -> None:
    devdata = Path(__file__).resolve().parents[3].parent / "shared" / "devdata" / "phiflow_D" / "D" / "transforms.json"
    if not devdata.is_file():
        pytest.skip("../shared/devdata not present")
    lo, hi = scene_box(devdata)
    np.testing.assert_allclose(lo, [0.09, 0.015, -0.51])
    np.testing.assert_allclose(hi, [0.59, 0.765, -0.01])

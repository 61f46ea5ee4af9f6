"""fluidcore.cameras: the Camera type, its readers (nerfstudio, PINF, COLMAP), validation and boxes."""

from __future__ import annotations

import json
import math
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch

from fluidcore import cameras
from fluidcore.cameras import (
    Camera,
    CameraError,
    box_center,
    check_box_visible,
    check_video_size,
    frusta_box,
    look_at,
    orbit,
    scene_box,
)

PLUME_BASE = np.array([0.339, -0.007, -0.226])  # triangulated from the 5 GT views (realdata README §3)
OPENGL_FLIP = np.diag([1.0, -1.0, -1.0, 1.0])


def _camera(name: str = "cam", width: int = 64, height: int = 48) -> Camera:
    return Camera(name, 80.0, 82.0, 31.0, 25.0, width, height, np.eye(4))


def _ring(n: int = 4, radius: float = 3.0) -> list[Camera]:
    """n cameras on a circle around the origin, all looking at it."""
    like = _camera()
    return [
        look_at([radius * math.cos(a), 0.5, radius * math.sin(a)], [0, 0, 0], [0, 1, 0], like, f"cam{i}")
        for i, a in enumerate(np.linspace(0, 2 * math.pi, n, endpoint=False))
    ]


def _ray_hits_box(origin: np.ndarray, direction: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> bool:
    """Slab test: does the ray origin + s * direction, s > 0, cross the box?"""
    with np.errstate(divide="ignore"):
        t1, t2 = (lo - origin) / direction, (hi - origin) / direction
    near, far = np.max(np.minimum(t1, t2)), np.min(np.maximum(t1, t2))
    return bool(far >= max(near, 0.0))


# --- the shared ScalarFlow cameras (the done-when check) -------------------------------------
def test_scalarflow_cameras_see_the_scene_box(realdata: Path) -> None:
    path = realdata / "scalarflow" / "transforms.json"
    loaded = cameras.load(path)
    assert sorted(loaded) == [f"view_0{k}" for k in range(5)]
    box = scene_box(path)
    assert box is not None
    lo, hi = box
    assert np.all(lo < PLUME_BASE) and np.all(PLUME_BASE < hi)
    points = torch.tensor(np.stack([box_center(box), PLUME_BASE]), dtype=torch.float64)
    for camera in loaded.values():
        assert (camera.width, camera.height) == (648, 1160)
        uv, depth = camera.project(points)
        assert torch.all(depth > 0)
        assert torch.all((uv[:, 0] >= 0) & (uv[:, 0] < camera.width)), camera.name
        assert torch.all((uv[:, 1] >= 0) & (uv[:, 1] < camera.height)), camera.name
        assert _ray_hits_box(camera.center(), camera.forward(), lo, hi), f"{camera.name} does not look at the box"


def test_wrong_axis_convention_is_caught(realdata: Path, tmp_path: Path) -> None:
    """The same poses stored in OpenCV axes under a nerfstudio label load, but look away."""
    path = realdata / "scalarflow" / "transforms.json"
    box = scene_box(path)
    check_box_visible(cameras.load(path), box)
    data = json.loads(path.read_text())
    for frame in data["frames"]:
        frame["transform_matrix"] = (np.asarray(frame["transform_matrix"]) @ OPENGL_FLIP).tolist()
    wrong = cameras.load(_write(tmp_path / "transforms.json", data))
    with pytest.raises(CameraError, match="view_00, view_01, view_02, view_03, view_04 do not see"):
        check_box_visible(wrong, box)


def test_scalarflow_frusta_overlap_contains_the_plume(realdata: Path) -> None:
    loaded = cameras.load(realdata / "scalarflow" / "transforms.json")
    lo, hi = frusta_box(loaded)
    assert np.all(lo < PLUME_BASE) and np.all(PLUME_BASE < hi)
    # The overlap is a bounded region a few times the plume's size, not the whole room.
    assert np.all(hi - lo < 3.0)


# --- Camera geometry ---------------------------------------------------------------------------------
def test_look_at_follows_opencv_axes() -> None:
    camera = look_at([0.0, 0.0, -5.0], [0.0, 0.0, 0.0], [0.0, 1.0, 0.0], _camera(), "front")
    np.testing.assert_allclose(camera.center(), [0.0, 0.0, -5.0], atol=1e-12)
    np.testing.assert_allclose(camera.camera_to_world() @ camera.world_to_camera, np.eye(4), atol=1e-12)
    uv, depth = camera.project(torch.tensor([[0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]))
    np.testing.assert_allclose(uv[0].numpy(), [camera.cx, camera.cy], atol=1e-5)
    np.testing.assert_allclose(depth.numpy(), [5.0, 5.0, 5.0], atol=1e-6)
    assert uv[1, 1] < camera.cy  # world up is image up (v grows downwards)
    assert uv[2, 0] > camera.cx  # looking along +z with +y up, world -x is on the right


def test_project_is_differentiable_and_matches_numpy() -> None:
    camera = _ring(3)[1]
    points = torch.randn(6, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0)) * 0.3
    points.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda p: camera.project(p), (points,))
    uv, depth = camera.project(points.detach())
    uv_np, depth_np = camera.project_numpy(points.detach().numpy())
    np.testing.assert_allclose(uv.numpy(), uv_np, rtol=1e-12)
    np.testing.assert_allclose(depth.numpy(), depth_np, rtol=1e-12)


def test_project_keeps_float32_and_intrinsics_viewmat() -> None:
    camera = _ring(3)[0]
    uv, depth = camera.project(torch.zeros(1, 3))
    assert uv.dtype == torch.float32 and depth.dtype == torch.float32
    k, view = camera.intrinsics(), camera.viewmat()
    assert k.dtype == view.dtype == torch.float32 and k.shape == (3, 3) and view.shape == (4, 4)
    homogeneous = view @ torch.tensor([0.0, 0.0, 0.0, 1.0])
    pixel = k @ homogeneous[:3]
    torch.testing.assert_close(pixel[:2] / pixel[2], uv[0])


def test_scaled_camera_projects_to_scaled_pixels() -> None:
    camera = _ring(3)[2]
    half = camera.scaled(32, 24)
    point = torch.tensor([[0.1, -0.2, 0.05]], dtype=torch.float64)
    uv, _ = camera.project(point)
    uv_half, _ = half.project(point)
    torch.testing.assert_close(uv_half, uv * 0.5)  # continuous pixels: an exact scale


def test_orbit_circles_the_target_starting_at_the_reference_view() -> None:
    like = look_at([0.0, 1.0, 4.0], [0.0, 0.0, 0.0], [0.0, 1.0, 0.0], _camera(), "input")
    ring = orbit([0.0, 0.0, 0.0], 4.0, 1.0, 8, like)
    assert [c.name for c in ring] == [f"orbit_{i:03d}" for i in range(8)]
    np.testing.assert_allclose(ring[0].center(), like.center(), atol=1e-9)
    for camera in ring:
        np.testing.assert_allclose(np.linalg.norm(camera.center() - [0.0, 1.0, 0.0]), 4.0, atol=1e-9)
        uv, _ = camera.project(torch.zeros(1, 3, dtype=torch.float64))
        np.testing.assert_allclose(uv[0].numpy(), [like.cx, like.cy], atol=1e-9)
    angles = [math.atan2(c.center()[2], c.center()[0]) for c in ring]
    steps = np.diff(np.unwrap(angles))
    np.testing.assert_allclose(np.abs(steps), 2 * math.pi / 8, atol=1e-9)


@pytest.mark.parametrize(
    ("change", "field"),
    [
        ({"fx": -1.0}, "fx"),
        ({"fy": float("nan")}, "fy"),
        ({"cx": float("inf")}, "cx"),
        ({"width": 0}, "width"),
        ({"height": 2.5}, "height"),
        ({"world_to_camera": np.diag([1.0, 1.0, 2.0, 1.0])}, "orthonormal"),
        ({"world_to_camera": np.diag([1.0, 1.0, -1.0, 1.0])}, "reflection"),
        ({"world_to_camera": np.eye(3)}, "world_to_camera"),
        ({"name": ""}, "name"),
        ({"fx": "wide"}, "fx must be a number"),
        ({"width": None}, "width must be a number"),
    ],
)
def test_camera_rejects_invalid_fields(change: dict, field: str) -> None:
    values = {"name": "c", "fx": 80.0, "fy": 80.0, "cx": 30.0, "cy": 20.0, "width": 60, "height": 40}
    values["world_to_camera"] = np.eye(4)
    values.update(change)
    with pytest.raises(CameraError, match=field):
        Camera(**values)


def test_check_video_size() -> None:
    camera = _camera(width=64, height=48)
    check_video_size(camera, "a.mp4", 64, 48)
    with pytest.raises(CameraError, match=r"video: a.mp4 is 128x96 but camera .* is 64x48"):
        check_video_size(camera, "a.mp4", 128, 96)


# --- nerfstudio transforms.json -----------------------------------------------------------------------
def _transforms(cams: list[Camera], **top) -> dict:
    """A nerfstudio file for `cams` (camera-to-world in OpenGL axes) with shared intrinsics."""
    first = cams[0]
    frames = [
        {
            "camera": c.name,
            "file_path": f"videos/{c.name}.mp4",
            "transform_matrix": (c.camera_to_world() @ OPENGL_FLIP).tolist(),
        }
        for c in cams
    ]
    shared = {"fl_x": first.fx, "fl_y": first.fy, "cx": first.cx, "cy": first.cy, "w": first.width, "h": first.height}
    return {"camera_model": "OPENCV", "k1": 0.0, **shared, **top, "frames": frames}


def _write(path: Path, data: dict) -> Path:
    path.write_text(json.dumps(data))
    return path


def test_nerfstudio_round_trip(tmp_path: Path) -> None:
    ring = _ring(4)
    data = _transforms(ring)
    data["frames"][2].update(fl_x=120.0, w=100, h=70)  # per-frame intrinsics override the shared ones
    loaded = cameras.load(_write(tmp_path / "transforms.json", data))
    assert list(loaded) == [c.name for c in ring]
    for camera in ring:
        np.testing.assert_allclose(loaded[camera.name].world_to_camera, camera.world_to_camera, atol=1e-12)
        assert loaded[camera.name].file_path == f"videos/{camera.name}.mp4"
    assert (loaded["cam2"].fx, loaded["cam2"].fy, loaded["cam2"].width) == (120.0, ring[0].fy, 100)


def test_write_transforms_round_trips(tmp_path: Path) -> None:
    ring = {c.name: c for c in _ring(3)}
    ring["cam1"] = ring["cam1"].scaled(128, 96)  # per-camera intrinsics survive
    matrix = np.eye(4).tolist()
    path = cameras.write_transforms(tmp_path / "out" / "transforms.json", ring, voxel_scale=1.0, voxel_matrix=matrix)
    loaded = cameras.load(path)
    assert list(loaded) == list(ring)
    for name, camera in ring.items():
        back = loaded[name]
        assert (back.fx, back.fy, back.cx, back.cy, back.width, back.height) == (
            camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height
        )
        np.testing.assert_allclose(back.world_to_camera, camera.world_to_camera, atol=1e-12)
    assert scene_box(path) is not None


def test_nerfstudio_opengl_pose_convention(tmp_path: Path) -> None:
    """An identity OpenGL camera-to-world sits at the origin looking down -z with +y up."""
    frame = {"file_path": "clips/side.mp4", "transform_matrix": np.eye(4).tolist()}
    data = {"fl_x": 100.0, "w": 40, "h": 30, "frames": [frame]}
    (camera,) = cameras.load(_write(tmp_path / "t.json", data)).values()
    assert camera.name == "side"  # no `camera` field: the file stem names it
    assert (camera.cx, camera.cy, camera.fy) == (20.0, 15.0, 100.0)
    uv, depth = camera.project(torch.tensor([[0.0, 0.0, -2.0], [0.0, 0.5, -2.0]]))
    torch.testing.assert_close(uv[0], torch.tensor([20.0, 15.0]))
    assert depth[0] == pytest.approx(2.0) and uv[1, 1] < 15.0


def test_format_is_detected_from_content(tmp_path: Path) -> None:
    path = _write(tmp_path / "upload.bin", _transforms(_ring(2)))
    assert len(cameras.load(path)) == 2
    (tmp_path / "random.json").write_bytes(np.random.default_rng(0).bytes(300))
    with pytest.raises(CameraError, match="unrecognised"):
        cameras.load(tmp_path / "random.json")
    with pytest.raises(CameraError, match="frames"):
        cameras.load(_write(tmp_path / "other.json", {"hello": 1}))
    (tmp_path / "broken.json").write_text('{"frames": [')
    with pytest.raises(CameraError, match="not valid JSON"):
        cameras.load(tmp_path / "broken.json")


def test_dataset_folder_loads_its_transforms(tmp_path: Path) -> None:
    with pytest.raises(CameraError, match="no COLMAP model .* and no transforms.json or info.json"):
        cameras.load(tmp_path)
    _write(tmp_path / "transforms.json", _transforms(_ring(3)))
    assert sorted(cameras.load(tmp_path)) == ["cam0", "cam1", "cam2"]


def _mutate(data: dict, path: str, value) -> dict:
    """Set data[a][b]... for a dotted path (integers index lists); value None deletes."""
    keys = [int(k) if k.isdigit() else k for k in path.split(".")]
    target = data
    for key in keys[:-1]:
        target = target[key]
    if value is None:
        del target[keys[-1]]
    else:
        target[keys[-1]] = value
    return data


@pytest.mark.parametrize(
    ("path", "value", "message"),
    [
        ("frames.1.transform_matrix", np.diag([1.0, 1.0, 3.0, 1.0]).tolist(), r"frames\[1\] \(cam1\): transform_matrix rotation is not orthonormal"),
        ("frames.0.transform_matrix", None, r"frames\[0\] \(cam0\): missing field transform_matrix"),
        ("fl_x", -5.0, "fl_x must be positive"),
        ("fl_y", 0.0, "fl_y must be positive"),
        ("w", None, "missing field w"),
        ("cx", float("nan"), "cx must be finite"),
        ("frames.1.camera", "cam0", r"frames\[1\].*duplicated camera name 'cam0'"),
        ("frames.1.camera", "CAM0", r"frames\[1\].*camera names 'cam0' and 'CAM0' differ only in case"),
        ("k4", 0.01, "k4 = 0.01: a fisheye coefficient"),
        ("camera_model", "OPENCV_FISHEYE", "camera_model 'OPENCV_FISHEYE' is not supported"),
        ("frames", [], "no cameras"),
        ("frames.0.camera", 7, "camera must be a non-empty string, got 7"),
    ],
)
def test_nerfstudio_errors_name_the_field(tmp_path: Path, path: str, value, message: str) -> None:
    data = _mutate(_transforms(_ring(3)), path, value)
    with pytest.raises(CameraError, match=message):
        cameras.load(_write(tmp_path / "transforms.json", data))


def test_a_camera_repeated_within_one_list_is_refused_not_folded(tmp_path: Path) -> None:
    """Issue 49 item 8: 5 cameras repeated to 65 identical entries were accepted as 5 (only PINF's
    train and test lists may list the same video twice, see test_pinf_info_json)."""
    data = _transforms(_ring(3))
    data["frames"] = data["frames"] * 4
    with pytest.raises(CameraError, match=r"frames\[3\]: duplicated camera name 'cam0'"):
        cameras.load(_write(tmp_path / "transforms.json", data))


# --- PINF / HyFluid info.json -------------------------------------------------------------------------
def _pinf_entry(camera: Camera, file_name: str, angle: float, hw: list[int] | None) -> dict:
    entry = {"file_name": file_name, "frame_rate": 30, "frame_num": 3, "camera_angle_x": angle}
    entry["transform_matrix"] = (camera.camera_to_world() @ OPENGL_FLIP).tolist()
    if hw is not None:
        entry["camera_hw"] = hw
    return entry


def test_pinf_info_json(tmp_path: Path) -> None:
    ring = _ring(2)
    train = [_pinf_entry(c, f"train0{i}.mp4", 0.5, [90, 160]) for i, c in enumerate(ring)]
    data = {"train_videos": train, "test_videos": [train[0]], "voxel_scale": 1.0, "voxel_matrix": np.eye(4).tolist()}
    loaded = cameras.load(_write(tmp_path / "info.json", data))
    assert sorted(loaded) == ["train00", "train01"]  # the test copy of train00 is the same camera
    camera = loaded["train01"]
    assert camera.fx == pytest.approx(80.0 / math.tan(0.25)) and camera.fy == camera.fx
    assert (camera.width, camera.height, camera.cx, camera.cy) == (160, 90, 80.0, 45.0)
    np.testing.assert_allclose(camera.world_to_camera, ring[1].world_to_camera, atol=1e-12)


def test_pinf_size_from_video(tmp_path: Path) -> None:
    """Original PINF files give no camera_hw: the size comes from the video next to them."""
    from fluidcore.video import write_mp4

    write_mp4(tmp_path / "train00.mp4", np.zeros((2, 36, 52, 3), dtype=np.uint8))
    data = {"train_videos": [_pinf_entry(_ring(1)[0], "train00.mp4", 0.6, None)]}
    camera = cameras.load(_write(tmp_path / "info.json", data))["train00"]
    assert (camera.width, camera.height) == (52, 36)
    data["train_videos"][0]["file_name"] = "missing.mp4"
    with pytest.raises(CameraError, match="missing fields w and h"):
        cameras.load(_write(tmp_path / "info.json", data))


def test_pinf_rejects_bad_angle(tmp_path: Path) -> None:
    data = {"train_videos": [_pinf_entry(_ring(1)[0], "a.mp4", 4.0, [10, 10])]}
    with pytest.raises(CameraError, match=r"train_videos\[0\] \(a\): camera_angle_x must be in"):
        cameras.load(_write(tmp_path / "info.json", data))


# --- scene boxes --------------------------------------------------------------------------------------
def test_scene_box_follows_pinf_axis_swap(tmp_path: Path) -> None:
    """PINF swaps the voxel matrix's x and z columns before scaling the unit cube by voxel_scale."""
    matrix = np.eye(4)
    matrix[:3, 3] = [1.0, 2.0, 3.0]
    path = _write(tmp_path / "info.json", {"frames": [], "voxel_scale": [1.0, 2.0, 3.0], "voxel_matrix": matrix.tolist()})
    lo, hi = scene_box(path)
    np.testing.assert_allclose(lo, [1.0, 2.0, 3.0])
    np.testing.assert_allclose(hi, [4.0, 4.0, 4.0])
    assert scene_box(_write(tmp_path / "plain.json", _transforms(_ring(2)))) is None
    with pytest.raises(CameraError, match="voxel_scale"):
        scene_box(_write(tmp_path / "bad.json", {"voxel_scale": [1.0, -1.0, 1.0], "voxel_matrix": matrix.tolist()}))


def test_frusta_box_of_a_ring_holds_the_target() -> None:
    lo, hi = frusta_box(_ring(4))
    assert np.all(lo < 0.0) and np.all(hi > 0.0)
    assert np.all(hi - lo < 6.0)  # bounded by the ring (radius 3)


def test_frusta_box_rejects_unbounded_and_empty_overlaps() -> None:
    with pytest.raises(CameraError, match="unbounded"):
        frusta_box(_ring(1))
    like = _camera()
    apart = [
        look_at([0, 0, 0], [0, 0, 1], [0, 1, 0], like, "a"),
        look_at([0, 0, -1], [0, 0, -2], [0, 1, 0], like, "b"),
    ]
    with pytest.raises(CameraError, match="do not overlap"):
        frusta_box(apart)


# --- COLMAP -------------------------------------------------------------------------------------------
def _quaternion(rotation: np.ndarray) -> list[float]:
    """(w, x, y, z) of a rotation matrix (trace formula; fine for rotations well below 180 degrees)."""
    w = math.sqrt(max(0.0, 1.0 + np.trace(rotation))) / 2.0
    if w > 1e-3:
        return [w, (rotation[2, 1] - rotation[1, 2]) / (4 * w), (rotation[0, 2] - rotation[2, 0]) / (4 * w), (rotation[1, 0] - rotation[0, 1]) / (4 * w)]
    raise ValueError("test helper needs rotations away from 180 degrees")


def _write_colmap_text(folder: Path, cams: list[Camera], model: str = "PINHOLE", extra: str = "") -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    camera_lines, image_lines = [], []
    for i, c in enumerate(cams, start=1):
        params = f"{c.fx} {c.fy} {c.cx} {c.cy}" if model == "PINHOLE" else f"{c.fx} {c.cx} {c.cy} {extra}"
        camera_lines.append(f"{i} {model} {c.width} {c.height} {params}")
        q = _quaternion(c.world_to_camera[:3, :3])
        t = c.world_to_camera[:3, 3]
        pose = " ".join(repr(float(v)) for v in (*q, *t))
        image_lines.append(f"{i} {pose} {i} {c.name}.png\n\n")  # second line: no 2D points
    (folder / "cameras.txt").write_text("\n".join(camera_lines) + "\n")
    (folder / "images.txt").write_text("".join(image_lines))
    (folder / "points3D.txt").write_text("")
    return folder


def _colmap_ring() -> list[Camera]:
    """Cameras near the identity rotation (world up = -y), where the test's quaternion helper is exact."""
    like = _camera()
    return [look_at([2 * math.sin(a), 0.3, -2 * math.cos(a)], [0, 0, 0], [0, -1, 0], like, f"cam{i}") for i, a in enumerate((0.0, 0.4, -0.5))]


def test_colmap_text_binary_and_zip_agree_with_pycolmap(tmp_path: Path) -> None:
    import pycolmap

    ring = _colmap_ring()
    text_dir = _write_colmap_text(tmp_path / "text", ring)
    reconstruction = pycolmap.Reconstruction(str(text_dir))
    binary_dir = tmp_path / "project" / "sparse" / "0"  # COLMAP's own layout, found below the root
    binary_dir.mkdir(parents=True)
    reconstruction.write_binary(str(binary_dir))
    archive = tmp_path / "upload.dat"
    with zipfile.ZipFile(archive, "w") as zf:
        for file in binary_dir.iterdir():
            zf.write(file, f"sparse/0/{file.name}")
    point = np.array([0.2, -0.1, 0.3])
    for source in (text_dir, tmp_path / "project", archive):
        loaded = cameras.load(source)
        assert sorted(loaded) == ["cam0", "cam1", "cam2"]
        for image in reconstruction.images.values():
            camera = loaded[Path(image.name).stem]
            expected = reconstruction.cameras[image.camera_id].img_from_cam(image.cam_from_world() * point)
            uv, _ = camera.project_numpy(point)
            np.testing.assert_allclose(uv[0], expected, atol=1e-6)


def test_colmap_keeps_distortion_and_rejects_hostile_zips(tmp_path: Path) -> None:
    ring = _colmap_ring()
    _write_colmap_text(tmp_path / "zero", ring, model="SIMPLE_RADIAL", extra="0.0")
    assert all(c.distortion == () for c in cameras.load(tmp_path / "zero").values())
    _write_colmap_text(tmp_path / "radial", ring, model="SIMPLE_RADIAL", extra="0.05")
    assert all(c.distortion == (0.05, 0.0, 0.0, 0.0) for c in cameras.load(tmp_path / "radial").values())
    evil = tmp_path / "evil.zip"
    with zipfile.ZipFile(evil, "w") as zf:
        zf.writestr("../cameras.txt", "1 PINHOLE 10 10 5 5 5 5\n")
    with pytest.raises(CameraError, match="escapes"):
        cameras.load(evil)
    empty = tmp_path / "empty.zip"
    with zipfile.ZipFile(empty, "w") as zf:
        zf.writestr("readme.txt", "nothing here")
    with pytest.raises(CameraError, match="no COLMAP model"):
        cameras.load(empty)


def test_cameras_module_does_not_import_torch() -> None:
    code = "import sys, fluidcore.cameras, fluidcore.video; print('torch' in sys.modules)"
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert result.stdout.strip() == "False"


def test_scene_box_min_max_is_read_and_checked(tmp_path: Path) -> None:
    path = tmp_path / "transforms.json"
    path.write_text(json.dumps({"scene_box": {"min": [0.1, 0.0, -0.5], "max": [0.6, 0.75, 0.0]}, "frames": []}))
    lo, hi = scene_box(path)
    np.testing.assert_allclose(lo, [0.1, 0.0, -0.5])
    np.testing.assert_allclose(hi, [0.6, 0.75, 0.0])
    path.write_text(json.dumps({"scene_box": {"min": [0.1, 0.0, -0.5], "max": [0.0, 0.75, 0.0]}, "frames": []}))
    with pytest.raises(CameraError, match="scene_box"):
        scene_box(path)

"""The counts a COLMAP model declares are capped before pycolmap reads it
(fluidcore.cameras.colmap_limits): text and binary, a truncated record, a record longer than
its file, and a valid binary model written by pycolmap itself (test_cameras) still loads."""

from __future__ import annotations

import struct
import time
from pathlib import Path

import pytest

from bench.upload_attacks import declared_images_zip, many_images_zip
from fluidcore.cameras import CameraError, load
from fluidcore.cameras import colmap_limits

PINHOLE = struct.pack("<Q", 1) + struct.pack("<iiQQ", 1, 1, 270, 480) + struct.pack("<4d", 300, 300, 135, 240)


def _image_record(points: int, name: bytes = b"view.png") -> bytes:
    return struct.pack("<I4d3dI", 1, 1, 0, 0, 0, 0, 0, 4, 1) + name + b"\0" + struct.pack("<Q", points)


def _binary_model(folder: Path, images: bytes, points: bytes = struct.pack("<Q", 0)) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "cameras.bin").write_bytes(PINHOLE)
    (folder / "images.bin").write_bytes(images)
    (folder / "points3D.bin").write_bytes(points)
    return folder


def test_a_text_model_over_the_image_cap_is_refused_before_pycolmap_reads_it(tmp_path: Path) -> None:
    archive = many_images_zip(tmp_path / "images.zip", 5 * colmap_limits.MAX_IMAGES)
    start = time.perf_counter()
    with pytest.raises(CameraError, match=r"images.txt: more than 1,000 images, the limit"):
        load(archive)
    assert time.perf_counter() - start < 30.0  # a generous bound: the probe's 821,732 took 285 s


def test_a_binary_model_declaring_1e9_images_is_a_camera_error_not_a_crash(tmp_path: Path) -> None:
    with pytest.raises(CameraError, match=r"images.bin: declares 1,000,000,000 images, more than the limit of 1,000"):
        load(declared_images_zip(tmp_path / "declared.zip", 10**9))


@pytest.mark.parametrize(
    "images, message",
    [
        (struct.pack("<Q", 2) + _image_record(0), "ends inside a record"),  # declares two, holds one
        (struct.pack("<Q", 1) + _image_record(10**12), "declares 24,000,000,000,000 bytes more than the file holds"),
        (struct.pack("<Q", 1) + _image_record(0, b"x" * 5000), "image name longer than 1024 bytes"),
        (struct.pack("<Q", 1) + _image_record(0) + b"junk", "4 bytes after its 1 records"),
    ],
)
def test_malformed_binary_records_are_named(tmp_path: Path, images: bytes, message: str) -> None:
    with pytest.raises(CameraError, match=message):
        colmap_limits.check_model_sizes(_binary_model(tmp_path / "model", images))


def test_points_and_cameras_are_walked_too(tmp_path: Path) -> None:
    track = struct.pack("<Q3d3BdQ", 1, 0, 0, 0, 0, 0, 0, 0.5, 10**9)  # a point whose track runs past the file
    with pytest.raises(CameraError, match="points3D.bin: a record declares"):
        colmap_limits.check_model_sizes(_binary_model(tmp_path / "a", struct.pack("<Q", 1) + _image_record(0),
                                                      struct.pack("<Q", 1) + track))
    folder = _binary_model(tmp_path / "b", struct.pack("<Q", 1) + _image_record(0))
    (folder / "cameras.bin").write_bytes(struct.pack("<Q", 1) + struct.pack("<iiQQ", 1, 99, 270, 480))
    with pytest.raises(CameraError, match="unknown camera model id 99"):
        colmap_limits.check_model_sizes(folder)
    fine = _binary_model(tmp_path / "c", struct.pack("<Q", 1) + _image_record(2) + bytes(48))
    colmap_limits.check_model_sizes(fine)  # one image with two 2D points, exactly as long as declared

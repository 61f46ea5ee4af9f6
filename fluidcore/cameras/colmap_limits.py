"""The sizes a COLMAP model declares, read and capped before pycolmap parses it (issue 36).

pycolmap reads a whole model before anything can be checked, and builds every image, camera and
point it declares: a 3.8 MB zip whose images.txt listed 821,732 images took 285 s and 1.28 GB
of the API's memory before its 422, and an images.bin declaring 1e9 images answered HTTP 500.
Here the counts come first, from the files themselves: a binary file's header and then each
record's own lengths, walked with every length checked against the bytes that remain, and a
text file's data lines, read until a cap is passed. A model over a cap, or a binary file whose
records do not fit its size, is a `CameraError` (the API's 422) naming the file.

The caps sit far above a capture rig (the API accepts 64 cameras) and far below what hurt. Walking
a file costs a few microseconds per record: 500,000 points take about a second and a half.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator
from pathlib import Path
from typing import BinaryIO

from fluidcore.cameras.camera import CameraError

MAX_IMAGES = 1_000  # registered images (each one a camera here)
MAX_CAMERAS = 1_000  # intrinsics records
MAX_POINTS = 500_000  # sparse 3D points: unused here, but pycolmap builds each one
MAX_NAME_BYTES = 1_024  # an image's file name in images.bin, up to its terminating NUL
MAX_TEXT_LINE = 1 << 20  # bytes of one line of a text model (a points2D line of 40,000 points)

# Parameters per COLMAP camera model id (colmap/sensor/models.h), for walking cameras.bin.
MODEL_PARAMS = {0: 3, 1: 4, 2: 4, 3: 5, 4: 8, 5: 8, 6: 12, 7: 5, 8: 4, 9: 5, 10: 12, 11: 16}
CAMERA_RECORD = struct.Struct("<iiQQ")  # camera_id, model_id, width, height; then params (doubles)
IMAGE_HEAD = struct.Struct("<I4d3dI")  # image_id, qvec, tvec, camera_id; then name, NUL, points2D
IMAGE_POINT_BYTES = 24  # x, y (doubles), point3D_id (int64)
POINT_HEAD = struct.Struct("<Q3d3BdQ")  # point3D_id, xyz, rgb, error, track length; then the track
TRACK_ELEMENT_BYTES = 8  # image_id, point2D_idx (int32 each)
COUNT = struct.Struct("<Q")


def check_model_sizes(model_dir: Path) -> None:
    """CameraError unless every model file in `model_dir` declares at most its cap of records,
    and (for .bin files) holds exactly the records it declares."""
    for stem, what, cap, walk, text_lines_per_record in (
        ("cameras", "cameras", MAX_CAMERAS, _walk_cameras, 1),
        ("images", "images", MAX_IMAGES, _walk_images, 2),
        ("points3D", "points", MAX_POINTS, _walk_points, 1),
    ):
        binary, text = model_dir / f"{stem}.bin", model_dir / f"{stem}.txt"
        if binary.is_file():
            _check_binary(binary, what, cap, walk)
        elif text.is_file():
            _check_text(text, what, cap, text_lines_per_record)


def _check_binary(path: Path, what: str, cap: int, walk) -> None:  # noqa: ANN001 - one of the _walk_* below
    size = path.stat().st_size
    with path.open("rb") as file:
        (count,) = _read(file, COUNT, path)
        if count > cap:
            raise CameraError(f"{path.name}: declares {count:,} {what}, more than the limit of {cap:,}")
        for _ in range(count):
            walk(file, path, size)
        if file.tell() != size:
            raise CameraError(f"{path.name}: {size - file.tell()} bytes after its {count} records; not a COLMAP model file")


def _check_text(path: Path, what: str, cap: int, lines_per_record: int) -> None:
    """A text model's records: its data lines (images.txt gives each image two, the second its
    2D points, possibly empty), counted until the cap is passed."""
    lines = 0
    for line in _text_lines(path):
        if line.startswith(b"#"):
            continue
        if lines_per_record == 1 and not line.strip():
            continue
        lines += 1
        if lines > cap * lines_per_record + 1:  # images.txt may end without its last, empty line
            raise CameraError(f"{path.name}: more than {cap:,} {what}, the limit")


def _text_lines(path: Path) -> Iterator[bytes]:
    with path.open("rb") as file:
        while line := file.readline(MAX_TEXT_LINE + 1):
            if len(line) > MAX_TEXT_LINE:
                raise CameraError(f"{path.name}: a line longer than {MAX_TEXT_LINE:,} bytes; not a COLMAP model file")
            yield line


def _read(file: BinaryIO, record: struct.Struct, path: Path) -> tuple:
    data = file.read(record.size)
    if len(data) != record.size:
        raise CameraError(f"{path.name}: ends inside a record; not a complete COLMAP model file")
    return record.unpack(data)


def _skip(file: BinaryIO, n_bytes: int, size: int, path: Path) -> None:
    if n_bytes > size - file.tell():
        raise CameraError(f"{path.name}: a record declares {n_bytes:,} bytes more than the file holds")
    file.seek(n_bytes, 1)


def _walk_cameras(file: BinaryIO, path: Path, size: int) -> None:
    _, model_id, _, _ = _read(file, CAMERA_RECORD, path)
    if model_id not in MODEL_PARAMS:
        raise CameraError(f"{path.name}: unknown camera model id {model_id}")
    _skip(file, 8 * MODEL_PARAMS[model_id], size, path)


def _walk_images(file: BinaryIO, path: Path, size: int) -> None:
    _read(file, IMAGE_HEAD, path)
    name = file.read(MAX_NAME_BYTES + 1)
    end = name.find(b"\0")
    if end < 0:
        raise CameraError(f"{path.name}: an image name longer than {MAX_NAME_BYTES} bytes or without its end")
    file.seek(end + 1 - len(name), 1)  # back to just after the NUL
    (points,) = _read(file, COUNT, path)
    _skip(file, points * IMAGE_POINT_BYTES, size, path)


def _walk_points(file: BinaryIO, path: Path, size: int) -> None:
    *_, track = _read(file, POINT_HEAD, path)
    _skip(file, track * TRACK_ELEMENT_BYTES, size, path)

"""COLMAP sparse models (cameras/images as .bin or .txt, in a folder or a .zip) read through pycolmap.

COLMAP already uses OpenCV camera axes and continuous pixel coordinates (the upper-left pixel's
centre is at (0.5, 0.5)), so `cam_from_world` is our `world_to_camera` unchanged. A camera is
named by its image's file stem (the video or frame it was calibrated from); only registered
images (with a pose) become cameras.

Lens models: pinhole ones are taken as they are; the radial and OpenCV models keep their
coefficients as the camera's `distortion` (OpenCV order), and the reconstruction undistorts
the frames with OpenCV (fluidcore.cameras.undistort). Fisheye and other models are rejected.

Zips (what the API receives) are opened defensively: member names may not escape the folder
(fluidcore.names.safe_join) and the members read must have plain names (`check_relative`), and
the member count and the declared size of the model files are capped before anything is
unpacked, so an upload cannot write elsewhere, fill the disk or keep the API busy; the counts of
images, cameras and points the model files declare are capped before pycolmap reads them
(`fluidcore.cameras.colmap_limits`).
"""

from __future__ import annotations

import ctypes
import re
import shutil
import signal
import sys
import tempfile
import zipfile
from pathlib import Path, PurePosixPath
from types import ModuleType

import numpy as np

from fluidcore.cameras.camera import Camera, CameraError, check_camera_name, check_new_camera
from fluidcore.cameras.colmap_limits import check_model_sizes
from fluidcore.names import UnsafeName, UnsafePath, check_relative, safe_join

# Where each supported model's extra parameters go in OpenCV's (k1, k2, p1, p2, k3, k4, k5, k6).
DISTORTION_SLOTS = {
    "SIMPLE_PINHOLE": (),
    "PINHOLE": (),
    "SIMPLE_RADIAL": (0,),
    "RADIAL": (0, 1),
    "OPENCV": (0, 1, 2, 3),
    "FULL_OPENCV": (0, 1, 2, 3, 4, 5, 6, 7),
}
MODEL_FILES = ("cameras", "images")
EXTRACTED_FILES = (*MODEL_FILES, "points3D", "rigs", "frames")  # what pycolmap reads of a model
# Caps checked on the zip's directory before anything is unpacked. A 2.5 MB zip of 20,000
# members cost 26.6 s of API CPU and a 510 kB one unpacked 500 MiB before these existed. A model
# is 2 to 5 files; 1,000 members leaves room for a zipped project folder's images and logs.
MAX_MEMBERS = 1_000
# Declared (and, while unpacking, actual) bytes of the model files: a 64-camera model with
# 10,000 keypoints per image and 200,000 points is about 40 MiB in text.
MAX_UNZIPPED_BYTES = 64 * 1024 * 1024


def find_model_dir(root: Path) -> Path | None:
    """The folder holding cameras.{bin,txt} and images.{bin,txt}: `root` itself or one below it
    (COLMAP writes sparse/0/). None when there is none; CameraError when there are several."""
    candidates = sorted({p.parent for p in root.rglob("cameras.*") if _is_model_dir(p.parent)})
    if not candidates:
        return None
    if len(candidates) > 1:
        listed = ", ".join(str(c.relative_to(root)) or "." for c in candidates)
        raise CameraError(f"{root.name}: several COLMAP models ({listed}); upload exactly one")
    return candidates[0]


def _is_model_dir(folder: Path) -> bool:
    return all(any((folder / f"{stem}.{ext}").is_file() for ext in ("bin", "txt")) for stem in MODEL_FILES)


def load_colmap_dir(folder: Path, label: str | None = None) -> dict[str, Camera]:
    """Cameras by name from a folder that is (or contains) one COLMAP sparse model; `label` names
    it in errors (a zip's own name, not the temporary folder it was unpacked into)."""
    label = label or folder.name
    model_dir = find_model_dir(folder)
    if model_dir is None:
        raise CameraError(f"{label}: no COLMAP model (cameras.bin/.txt and images.bin/.txt) found")
    check_model_sizes(model_dir)
    pycolmap = _import_pycolmap()
    try:
        reconstruction = pycolmap.Reconstruction(str(model_dir))
    except PYCOLMAP_REFUSALS as error:
        raise CameraError(f"{label}: unreadable COLMAP model: {pycolmap_reason(error)}") from None
    return cameras_from_reconstruction(reconstruction, label)


# What pycolmap raises for a model it cannot read: its checks (RuntimeError, ValueError) and a
# reference to a missing record (C++ out_of_range as IndexError: "Rig with ID 7 does not exist",
# which was an internal error before issue 49).
PYCOLMAP_REFUSALS = (ValueError, RuntimeError, IndexError, KeyError)
_SOURCE_LINE = re.compile(r"\[[\w./-]+\.(?:cc|h|cpp):\d+\]\s*")


def pycolmap_reason(error: Exception) -> str:
    """pycolmap's message without what is the server's own business (issue 49): the C++ source
    line and the failed check's expression ("[reconstruction_io_text.cc:246] Check failed:
    line_stream1 >> image_id >> ...") become "a line or record it could not parse", and no path is
    kept."""
    text = _SOURCE_LINE.sub("", str(error).strip())
    if text.startswith("Check failed"):
        return "a line or record it could not parse"
    return re.sub(r"(/[^\s/]+)+/?", "<path>", text).splitlines()[0][:200] if text else type(error).__name__


# glog's failure handler, which importing pycolmap installs, takes these over from the process.
_FAILURE_SIGNALS = (signal.SIGSEGV, signal.SIGILL, signal.SIGFPE, signal.SIGABRT, signal.SIGBUS, signal.SIGTERM)
_SIGACTION_BYTES = 256  # more than struct sigaction on any Linux ABI; kept opaque, only copied back


def _import_pycolmap() -> ModuleType:
    """`import pycolmap`, keeping the process's own signal handlers.

    The import installs glog's failure handler for SIGTERM among others, silently replacing what
    the process had: `fluidnexus serve` then died on SIGTERM with a stack dump (exit 143) instead
    of stopping cleanly, after any COLMAP upload. The handlers are saved and put back around the
    first import with sigaction(2) itself, which (unlike `signal.signal`) works from the request
    threads the API validates uploads on.
    """
    if "pycolmap" in sys.modules or not sys.platform.startswith("linux"):
        import pycolmap

        return pycolmap
    libc = ctypes.CDLL(None, use_errno=True)
    saved = {signum: ctypes.create_string_buffer(_SIGACTION_BYTES) for signum in _FAILURE_SIGNALS}
    for signum, action in saved.items():
        libc.sigaction(int(signum), None, action)
    try:
        import pycolmap
    finally:
        for signum, action in saved.items():
            libc.sigaction(int(signum), action, None)
    return pycolmap


def load_colmap_zip(path: Path) -> dict[str, Camera]:
    """Cameras by name from a .zip holding one COLMAP sparse model (at any depth)."""
    with tempfile.TemporaryDirectory(prefix="fluidnexus-colmap-") as tmp:
        _safe_extract(path, Path(tmp))
        return load_colmap_dir(Path(tmp), path.name)


def _safe_extract(path: Path, target: Path) -> None:
    try:
        archive = zipfile.ZipFile(path)
    except zipfile.BadZipFile as error:
        raise CameraError(f"{path.name}: not a readable zip archive ({error})") from None
    with archive:
        members = [m for m in archive.infolist() if not m.is_dir()]
        models = _model_members(path, members)
        for member in members:
            try:  # a member that would land outside is refused even when it would not be extracted
                destination = safe_join(target, member.filename)
                wanted = member in models
                if wanted:
                    check_relative(member.filename, "member")
            except (UnsafeName, UnsafePath) as error:
                raise CameraError(f"{path.name}: {error}") from None
            if wanted:
                try:
                    destination.parent.mkdir(parents=True, exist_ok=True)
                    with archive.open(member) as source, destination.open("wb") as out:
                        shutil.copyfileobj(source, out)
                except (zipfile.BadZipFile, OSError) as error:
                    raise CameraError(f"{path.name}: cannot unpack {member.filename}: {error}") from None


def _model_members(path: Path, members: list[zipfile.ZipInfo]) -> list[zipfile.ZipInfo]:
    """The model files among `members` (the zip's files), after the caps on the zip's directory:
    at most MAX_MEMBERS members, one model folder, and MAX_UNZIPPED_BYTES declared for its
    files. The declared sizes bound what is written: zipfile reads no more than a member's
    declared size (and a member whose data runs longer fails its CRC check)."""
    if len(members) > MAX_MEMBERS:
        raise CameraError(f"{path.name}: {len(members)} members, more than the limit of {MAX_MEMBERS}")
    models = [m for m in members if PurePosixPath(m.filename).name.split(".")[0] in EXTRACTED_FILES]
    folders = sorted({str(PurePosixPath(m.filename).parent) for m in models})
    if len(folders) > 1:
        listed = ", ".join(folders[:5]) + (", ..." if len(folders) > 5 else "")
        raise CameraError(f"{path.name}: several COLMAP models ({listed}); upload exactly one")
    declared = sum(m.file_size for m in models)
    if declared > MAX_UNZIPPED_BYTES:
        raise CameraError(f"{path.name}: its model files unpack to {declared >> 20} MiB, more than the limit of "
                          f"{MAX_UNZIPPED_BYTES >> 20} MiB")
    return models


def cameras_from_reconstruction(reconstruction, source: str) -> dict[str, Camera]:
    cameras: dict[str, Camera] = {}
    for image in sorted(reconstruction.images.values(), key=lambda im: im.name):
        if not image.has_pose:
            continue
        name = PurePosixPath(image.name).stem
        context = f"{source}: image {image.name!r}"
        check_camera_name(name, f"{context}: camera name")
        check_new_camera(cameras, name, context)
        colmap_camera = reconstruction.cameras[image.camera_id]
        fx, fy, cx, cy, distortion = _intrinsics(colmap_camera, context)
        world_to_camera = np.eye(4)
        world_to_camera[:3, :] = image.cam_from_world().matrix()  # pycolmap 4.x: a method
        try:
            cameras[name] = Camera(
                name, fx, fy, cx, cy, colmap_camera.width, colmap_camera.height, world_to_camera,
                file_path=image.name, distortion=distortion,
            )
        except CameraError as error:
            raise CameraError(f"{context}: {error}") from None
    if not cameras:
        raise CameraError(f"{source}: the COLMAP model has no registered images")
    return cameras


def _intrinsics(colmap_camera, context: str) -> tuple[float, float, float, float, tuple[float, ...]]:
    model = colmap_camera.model.name
    if model not in DISTORTION_SLOTS:
        raise CameraError(f"{context}: camera model {model} is not supported (use {', '.join(DISTORTION_SLOTS)})")
    params = np.asarray(colmap_camera.params, dtype=np.float64)
    extra = params[list(colmap_camera.extra_params_idxs())]
    slots = DISTORTION_SLOTS[model]
    distortion = np.zeros(8 if len(slots) > 4 else 4)
    distortion[list(slots)] = extra
    k = np.asarray(colmap_camera.calibration_matrix(), dtype=np.float64)
    return float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2]), tuple(distortion.tolist())

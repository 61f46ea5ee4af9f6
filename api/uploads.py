"""Scene uploads: spool every part to a private folder, validate all of it, and only then store.

Validation uses fluidcore's torch-free readers (`fluidcore.cameras.load`,
`fluidcore.video.probe`), so what the API accepts is exactly what the worker can read.
Nothing touches storage until the whole upload is known to be good, and a failed store
removes what it had written, so a bad request never leaves or loses anything.
"""

from __future__ import annotations

import mimetypes
from dataclasses import dataclass
from pathlib import Path, PurePath
from typing import TYPE_CHECKING, BinaryIO

from fluidcore.names import UnsafeName, check_name, check_relative
from service.settings import Settings
from service.storage import Storage

if TYPE_CHECKING:  # fluidcore is imported where it is used, keeping `import api` light
    from fluidcore.cameras import Camera
    from fluidcore.video import VideoInfo


class UploadRejected(ValueError):
    """The upload cannot be accepted; `status_code` is 413 for size limits, else 422."""

    def __init__(self, message: str, status_code: int = 422) -> None:
        super().__init__(message)
        self.status_code = status_code


@dataclass(frozen=True)
class SpooledVideo:
    camera: str
    filename: str
    path: Path
    size: int
    width: int
    height: int
    fps: float
    n_frames: int
    codec: str


@dataclass(frozen=True)
class ValidatedScene:
    cameras_path: Path
    camera_names: list[str]
    videos: dict[str, SpooledVideo]
    n_frames: int
    fps: float


def safe_filename(name: str | None, field: str) -> str:
    """The name of an uploaded part, refused unless it follows the naming rule (fluidcore.names)
    exactly as sent: a directory part, a drive or a traversal is refused, never stripped."""
    try:
        return check_name(name, f"{field}: file name")
    except UnsafeName as exc:
        raise UploadRejected(str(exc)) from None


def spool(source: BinaryIO, target: Path, limit: int, field: str) -> int:
    """Copy an uploaded part to `target`, refusing (413) more than `limit` bytes."""
    size = 0
    with target.open("wb") as out:
        while chunk := source.read(1024 * 1024):
            size += len(chunk)
            if size > limit:
                raise UploadRejected(f"{field}: {target.name} is larger than the limit of {limit} bytes", 413)
            out.write(chunk)
    if size == 0:
        raise UploadRejected(f"{field}: {target.name} is empty")
    return size


def match_camera(filename: str, cameras: dict[str, Camera]) -> str:
    """The camera a video belongs to: its stem is a camera's name or the base name of its file_path."""
    stem = PurePath(filename).stem
    for name, camera in cameras.items():
        aliases = {name}
        if camera.file_path:
            aliases |= {PurePath(camera.file_path).name, PurePath(camera.file_path).stem}
        if stem in aliases or filename in aliases:
            return name
    known = ", ".join(sorted(cameras))
    raise UploadRejected(f"video: {filename!r} matches no camera; known cameras: {known}")


def single_camera_file(folder: Path, video_sizes: dict[str, int], fov: float, distance: float, up: str) -> str:
    """Write the transforms.json of `fluidnexus cameras single` for the one spooled video (an
    upload without a camera file); returns its file name. Same parameters, same file as the CLI."""
    from fluidcore.cameras import CameraError
    from fluidcore.cameras.single import write_single_camera
    from fluidcore.video import VideoError

    if len(video_sizes) != 1:
        raise UploadRejected(f"fov: a scene without a cameras file takes exactly one video, got {len(video_sizes)}")
    name = "transforms.json"
    if name in video_sizes:
        raise UploadRejected(f"video: the file name {name!r} is reserved for the generated cameras file")
    try:
        write_single_camera(folder / name, folder / next(iter(video_sizes)), fov, distance, up)
    except CameraError as exc:
        raise UploadRejected(f"cameras: {exc}") from None
    except VideoError as exc:
        raise UploadRejected(f"video: {exc}") from None
    return name


def validate_scene(
    folder: Path, cameras_file: str, video_sizes: dict[str, int], settings: Settings
) -> ValidatedScene:
    """Check the spooled cameras file and videos in `folder`; raise UploadRejected naming the problem."""
    from fluidcore.cameras import CameraError, load
    from fluidcore.video import VideoError, probe

    try:
        cameras = load(folder / cameras_file)
    except CameraError as exc:
        raise UploadRejected(f"cameras: {exc}") from None
    _check_file_paths(cameras)
    _check_cameras(cameras, settings)
    if not video_sizes:
        raise UploadRejected("video: at least one video part is required")
    if len(video_sizes) > settings.max_videos:
        raise UploadRejected(f"video: at most {settings.max_videos} videos per scene")

    videos: dict[str, SpooledVideo] = {}
    for filename, size in video_sizes.items():
        camera_name = match_camera(filename, cameras)
        if camera_name in videos:
            raise UploadRejected(
                f"video: {filename!r} and {videos[camera_name].filename!r} are both for camera {camera_name!r}"
            )
        try:
            info = probe(folder / filename)
        except VideoError as exc:
            raise UploadRejected(f"video: {filename}: {exc}") from None
        _check_video(filename, info, cameras[camera_name], settings)
        videos[camera_name] = SpooledVideo(
            camera_name, filename, folder / filename, size, info.width, info.height, float(info.fps),
            info.n_frames, info.codec,
        )

    rates = {v.fps for v in videos.values()}
    if max(rates) - min(rates) > 1e-3 * max(rates):
        listing = ", ".join(f"{v.filename}: {v.fps:g}" for v in videos.values())
        raise UploadRejected(f"video: all videos must have the same frame rate ({listing})")
    return ValidatedScene(
        cameras_path=folder / cameras_file,
        camera_names=sorted(cameras),
        videos=videos,
        n_frames=min(v.n_frames for v in videos.values()),
        fps=max(rates),
    )


def _check_file_paths(cameras: dict[str, Camera]) -> None:
    """A cameras file on the server may only name the parts uploaded with it: every `file_path`
    must follow the naming rule as a relative path (the CLI's own files may point elsewhere)."""
    for camera in cameras.values():
        if camera.file_path is not None:
            try:
                check_relative(camera.file_path, f"cameras: camera {camera.name!r}: file_path")
            except UnsafeName as exc:
                raise UploadRejected(str(exc)) from None


def _check_cameras(cameras: dict[str, Camera], settings: Settings) -> None:
    """Count, size and plausible intrinsics/extrinsics of every camera, with or without a video:
    the worker renders every camera, so a camera's pixels cost memory even with no footage."""
    from fluidcore.artifacts import check_camera_names
    from fluidcore.cameras import CameraError, check_ranges
    from fluidcore.jobs import JobInputError

    try:
        check_camera_names(list(cameras))
    except JobInputError as exc:
        raise UploadRejected(f"cameras: {exc}") from None
    if len(cameras) > settings.max_cameras:
        raise UploadRejected(f"cameras: {len(cameras)} cameras, more than the limit of {settings.max_cameras}")
    total = 0
    for camera in cameras.values():
        pixels = camera.width * camera.height
        if pixels > settings.max_camera_pixels:
            raise UploadRejected(
                f"cameras: camera {camera.name!r} is {camera.width}x{camera.height}, more than the limit of "
                f"{settings.max_camera_pixels} pixels per camera"
            )
        total += pixels
        try:
            check_ranges(camera)
        except CameraError as exc:
            raise UploadRejected(f"cameras: {exc}") from None
    if total > settings.max_scene_pixels:
        raise UploadRejected(
            f"cameras: {total} pixels over all cameras, more than the limit of {settings.max_scene_pixels} per scene"
        )


def _check_video(filename: str, info: VideoInfo, camera: Camera, settings: Settings) -> None:
    """Limits from the settings, and exactly the camera's frame size (its intrinsics are in those pixels)."""
    from fluidcore.cameras import CameraError, check_video_size

    if info.n_frames < 1 or info.fps <= 0:
        raise UploadRejected(f"video: {filename} has no frames")
    seconds = info.n_frames / info.fps
    if seconds > settings.max_video_seconds:
        raise UploadRejected(
            f"video: {filename} lasts {seconds:.1f} s, longer than the limit of {settings.max_video_seconds:g} s"
        )
    try:  # the camera's size is within the pixel limits (_check_cameras), so then is the video's
        check_video_size(camera, filename, info.width, info.height)
    except CameraError as exc:
        raise UploadRejected(str(exc)) from None


def store_scene(storage: Storage, prefix: str, scene: ValidatedScene) -> dict[str, str]:
    """Upload the validated files under `prefix`; on any failure remove what was written and re-raise.

    Returns file name -> storage key. Videos and the cameras file share one folder because a
    cameras file may name its videos by relative path (and read their size from them).
    """
    written: dict[str, str] = {}
    try:
        for path in [scene.cameras_path, *(v.path for v in scene.videos.values())]:
            key = f"{prefix}/{path.name}"
            storage.put_file(key, path, mimetypes.guess_type(path.name)[0] or "application/octet-stream")
            written[path.name] = key
    except BaseException:
        for key in written.values():
            storage.delete(key)
        raise
    return written

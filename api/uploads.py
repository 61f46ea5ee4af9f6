"""Scene uploads: spool every part to a private folder, validate all of it, and only then store.

Validation uses fluidcore's torch-free readers (`fluidcore.cameras.load`,
`fluidcore.video.read_header` and `verify`), so what the API accepts is exactly what the worker
can read. Costs are capped before they are paid: a video's size and length are checked in its
headers before any frame is decoded, and then every frame is decoded under the camera's pixel
count and a frame cap (docs/service.md "Limits").
Nothing touches storage until the whole upload is known to be good, and a failed store
removes what it had written, so a bad request never leaves or loses anything.
"""

from __future__ import annotations

import mimetypes
import multiprocessing
import threading
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures import TimeoutError as FutureTimeout
from concurrent.futures.process import BrokenProcessPool
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path, PurePath
from typing import TYPE_CHECKING, Any, BinaryIO

from fluidcore.names import UnsafeName, check_name, check_relative
from service.settings import Settings
from service.storage import Storage

if TYPE_CHECKING:  # fluidcore is imported where it is used, keeping `import api` light
    from fluidcore.cameras import Camera
    from fluidcore.video import VideoHeader, VideoInfo

UPLOAD_RETRY_AFTER_S = 5  # an upload's check takes about a second on the dev scene's view; a few later, a slot is free
GONE_POLL_S = 0.25  # how often a check in progress asks whether its client is still there


class ClientGone(Exception):
    """The client closed the connection before its upload was stored: nothing is stored (its
    check, if it had started, finishes in its process and is thrown away)."""


class OwnerUploads:
    """At most `limit` uploads of one owner admitted at once, in this API process (taken by
    api.middleware.AdmissionLimit once the key is checked, before the upload waits for a place);
    one more is a 429 with `Retry-After` before its body is read. A key whose uploads time out and
    are sent again cannot fill every checker (issue 36: 20 clients of one key timed out on 120 of
    124 uploads, each still checked and stored)."""

    def __init__(self, limit: int) -> None:
        self.limit = limit
        self._counts: dict[str, int] = {}
        self._lock = threading.Lock()

    def take(self, owner: str) -> None:
        """One of `owner`'s places, or OverLimit; `release` gives it back."""
        from service.errors import OverLimit

        with self._lock:
            if self._counts.get(owner, 0) >= self.limit:
                raise OverLimit(f"uploads: {self.limit} of your uploads are being checked already; send the next one when "
                                "one of them is answered", retry_after=UPLOAD_RETRY_AFTER_S)
            self._counts[owner] = self._counts.get(owner, 0) + 1

    def release(self, owner: str) -> None:
        with self._lock:
            self._counts[owner] -= 1
            if not self._counts[owner]:
                del self._counts[owner]


class UploadRejected(ValueError):
    """The upload cannot be accepted; `status_code` is 413 for size limits, else 422."""

    def __init__(self, message: str, status_code: int = 422) -> None:
        super().__init__(message)
        self.status_code = status_code

    def __reduce__(self) -> tuple[type[UploadRejected], tuple[str, int]]:
        """Keep the status code when raised in a validation process."""
        return UploadRejected, (str(self), self.status_code)


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


def single_camera_file(folder: Path, video_sizes: dict[str, int], fov: float, distance: float, up: str,
                       max_pixels: int) -> str:
    """Write the transforms.json of `fluidnexus cameras single` for the one spooled video (an
    upload without a camera file); returns its file name. Same parameters, same file as the CLI;
    the video's first frame is decoded under `max_pixels` (the camera-file path's cap:
    `Settings.max_camera_pixels`; before, the built-in 8K cap let one 8000x8000 16-bit RGBA PNG
    frame cost 1.04 GB and 6.4 s)."""
    from fluidcore.cameras import CameraError
    from fluidcore.cameras.single import write_single_camera
    from fluidcore.video import VideoError

    if len(video_sizes) != 1:
        raise UploadRejected(f"fov: a scene without a cameras file takes exactly one video, got {len(video_sizes)}")
    name = "transforms.json"
    if name in video_sizes:
        raise UploadRejected(f"video: the file name {name!r} is reserved for the generated cameras file")
    try:
        write_single_camera(folder / name, folder / next(iter(video_sizes)), fov, distance, up, max_pixels=max_pixels)
    except CameraError as exc:
        raise UploadRejected(f"cameras: {exc}") from None
    except VideoError as exc:
        raise UploadRejected(f"video: {exc}") from None
    return name


def validate_scene(
    folder: Path, cameras_file: str, video_sizes: dict[str, int], settings: Settings
) -> ValidatedScene:
    """Check the spooled cameras file and videos in `folder`; raise UploadRejected naming the problem."""
    from fluidcore.cameras import CameraError, declared_fps, load, scene_box
    from fluidcore.cameras.world_up import declared_up
    from fluidcore.video import VideoError, common_rate, read_header, verify

    try:
        cameras = load(folder / cameras_file)
        declared_up(folder / cameras_file)  # the file's own `up`, `fps` and box, checked here, read by the job
        declared_fps(folder / cameras_file)
        scene_box(folder / cameras_file)  # before issue 49 a box the worker could not use was found by the job
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
        camera = cameras[camera_name]
        try:  # the header first: a video that cannot fit is refused before a frame is decoded
            _check_header(filename, read_header(folder / filename, settings.max_camera_pixels), camera, settings)
            info = verify(folder / filename, camera.width * camera.height, settings.max_video_frames)
        except VideoError as exc:
            raise UploadRejected(f"video: {exc}") from None
        _check_video(filename, info, camera, settings)
        videos[camera_name] = SpooledVideo(
            camera_name, filename, folder / filename, size, info.width, info.height, float(info.fps),
            info.n_frames, info.codec,
        )

    try:
        fps = common_rate({v.filename: v.fps for v in videos.values()})
    except VideoError as exc:
        raise UploadRejected(f"video: {exc}") from None
    return ValidatedScene(
        cameras_path=folder / cameras_file,
        camera_names=sorted(cameras),
        videos=videos,
        n_frames=min(v.n_frames for v in videos.values()),
        fps=fps,
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


def check_upload(
    folder: Path,
    cameras_file: str | None,
    video_sizes: dict[str, int],
    single: tuple[float, float, str] | None,
    settings: Settings,
) -> tuple[ValidatedScene, dict[str, Any]]:
    """Everything an upload costs in CPU, in one call for `Validators`: the generated cameras
    file when there is none (`single` = fov, distance, up), `validate_scene`, and the scene's
    geometry (`fluidcore.scene_info.from_cameras_file`)."""
    from fluidcore import scene_info

    if cameras_file is None:
        if single is None:
            raise UploadRejected("cameras: give either a cameras file or fov")
        cameras_file = single_camera_file(folder, video_sizes, *single, max_pixels=settings.max_camera_pixels)
    validated = validate_scene(folder, cameras_file, video_sizes, settings)
    return validated, scene_info.from_cameras_file(validated.cameras_path)


class Validators:
    """`check_upload` in a pool of processes, so the API's event loop and request threads never
    wait for an upload's parsing and decoding. bench/load.py, 200 pollers + 20 uploaders of the
    dev scene's view, 20 s on 2 busy cores: polling made 450 GET/s without uploads; with them,
    90 GET/s (p99 3.6 s) when uploads were checked on the API's threads (each poll queued for the
    GIL), 172 (p99 2.9 s) in processes, 280 (p99 1.8 s) in processes at nice 10. They run at the
    API's own priority since issue 36's realistic clips: 100 pollers + 20 uploaders of a 2.6 MB
    1080x1920 clip for 60 s while the embedded worker (nice 19) reconstructs, 2 places, 3 s wait:
    at nice 10, 10 uploads answered and 10 timed out at 10 s (GET p99 0.4 s); at the API's
    priority, 66 answered, none timed out (GET p99 1.1 s; docs/reliability.md). Forked from a fork server (the API has threads; the
    server has the readers imported, so a process starts in milliseconds), started on first
    use, at most `workers` at once; a pool whose process died (a crashing decoder) is replaced."""

    def __init__(self, workers: int) -> None:
        self.workers = workers
        self._pool: ProcessPoolExecutor | None = None
        self._lock = threading.Lock()

    def _current(self) -> ProcessPoolExecutor:
        with self._lock:
            if self._pool is None:
                context = multiprocessing.get_context("forkserver")
                context.set_forkserver_preload([__name__, "fluidcore.video", "fluidcore.cameras", "fluidcore.scene_info"])
                self._pool = ProcessPoolExecutor(self.workers, mp_context=context)
            return self._pool

    def check(
        self,
        folder: Path,
        cameras_file: str | None,
        video_sizes: dict[str, int],
        single: tuple[float, float, str] | None,
        settings: Settings,
        gone: Callable[[], bool] = lambda: False,
    ) -> tuple[ValidatedScene, dict[str, Any]]:
        """`check_upload` in one of the processes; its UploadRejected is raised here. `gone()` is
        asked while the check runs: once the client has left, ClientGone (a check still waiting
        for a process is cancelled)."""
        pool = self._current()
        try:
            future = pool.submit(check_upload, folder, cameras_file, video_sizes, single, settings)
            while True:
                try:
                    return future.result(timeout=GONE_POLL_S)
                except FutureTimeout:
                    if gone():
                        future.cancel()
                        raise ClientGone() from None
        except BrokenProcessPool:
            with self._lock:
                if self._pool is pool:
                    self._pool = None
            pool.shutdown(wait=False, cancel_futures=True)
            raise UploadRejected("upload: reading these files stopped the process that checked them") from None

    def close(self) -> None:
        with self._lock:
            if self._pool is not None:
                self._pool.shutdown(cancel_futures=True)
                self._pool = None


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


def _check_header(filename: str, header: VideoHeader, camera: Camera, settings: Settings) -> None:
    """What the headers declare against the camera and the limits. Pixel counts are compared
    (a phone's display rotation, known only from a decoded frame, swaps width and height), then
    decoding is capped at the camera's pixels, so a header that lies is caught by `verify`."""
    from fluidcore.cameras import CameraError, check_video_size

    if header.width and header.height and header.width * header.height != camera.width * camera.height:
        try:
            check_video_size(camera, filename, header.width, header.height)
        except CameraError as exc:
            raise UploadRejected(str(exc)) from None
    if header.n_frames > settings.max_video_frames:
        raise UploadRejected(
            f"video: {filename} has {header.n_frames} frames, more than the limit of {settings.max_video_frames}"
        )
    if header.n_frames and header.fps > 0 and header.n_frames / header.fps > settings.max_video_seconds:
        raise UploadRejected(
            f"video: {filename} lasts {header.n_frames / header.fps:.1f} s, longer than the limit of "
            f"{settings.max_video_seconds:g} s"
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

"""Video files in and out: probe, decode (MP4/MOV/WebM/... through PyAV) and encode browser-ready MP4.

Decoding returns uint8 RGB arrays (T, H, W, 3), the in-memory video convention of
docs/architecture.md, upright as a player shows them (a phone's display rotation is applied,
as ffmpeg does when frames are extracted for calibration). Colour conversion follows the
stream's colorspace tag (BT.709 HD video is not decoded as BT.601); untagged streams are BT.601
as ffmpeg assumes.

Encoding writes H.264 (libx264) in yuv420p, which every browser plays, with `+faststart` so
playback starts before the download ends, tagged BT.601 to match the conversion used. yuv420p
needs even dimensions: odd sizes are PADDED by one edge-replicated row/column at the bottom/right
(cropping would drop real pixels). Files are written to a temporary name and renamed, so a
failed encode never leaves a half-written file where a good one was.

Any file PyAV cannot read as video (random bytes, text named .mp4, truncated downloads) raises
VideoError with the file name and the reason. No torch here: the API probes uploads.

Uploads are hostile input, so decoding is bounded: every file is opened with a cap on the pixels
of one frame, passed to FFmpeg's decoder (`max_pixels`), which refuses a larger frame before
allocating it (a 0.8 MB MOV holding one 16000x16000 PNG frame otherwise costs 768 MB as it is
merely opened); `read_header` reads size and frame count without decoding anything, and
`verify` decodes the whole stream frame by frame under that cap and a frame-count cap, with
FFmpeg's error concealment off (`err_detect=explode`), so damage after the first frame is found
at upload time instead of being decoded into grey frames by the job.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path

import av
import numpy as np
from av.video.reformatter import Interpolation

from fluidcore.errors import InputError
from fluidcore.files import atomic_output

CRF = 18  # visually lossless for smoke; the shared benchmark files use the same
GREY_TOLERANCE = 3  # max |R-G|, |G-B| of a grey pixel after 4:2:0 chroma rounding
GREY_FRACTION = 0.999  # share of pixels that must be grey (a few noisy pixels do not make colour)
_COLORSPACES = {1: "itu709", 5: "itu601", 6: "itu601", 7: "smpte240m", 9: "bt2020"}  # AVColorSpace -> swscale
MAX_PIXELS = 7680 * 4320  # one frame's pixels unless the caller allows fewer: 8K UHD, 100 MB as RGB24
MAX_FRAMES = 100_000  # frames `verify` decodes unless the caller allows fewer: 55 min at 30 fps


class VideoError(InputError):
    """A file is not a readable video, or a video request/write is invalid; the message says why."""


@dataclass(frozen=True)
class VideoInfo:
    """What a video file holds: size as displayed (rotation applied); n_frames counted from
    the packets actually present."""

    width: int
    height: int
    fps: float
    n_frames: int
    codec: str
    pix_fmt: str = ""


@dataclass(frozen=True)
class VideoHeader:
    """What the container and stream headers declare, before any frame is decoded: the stored
    (not displayed) size, 0 x 0 when the header does not give it; n_frames 0 when not stored
    (WebM). Headers can lie: `verify` checks every decoded frame against them."""

    width: int
    height: int
    n_frames: int
    fps: float
    codec: str


def _open(path: str | Path, max_pixels: int = MAX_PIXELS) -> av.container.InputContainer:
    """The container, its first video stream's decoder capped at `max_pixels` per frame and
    with error concealment off (a damaged frame raises instead of being patched over).

    The cap is also given to the stream probing that opening does (FFmpeg decodes a frame there
    when the header lacks the size); formats that only reveal their streams by decoding, where
    it cannot apply, are refused."""
    path = Path(path)
    if not path.is_file():
        raise VideoError(f"{path}: no such file")
    # Decoders allocate the coded size, padded to their block size (H.264 decodes 270x480 as
    # 272x480), so FFmpeg's cap leaves room for that; callers check the exact one per frame.
    cap = {"max_pixels": str(2 * int(max_pixels) + 64 * 64)}
    try:
        container = av.open(str(path), mode="r", options=cap, stream_options=[{}])
    except ValueError:  # PyAV: the format exposes no streams before probing them
        raise VideoError(
            f"{path.name}: not a readable video (no streams declared in its header; remux it to MP4)"
        ) from None
    except (av.FFmpegError, UnicodeDecodeError) as error:
        raise VideoError(f"{path.name}: not a readable video ({_reason(error)})") from None
    if not container.streams.video:
        container.close()
        raise VideoError(f"{path.name}: contains no video stream")
    container.streams.video[0].codec_context.options = {**cap, "err_detect": "explode"}
    return container


def _rate(stream: av.VideoStream) -> float:
    rate = stream.average_rate or stream.guessed_rate or stream.base_rate
    return float(rate) if rate else 0.0


def read_header(path: str | Path, max_pixels: int = MAX_PIXELS) -> VideoHeader:
    """Size, declared frame count, frame rate and codec from the headers alone (nothing is
    decoded), so a caller can refuse a video that cannot fit before paying for decoding it.
    A declared size over `max_pixels` raises VideoError."""
    path = Path(path)
    with _open(path, max_pixels) as container:
        stream = container.streams.video[0]
        context = stream.codec_context
        header = VideoHeader(context.width, context.height, stream.frames, _rate(stream), context.name)
    if header.width * header.height > max_pixels:
        raise VideoError(
            f"{path.name}: frames are {header.width}x{header.height}, more than the limit of {max_pixels} pixels"
        )
    return header


def _reason(error: Exception) -> str:
    return getattr(error, "strerror", None) or str(error)


def probe(path: str | Path, max_pixels: int = MAX_PIXELS) -> VideoInfo:
    """Displayed size (rotation applied), frame rate, frame count and codec of the first video
    stream. Decodes the first frame (no larger than `max_pixels`), so a file that is not a
    playable video fails here; a file with fewer packets than its header declares is reported
    truncated. `verify` decodes them all."""
    path = Path(path)
    with _open(path, max_pixels) as container:
        stream = container.streams.video[0]
        first = _first_frame(container, stream, path)
        fps = _rate(stream)
        codec, pix_fmt, declared = stream.codec_context.name, stream.codec_context.pix_fmt or "", stream.frames
        shape = (first.width, first.height, _quarter_turns(first))
    return _info(path, shape, fps, _packets_in(path, max_pixels), declared, codec, pix_fmt)


def verify(path: str | Path, max_pixels: int = MAX_PIXELS, max_frames: int = MAX_FRAMES) -> VideoInfo:
    """`probe`, after decoding every frame (without colour conversion) under the caps: a frame
    larger than `max_pixels`, a size that changes between frames or differs from the header's,
    more than `max_frames` packets, or any damaged frame raises VideoError. What the API runs
    on an upload, once `read_header` has shown that the video can fit; 150 frames of 270x480
    H.264 take about 0.1 s of one core."""
    path = Path(path)
    header = read_header(path, max_pixels)
    if header.n_frames > max_frames:
        raise VideoError(f"{path.name}: {header.n_frames} frames, more than the limit of {max_frames}")
    with _open(path, max_pixels) as container:
        stream = container.streams.video[0]
        packets, shape = 0, None
        try:
            for packet in container.demux(stream):  # the last, empty packet flushes the decoder
                if packet.size:
                    packets += 1
                if packets > max_frames:
                    raise VideoError(f"{path.name}: more than the limit of {max_frames} frames")
                for frame in packet.decode():
                    shape = _same_shape(path, header, shape, frame, max_pixels)
        except av.FFmpegError as error:
            raise VideoError(
                f"{path.name}: damaged video, or a frame larger than {max_pixels} pixels, at packet {packets} "
                f"({_reason(error)})"
            ) from None
        pix_fmt = stream.codec_context.pix_fmt or ""
    if shape is None:
        raise VideoError(f"{path.name}: the video stream holds no decodable frame")
    return _info(path, shape, header.fps, packets, header.n_frames, header.codec, pix_fmt)


def _same_shape(
    path: Path, header: VideoHeader, shape: tuple[int, int, int] | None, frame: av.VideoFrame, max_pixels: int
) -> tuple[int, int, int]:
    """(width, height, quarter turns) of the first frame; later frames must match it, it the
    header, and none may exceed `max_pixels`."""
    current = (frame.width, frame.height, _quarter_turns(frame))
    if frame.width * frame.height > max_pixels:
        raise VideoError(f"{path.name}: a frame is {frame.width}x{frame.height}, more than the limit of {max_pixels} pixels")
    expected = shape or ((header.width, header.height) if header.width and header.height else current[:2])
    if current[:2] != expected[:2]:
        said = "the first frame" if shape else "the header"
        raise VideoError(
            f"{path.name}: a frame is {current[0]}x{current[1]} but {said} says {expected[0]}x{expected[1]}"
        )
    return shape or current


def _info(
    path: Path, shape: tuple[int, int, int], fps: float, n_frames: int, declared: int, codec: str, pix_fmt: str
) -> VideoInfo:
    """VideoInfo as displayed, after the checks every reader shares: no fewer packets than the
    header declares (a cut-off upload), at least one frame, a finite positive rate."""
    if declared and n_frames < declared:
        raise VideoError(f"{path.name}: truncated video: header says {declared} frames, only {n_frames} present")
    if not (n_frames > 0 and math.isfinite(fps) and fps > 0):
        raise VideoError(f"{path.name}: unusable video stream ({n_frames} frames, {fps} fps)")
    width, height, turns = shape
    if turns % 2:
        width, height = height, width
    return VideoInfo(width, height, fps, n_frames, codec, pix_fmt)


def _first_frame(container: av.container.InputContainer, stream: av.VideoStream, path: Path) -> av.VideoFrame:
    try:
        for frame in container.decode(stream):
            return frame
    except av.FFmpegError as error:
        raise VideoError(f"{path.name}: corrupt or truncated video ({_reason(error)})") from None
    raise VideoError(f"{path.name}: the video stream holds no decodable frame")


def _quarter_turns(frame: av.VideoFrame) -> int:
    """Counter-clockwise quarter turns the player applies (phone videos store portrait as
    landscape plus a display rotation); flips in the display matrix are not handled."""
    return round(frame.rotation / 90) % 4


def _packets_in(path: Path, max_pixels: int = MAX_PIXELS) -> int:
    with _open(path, max_pixels) as container:
        return _count_packets(container, container.streams.video[0], path)


def _count_packets(container: av.container.InputContainer, stream: av.VideoStream, path: Path) -> int:
    """Frame count by demuxing (reads the file, decodes nothing): WebM stores no count, and a
    count below the header's reveals a truncated upload at probe time."""
    try:
        return sum(1 for packet in container.demux(stream) if packet.size > 0)
    except av.FFmpegError as error:
        raise VideoError(f"{path.name}: corrupt or truncated video ({_reason(error)})") from None


RATE_TOLERANCE = 0.01  # relative: 29.97 and 30 fps are one rate, 24 and 25 are not


def common_rate(rates: dict[str, float]) -> float:
    """The one frame rate of a scene's videos (file name -> fps): videos of one moment in time
    share it, or the physics' seconds would differ from view to view (VideoError listing them)."""
    if not rates:
        raise VideoError("no videos")
    high, low = max(rates.values()), min(rates.values())
    if high - low > RATE_TOLERANCE * high:
        listing = ", ".join(f"{name}: {fps:g}" for name, fps in rates.items())
        raise VideoError(f"all videos must have the same frame rate ({listing})")
    return high


def rate_mismatch(video_fps: float, declared_fps: float | None) -> str | None:
    """What to tell the user when the camera file states another frame rate than the videos play
    at; None when it states none or the same. The videos' rate is what the run uses: it is how
    their frames are spaced in time, whatever the file says."""
    if declared_fps is None or abs(video_fps - declared_fps) <= RATE_TOLERANCE * max(video_fps, declared_fps):
        return None
    return (f"the videos play at {video_fps:g} fps but the camera file says {declared_fps:g} fps: the videos' rate is "
            "used, so the smoke's speeds are per second of the video as encoded; if the clip was slowed down or sped "
            "up when it was encoded, re-encode it at its real rate")


def read_frames(
    path: str | Path,
    start: int = 0,
    stop: int | None = None,
    step: int = 1,
    size: tuple[int, int] | None = None,
) -> np.ndarray:
    """Frames start, start+step, ... before stop (None: to the end) as uint8 RGB (T, H, W, 3).

    `size=(width, height)` resizes while converting (area filter when shrinking, bicubic when
    enlarging). Asking for frames past the end, or a file that ends before its header says it
    should (a truncated upload), raises VideoError rather than returning fewer frames.
    """
    _check_range(start, stop, step)
    if size is not None and not (len(size) == 2 and all(int(s) == s and s > 0 for s in size)):
        raise VideoError(f"size must be (width, height) positive integers, got {size!r}")
    path = Path(path)
    with _open(path) as container:
        stream = container.streams.video[0]
        stream.thread_type = "AUTO"
        declared = stream.frames
        frames, index = [], -1
        try:
            for index, frame in enumerate(container.decode(stream)):
                if stop is not None and index >= stop:
                    break
                if index >= start and (index - start) % step == 0:
                    frames.append(_to_rgb(frame, size))
        except av.FFmpegError as error:
            raise VideoError(f"{path.name}: corrupt or truncated video after {index + 1} frames ({_reason(error)})") from None
    decoded = index + 1
    if stop is None and declared and decoded < declared and _packets_in(path) < declared:
        # Fewer packets than declared is a cut-off file; fewer frames alone can be an edit list.
        raise VideoError(f"{path.name}: truncated video: header says {declared} frames, only {decoded} decode")
    if stop is not None and decoded < stop:
        raise VideoError(f"{path.name}: frames up to {stop} requested but the video has only {decoded}")
    if not frames:
        raise VideoError(f"{path.name}: no frames in [{start}, {stop}) (the video has {decoded})")
    return np.stack(frames)


def _check_range(start: int, stop: int | None, step: int) -> None:
    if int(start) != start or start < 0:
        raise VideoError(f"start must be a non-negative integer, got {start!r}")
    if stop is not None and (int(stop) != stop or stop <= start):
        raise VideoError(f"stop must be an integer greater than start ({start}), got {stop!r}")
    if int(step) != step or step < 1:
        raise VideoError(f"step must be a positive integer, got {step!r}")


def _to_rgb(frame: av.VideoFrame, size: tuple[int, int] | None) -> np.ndarray:
    """RGB24 as displayed (display rotation applied), converted exactly as the ffmpeg command
    line does (accurate rounding, full chroma interpolation), so metrics match numbers computed
    with ffmpeg-decoded frames. `size` is the displayed (width, height)."""
    turns = _quarter_turns(frame)
    filter_ = Interpolation.BICUBIC
    options: dict[str, object] = {"format": "rgb24"}
    colorspace = _COLORSPACES.get(int(frame.colorspace))
    if colorspace:
        options["src_colorspace"] = colorspace
    if size is not None:
        stored = (size[1], size[0]) if turns % 2 else (size[0], size[1])
        if stored != (frame.width, frame.height):
            if stored[0] * stored[1] < frame.width * frame.height:
                filter_ = Interpolation.AREA  # shrinking: average, do not alias
            options.update(width=int(stored[0]), height=int(stored[1]))
    options["interpolation"] = filter_ | Interpolation.ACCURATE_RND | Interpolation.FULL_CHR_H_INT
    image = frame.to_ndarray(**options)
    return np.ascontiguousarray(np.rot90(image, turns)) if turns else image


def is_grayscale(frames: np.ndarray) -> bool:
    """True when (almost) every pixel has R = G = B up to codec rounding: grey smoke footage.

    One channel is trivially grey. A few deviating pixels (compression noise, a timestamp
    overlay) are tolerated; coloured smoke or a coloured scene is not.
    """
    frames = np.asarray(frames)
    if frames.ndim < 3:
        raise VideoError(f"frames must be (..., H, W, C), got shape {frames.shape}")
    if frames.shape[-1] == 1:
        return True
    if frames.shape[-1] not in (3, 4):
        raise VideoError(f"frames must have 1, 3 or 4 channels, got {frames.shape[-1]}")
    rgb = frames[..., :3].astype(np.int16) if frames.dtype == np.uint8 else np.asarray(frames[..., :3]) * 255.0
    spread = np.max(rgb, axis=-1) - np.min(rgb, axis=-1)
    return bool(np.mean(spread <= GREY_TOLERANCE) >= GREY_FRACTION)


def write_mp4(path: str | Path, frames: np.ndarray, fps: float = 30.0) -> Path:
    """Encode frames (T, H, W, C), C in {1, 3}, uint8 or float in [0, 1], as H.264 yuv420p MP4.

    Odd widths/heights are padded by one replicated edge row/column (see the module docstring).
    Returns the path written.
    """
    path = Path(path)
    video = _as_uint8_rgb(frames)
    if not (isinstance(fps, (int, float)) and math.isfinite(fps) and 0 < fps <= 1000):
        raise VideoError(f"fps must be a positive finite number up to 1000, got {fps!r}")
    pad_h, pad_w = video.shape[1] % 2, video.shape[2] % 2
    if pad_h or pad_w:
        video = np.pad(video, ((0, 0), (0, pad_h), (0, pad_w), (0, 0)), mode="edge")
    with atomic_output(path, suffix=".mp4") as temporary:
        _encode(temporary, video, fps)
    return path


def _as_uint8_rgb(frames: np.ndarray) -> np.ndarray:
    video = np.asarray(frames)
    if video.ndim != 4 or video.shape[-1] not in (1, 3) or 0 in video.shape:
        raise VideoError(f"frames must be a non-empty (T, H, W, C) array with C = 1 or 3, got shape {video.shape}")
    if video.dtype == np.uint8:
        pass
    elif np.issubdtype(video.dtype, np.floating):
        if not np.all(np.isfinite(video)):
            raise VideoError("frames contain NaN or infinite values")
        low, high = float(video.min()), float(video.max())
        if low < -1e-6 or high > 1 + 1e-6:
            raise VideoError(f"float frames must lie in [0, 1], got values in [{low:.4g}, {high:.4g}]")
        video = np.round(np.clip(video, 0.0, 1.0) * 255.0).astype(np.uint8)
    else:
        raise VideoError(f"frames must be uint8 or float in [0, 1], got dtype {video.dtype}")
    if video.shape[-1] == 1:
        video = np.repeat(video, 3, axis=-1)
    return np.ascontiguousarray(video)


def _encode(path: Path, video: np.ndarray, fps: float) -> None:
    with av.open(str(path), mode="w", format="mp4", options={"movflags": "+faststart"}) as container:
        stream = container.add_stream("libx264", rate=Fraction(fps).limit_denominator(1001))
        stream.width, stream.height = video.shape[2], video.shape[1]
        stream.pix_fmt = "yuv420p"
        stream.options = {"crf": str(CRF), "preset": "medium"}
        context = stream.codec_context
        context.color_primaries = context.color_trc = context.colorspace = 6  # SMPTE 170M = BT.601
        context.color_range = 1  # limited ("tv") range, what players assume for yuv420p
        for image in video:
            frame = av.VideoFrame.from_ndarray(image, format="rgb24").reformat(
                format="yuv420p", dst_colorspace="itu601"
            )
            container.mux(stream.encode(frame))
        container.mux(stream.encode(None))

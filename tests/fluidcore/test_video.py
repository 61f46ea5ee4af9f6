"""fluidcore.video: probe, decode (MP4/MOV/WebM), frame selection, resize, grey detection, browser MP4."""

from __future__ import annotations

from fractions import Fraction
from pathlib import Path

import av
import numpy as np
import pytest

from fluidcore.video import VideoError, is_grayscale, probe, read_frames, write_mp4


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return float(10 * np.log10(255.0**2 / mse))


def _pattern(frames: int, height: int, width: int, colour: bool) -> np.ndarray:
    """Smooth moving pattern, uint8 (T, H, W, 3); grey when colour is False."""
    y, x = np.mgrid[0:height, 0:width] / max(height, width)
    video = []
    for t in range(frames):
        a = 0.5 + 0.35 * np.sin(9 * x + 0.7 * t) * np.cos(5 * y)
        rgb = np.stack([a, 0.3 + 0.6 * y, 0.5 + 0.4 * np.cos(7 * y - 0.5 * t)], -1) if colour else np.repeat(a[..., None], 3, -1)
        video.append(rgb)
    return np.round(np.stack(video) * 255).astype(np.uint8)


def _ramp(frames: int) -> np.ndarray:
    """Frame t is flat grey 20 * t + 10: the mean names the frame index."""
    return np.stack([np.full((32, 48, 3), 20 * t + 10, dtype=np.uint8) for t in range(frames)])


def test_write_mp4_is_browser_h264_and_round_trips(tmp_path: Path) -> None:
    grey = _pattern(6, 64, 96, colour=False)
    path = write_mp4(tmp_path / "out" / "grey.mp4", grey, fps=24)
    with av.open(str(path)) as container:  # check with PyAV itself, not with our probe
        stream = container.streams.video[0]
        assert stream.codec_context.name == "h264"
        assert stream.codec_context.pix_fmt == "yuv420p"
        assert float(stream.average_rate) == 24.0
    info = probe(path)
    assert (info.width, info.height, info.n_frames, info.codec, info.pix_fmt) == (96, 64, 6, "h264", "yuv420p")
    assert _psnr(read_frames(path), grey) > 40.0
    colour = _pattern(6, 64, 96, colour=True)
    write_mp4(tmp_path / "colour.mp4", colour.astype(np.float32) / 255.0)  # float input
    assert _psnr(read_frames(tmp_path / "colour.mp4"), colour) > 30.0  # 4:2:0 chroma costs a few dB


def test_odd_sizes_are_padded_to_even(tmp_path: Path) -> None:
    frames = _pattern(3, 37, 51, colour=False)
    info = probe(write_mp4(tmp_path / "odd.mp4", frames))
    assert (info.width, info.height) == (52, 38)
    back = read_frames(tmp_path / "odd.mp4")
    assert _psnr(back[:, :37, :51], frames) > 40.0  # nothing cropped
    assert _psnr(back[:, 37, :51], frames[:, 36]) > 35.0  # the padding repeats the edge


def test_single_channel_float_input(tmp_path: Path) -> None:
    grey = _pattern(2, 32, 32, colour=False)[..., :1].astype(np.float32) / 255.0
    back = read_frames(write_mp4(tmp_path / "one.mp4", grey))
    assert back.shape == (2, 32, 32, 3)
    assert _psnr(back[..., 1:2], np.round(grey * 255)) > 35.0  # tiny frame: x264 spends few bits


def test_frame_selection_and_resize(tmp_path: Path) -> None:
    path = write_mp4(tmp_path / "ramp.mp4", _ramp(10))
    picked = read_frames(path, start=1, stop=8, step=3)
    np.testing.assert_allclose(picked.reshape(3, -1).mean(1), [30, 90, 150], atol=2.0)
    assert read_frames(path, start=8).shape[0] == 2
    resized = read_frames(path, stop=2, size=(24, 16))
    assert resized.shape == (2, 16, 24, 3)
    np.testing.assert_allclose(resized.reshape(2, -1).mean(1), [10, 30], atol=2.0)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"stop": 11}, "only 10"),
        ({"start": -1}, "start"),
        ({"start": 4, "stop": 4}, "stop"),
        ({"step": 0}, "step"),
        ({"size": (0, 10)}, "size"),
    ],
)
def test_invalid_requests(tmp_path: Path, kwargs: dict, message: str) -> None:
    path = write_mp4(tmp_path / "ramp.mp4", _ramp(10))
    with pytest.raises(VideoError, match=message):
        read_frames(path, **kwargs)


@pytest.mark.parametrize("kept", [0.6, 0.95])  # cut inside the first frames / near the end
def test_broken_files_raise_clear_errors(tmp_path: Path, kept: float) -> None:
    good = write_mp4(tmp_path / "good.mp4", _pattern(20, 64, 64, colour=True))
    data = good.read_bytes()
    (tmp_path / "truncated.mp4").write_bytes(data[: int(len(data) * kept)])
    (tmp_path / "random.mp4").write_bytes(np.random.default_rng(0).bytes(4096))
    (tmp_path / "text.mp4").write_text("this is a text file with a video name\n" * 50)
    for name, message in [("truncated", ".*truncated"), ("random", "not a readable video"), ("text", "not a readable video")]:
        path = tmp_path / f"{name}.mp4"
        with pytest.raises(VideoError, match=f"{name}.mp4: {message}"):
            probe(path)
        with pytest.raises(VideoError, match=f"{name}.mp4"):
            read_frames(path)
    with pytest.raises(VideoError, match="no such file"):
        probe(tmp_path / "absent.mp4")


def test_bad_frames_leave_an_existing_file_alone(tmp_path: Path) -> None:
    path = write_mp4(tmp_path / "keep.mp4", _ramp(3))
    bad = np.full((2, 8, 8, 3), np.nan, dtype=np.float32)
    for frames, message in [(bad, "NaN"), (bad[..., :2] * 0 + 2.0, "C = 1 or 3"), (np.full((1, 8, 8, 3), 1.5), r"\[0, 1\]")]:
        with pytest.raises(VideoError, match=message):
            write_mp4(path, frames)
    with pytest.raises(VideoError, match="fps"):
        write_mp4(path, _ramp(2), fps=0)
    assert probe(path).n_frames == 3
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep.mp4"]  # no temporary leftovers


def _encode_with_pyav(path: Path, codec: str, frames: np.ndarray, pix_fmt: str) -> Path:
    try:
        av.codec.Codec(codec, "w")
    except Exception:  # PyAV raises UnknownCodecError; its base differs between versions
        pytest.skip(f"encoder {codec} is not in this PyAV build")
    with av.open(str(path), mode="w") as container:
        stream = container.add_stream(codec, rate=Fraction(25))
        stream.width, stream.height, stream.pix_fmt = frames.shape[2], frames.shape[1], pix_fmt
        for image in frames:
            container.mux(stream.encode(av.VideoFrame.from_ndarray(image, format="rgb24")))
        container.mux(stream.encode(None))
    return path


@pytest.mark.parametrize(
    ("name", "codec", "pix_fmt"),
    [("clip.mov", "libx264", "yuv420p"), ("clip.mov", "prores_ks", "yuv422p10le"), ("clip.webm", "libvpx-vp9", "yuv420p")],
)
def test_mov_and_webm_decode(tmp_path: Path, name: str, codec: str, pix_fmt: str) -> None:
    frames = _pattern(5, 48, 64, colour=False)
    path = _encode_with_pyav(tmp_path / name, codec, frames, pix_fmt)
    info = probe(path)
    assert (info.width, info.height, info.n_frames) == (64, 48, 5)
    assert info.fps == pytest.approx(25.0)
    assert _psnr(read_frames(path), frames) > 35.0


def test_is_grayscale() -> None:
    grey = _pattern(2, 32, 32, colour=False)
    assert is_grayscale(grey)
    assert is_grayscale(grey[..., :1])
    noisy = grey.astype(np.int16) + np.random.default_rng(1).integers(-1, 2, grey.shape)
    assert is_grayscale(np.clip(noisy, 0, 255).astype(np.uint8))  # codec rounding is still grey
    assert not is_grayscale(_pattern(2, 32, 32, colour=True))
    tinted = grey.copy()
    tinted[..., 0] = np.clip(tinted[..., 0].astype(int) + 30, 0, 255)
    assert not is_grayscale(tinted)


def test_shared_input_video(realdata: Path) -> None:
    path = realdata / "scalarflow" / "videos" / "input_view_02.mp4"
    info = probe(path)
    assert (info.width, info.height, info.n_frames, info.codec) == (648, 1160, 120, "h264")
    frames = read_frames(path, start=0, stop=30, step=10, size=(324, 580))
    assert frames.shape == (3, 580, 324, 3)
    assert is_grayscale(frames)  # ScalarFlow panels are processed grey smoke


def test_display_rotation_is_applied(tmp_path: Path) -> None:
    """A phone stores portrait video as landscape plus a rotation; we return what players show."""
    image = np.zeros((32, 64, 3), dtype=np.uint8)
    image[:8, :16] = 255  # a white block in the stored top-left corner
    path = tmp_path / "portrait.mp4"
    with av.open(str(path), mode="w") as container:
        stream = container.add_stream("libx264", rate=Fraction(25))
        stream.width, stream.height, stream.pix_fmt = 64, 32, "yuv420p"
        stream.set_display_rotation(90)  # counter-clockwise, as players apply it
        for _ in range(2):
            container.mux(stream.encode(av.VideoFrame.from_ndarray(image, format="rgb24")))
        container.mux(stream.encode(None))
    info = probe(path)
    assert (info.width, info.height) == (32, 64)
    frames = read_frames(path)
    assert frames.shape == (2, 64, 32, 3)
    assert frames[0, 60, 2].mean() > 200 and frames[0, 2, 2].mean() < 50  # top-left went to bottom-left
    assert read_frames(path, size=(16, 32)).shape == (2, 32, 16, 3)

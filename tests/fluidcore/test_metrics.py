"""fluidcore.metrics against scikit-image, and LPIPS through the real weight-loading path with a tiny net."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from fluidcore import metrics, weights
from fluidcore.metrics import AlexLPIPS, MetricError, lpips, lpips_available, psnr, ssim, ssim_tensor

SKIMAGE_SETTINGS = {
    "gaussian": {"gaussian_weights": True, "sigma": 1.5, "use_sample_covariance": False},
    "uniform": {},  # skimage's defaults: 7x7 box, sample covariance (the realdata anchors)
}


def _pair(shape: tuple[int, ...], seed: int = 0, noise: float = 0.03) -> tuple[np.ndarray, np.ndarray]:
    """A smooth image with texture, and a noisy, slightly shifted copy; both in [0, 1]."""
    rng = np.random.default_rng(seed)
    *lead, h, w, c = shape
    y, x = np.mgrid[0:h, 0:w] / 16.0
    base = 0.5 + 0.3 * np.sin(x[..., None] + np.arange(c)) * np.cos(y[..., None]) + 0.1 * rng.random((*lead, h, w, c))
    target = np.clip(base, 0, 1).astype(np.float32)
    pred = np.clip(np.roll(target, 1, axis=-2) + noise * rng.standard_normal(target.shape), 0, 1).astype(np.float32)
    return pred, target


def _skimage_ssim(pred: np.ndarray, target: np.ndarray, window: str) -> float:
    frames = pred[None] if pred.ndim == 3 else pred
    targets = target[None] if target.ndim == 3 else target
    scores = [
        structural_similarity(t, p, channel_axis=-1, data_range=1.0, **SKIMAGE_SETTINGS[window])
        for p, t in zip(frames, targets)
    ]
    return float(np.mean(scores))


@pytest.mark.parametrize("window", ["gaussian", "uniform"])
@pytest.mark.parametrize("shape", [(48, 64, 1), (40, 57, 3), (3, 33, 45, 3), (2, 30, 30, 1)])
def test_ssim_matches_skimage(shape: tuple[int, ...], window: str) -> None:
    pred, target = _pair(shape)
    expected = _skimage_ssim(pred, target, window)
    assert ssim(torch.from_numpy(pred), torch.from_numpy(target), window=window) == pytest.approx(expected, abs=1e-3)
    assert 0.2 < expected < 0.99  # the pair is neither identical nor unrelated


def test_grey_rgb_shortcut_matches_skimage() -> None:
    pred, target = (np.repeat(a, 3, axis=-1) for a in _pair((2, 40, 50, 1)))
    expected = _skimage_ssim(pred, target, "uniform")
    assert ssim(torch.from_numpy(pred), torch.from_numpy(target), window="uniform") == pytest.approx(expected, abs=1e-3)
    tinted = pred.copy()
    tinted[..., 0] = np.clip(tinted[..., 0] + 0.2, 0, 1)  # no longer grey: all channels count
    expected = _skimage_ssim(tinted, target, "uniform")
    assert ssim(torch.from_numpy(tinted), torch.from_numpy(target), window="uniform") == pytest.approx(expected, abs=1e-3)


def test_psnr_matches_skimage_per_frame_mean() -> None:
    pred, target = _pair((4, 32, 40, 3), noise=0.03)
    expected = np.mean([peak_signal_noise_ratio(t, p, data_range=1.0) for p, t in zip(pred, target)])
    assert psnr(torch.from_numpy(pred), torch.from_numpy(target)) == pytest.approx(expected, abs=1e-3)
    frame = torch.from_numpy(target[0])
    assert psnr(frame, frame) == metrics.PSNR_CAP_DB  # identical: capped, finite


def test_ssim_is_long_video_safe(monkeypatch: pytest.MonkeyPatch) -> None:
    """Chunking over frames must not change the result."""
    pred, target = (torch.from_numpy(a) for a in _pair((5, 24, 24, 1)))
    whole = ssim(pred, target)
    monkeypatch.setattr(metrics, "CHUNK_ELEMENTS", 24 * 24 * 2)  # two frames per chunk
    assert ssim(pred, target) == pytest.approx(whole, abs=1e-12)


def test_ssim_tensor_is_differentiable() -> None:
    pred, target = (torch.from_numpy(a).double() for a in _pair((16, 16, 1)))
    pred.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda p: ssim_tensor(p, target), (pred,))
    ssim_tensor(pred, target).backward()
    assert pred.grad is not None and pred.grad.abs().sum() > 0


@pytest.mark.parametrize("check_values", [False, True])
def test_ssim_tensor_never_converts_a_grad_tensor(check_values: bool) -> None:
    """float() on a tensor that needs grad warns (and syncs a GPU) on every reconstruction step."""
    pred, target = (torch.from_numpy(a) for a in _pair((16, 16, 1)))
    pred.requires_grad_(True)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ssim_tensor(pred, target, check_values=check_values).backward()
    assert pred.grad is not None


def test_loss_path_tolerates_overshoot_but_the_metric_does_not() -> None:
    """A renderer under optimisation may overshoot [0, 1]; the loss must not stop it, the score must."""
    pred, target = (torch.from_numpy(a) for a in _pair((20, 20, 1)))
    overshoot = pred * 1.3
    assert torch.isfinite(ssim_tensor(overshoot, target))
    with pytest.raises(MetricError, match=r"\[0, 1\]"):
        ssim(overshoot, target)


@pytest.mark.parametrize(
    ("pred", "target", "message"),
    [
        (torch.zeros(8, 8, 3), torch.zeros(8, 8, 1), "shapes differ"),
        (torch.zeros(8, 8), torch.zeros(8, 8), r"\(H, W, C\)"),
        (torch.full((8, 8, 1), 255.0), torch.zeros(8, 8, 1), r"\[0, 1\]"),
        (torch.full((8, 8, 1), float("nan")), torch.zeros(8, 8, 1), "NaN"),
        (torch.zeros(8, 8, 1, dtype=torch.uint8), torch.zeros(8, 8, 1), "float tensor"),
    ],
)
def test_bad_inputs_are_rejected(pred: torch.Tensor, target: torch.Tensor, message: str) -> None:
    with pytest.raises(MetricError, match=message):
        psnr(pred, target)


def test_ssim_rejects_images_smaller_than_the_window() -> None:
    with pytest.raises(MetricError, match="11x11"):
        ssim(torch.zeros(10, 20, 1), torch.zeros(10, 20, 1))
    with pytest.raises(MetricError, match="window"):
        ssim(torch.zeros(20, 20, 1), torch.zeros(20, 20, 1), window="box")


# --- LPIPS --------------------------------------------------------------------------------------
TINY_WIDTHS = (4, 6, 8, 6, 5)


def _tiny_state(seed: int = 0) -> dict[str, torch.Tensor]:
    """A randomly initialised tiny LPIPS network's weights (non-negative heads, as trained ones are)."""
    torch.manual_seed(seed)
    model = AlexLPIPS(TINY_WIDTHS)
    for k in range(5):
        head = getattr(model, f"lin{k}").model[1]
        head.weight.data.abs_()
    return model.state_dict()


def _reference_lpips(state: dict[str, torch.Tensor], x: torch.Tensor, y: torch.Tensor) -> float:
    """LPIPS written out layer by layer from the published recipe, independent of AlexLPIPS."""
    shift = torch.tensor([-0.030, -0.088, -0.188]).view(1, 3, 1, 1)
    scale = torch.tensor([0.458, 0.448, 0.450]).view(1, 3, 1, 1)

    def features(image: torch.Tensor) -> list[torch.Tensor]:
        h = ((image.permute(2, 0, 1)[None] * 2 - 1) - shift) / scale
        taps = []
        for layer, (index, stride, padding) in enumerate([(0, 4, 2), (3, 1, 2), (6, 1, 1), (8, 1, 1), (10, 1, 1)]):
            h = F.relu(F.conv2d(h, state[f"features.{index}.weight"], state[f"features.{index}.bias"], stride, padding))
            taps.append(h)
            if layer < 2:
                h = F.max_pool2d(h, 3, 2)
        return taps

    total = 0.0
    for k, (a, b) in enumerate(zip(features(x), features(y))):
        a = a / (a.norm(dim=1, keepdim=True) + 1e-10)
        b = b / (b.norm(dim=1, keepdim=True) + 1e-10)
        total += float((F.conv2d((a - b) ** 2, state[f"lin{k}.model.1.weight"])).mean())
    return total


def test_lpips_is_null_without_weights(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    pred, target = (torch.from_numpy(a) for a in _pair((40, 40, 3)))
    assert lpips(pred, target, weights_dir=tmp_path) is None
    monkeypatch.setenv(weights.ENV_VAR, str(tmp_path))
    assert weights.weights_dir() == tmp_path and lpips(pred, target) is None and not lpips_available()
    heads_only = {k: v for k, v in _tiny_state().items() if k.startswith("lin")}
    (tmp_path / "lpips").mkdir()
    torch.save(heads_only, tmp_path / "lpips" / "alex.pth")
    assert lpips(pred, target) is None  # the heads alone are not a network: still null


def test_lpips_loads_a_tiny_network_through_the_real_path(tmp_path: Path) -> None:
    state = _tiny_state()
    (tmp_path / "lpips").mkdir()
    torch.save(state, tmp_path / "lpips" / "alex.pth")
    pred, target = (torch.from_numpy(a) for a in _pair((2, 48, 64, 3)))
    value = lpips(pred, target, weights_dir=tmp_path)
    expected = np.mean([_reference_lpips(state, p, t) for p, t in zip(pred, target)])
    assert value == pytest.approx(expected, rel=1e-4)
    assert value > 0
    assert lpips(target, target, weights_dir=tmp_path) == pytest.approx(0.0, abs=1e-7)
    grey = target[..., :1]
    assert lpips(grey, grey.flip(0), weights_dir=tmp_path) > 0  # one channel is repeated to RGB


def test_lpips_split_files_like_the_published_ones(tmp_path: Path) -> None:
    """Published layout: LPIPS heads in alex.pth, torchvision's AlexNet (with its classifier) beside it."""
    state = _tiny_state(seed=1)
    (tmp_path / "lpips").mkdir()
    backbone = {k: v for k, v in state.items() if k.startswith("features.")}
    backbone["classifier.1.weight"] = torch.zeros(2, 2)  # ignored, as torchvision's classifier is
    torch.save(backbone, tmp_path / "lpips" / "alexnet.pth")
    torch.save({k: v for k, v in state.items() if k.startswith("lin")}, tmp_path / "lpips" / "alex.pth")
    pred, target = (torch.from_numpy(a) for a in _pair((40, 44, 3)))
    assert lpips_available(tmp_path)
    assert lpips(pred, target, weights_dir=tmp_path) == pytest.approx(_reference_lpips(state, pred, target), rel=1e-4)


def test_lpips_bad_weights_and_inputs_raise(tmp_path: Path) -> None:
    (tmp_path / "lpips").mkdir()
    (tmp_path / "lpips" / "alex.pth").write_bytes(b"not a torch file")
    image = torch.rand(40, 40, 3)
    with pytest.raises(MetricError, match="unreadable LPIPS weights"):
        lpips(image, image, weights_dir=tmp_path)
    state = _tiny_state()
    del state["lin3.model.1.weight"]
    torch.save(state, tmp_path / "lpips" / "alex.pth")
    with pytest.raises(MetricError, match="lin3.model.1.weight"):
        lpips(image, image, weights_dir=tmp_path)
    torch.save(_tiny_state(), tmp_path / "lpips" / "alex.pth")
    with pytest.raises(MetricError, match="too small"):
        lpips(torch.rand(20, 40, 3), torch.rand(20, 40, 3), weights_dir=tmp_path)


def test_weights_find_stays_inside_the_models_folder(tmp_path: Path) -> None:
    (tmp_path / "a").mkdir()
    assert weights.find("a", tmp_path) == tmp_path / "a"
    assert weights.find("b.pth", tmp_path) is None
    for name in ("../escape.pth", "/etc/passwd", ""):
        with pytest.raises(ValueError, match="relative path"):
            weights.find(name, tmp_path)


def test_decode_and_metrics_reproduce_the_realdata_anchors(realdata: Path) -> None:
    """End to end against an independent pipeline: anchors.json was computed from ffmpeg-decoded
    frames with scikit-image; our PyAV decode plus torch metrics must give the same per-frame numbers."""
    import json

    from fluidcore.video import read_frames

    scene = realdata / "scalarflow"
    anchors = json.loads((scene / "anchors.json").read_text())["per_frame"]["nvs"]["0"]["pinf"]
    gt, pred = (
        torch.from_numpy(read_frames(scene / folder / "nvs_view_00.mp4", 0, 2)).float() / 255.0
        for folder in ("gt", "baselines/pinf")
    )
    for frame in range(2):
        expected_psnr, expected_ssim = anchors[frame]
        assert psnr(pred[frame], gt[frame]) == pytest.approx(expected_psnr, abs=1e-3)
        assert ssim(pred[frame], gt[frame], window="uniform") == pytest.approx(expected_ssim, abs=1e-4)


@pytest.mark.slow
def test_metrics_bench_prints_one_json_object() -> None:
    import json
    import subprocess
    import sys

    root = Path(__file__).resolve().parents[2]
    result = subprocess.run(
        [sys.executable, str(root / "bench" / "metrics.py"), "--repeats", "1", "--threads", "1", "--json"],
        capture_output=True, text=True, check=True, cwd=root,
    )
    report = json.loads(result.stdout)
    assert report["threads"] == 1
    assert {row["what"] for row in report["rows"]} >= {"ssim_tensor fwd+bwd f32", "read_frames", "write_mp4 (x264 crf 18)"}
    assert all(row["ms"] > 0 for row in report["rows"])

"""Image quality metrics in torch: PSNR, SSIM and LPIPS, on the device of their inputs.

Inputs are images (H, W, C) or videos (T, H, W, C), float in [0, 1], C = 1 (grey smoke) or 3.
Video scores are the mean of per-frame scores, as the shared realdata anchors are computed.

PSNR is 10 log10(1 / MSE) per frame; identical frames are capped at 100 dB so reports stay
finite JSON.

SSIM follows scikit-image's `structural_similarity(..., channel_axis=-1, data_range=1)` exactly:
  - window="gaussian" (default): 11-tap Gaussian, sigma 1.5, population covariance
    (skimage gaussian_weights=True, use_sample_covariance=False; the usual paper setting);
  - window="uniform": 7x7 box with sample covariance (skimage's defaults, which the
    realdata anchors.json numbers use; pick this to compare with them).
Statistics are taken only where the whole window fits (skimage's border crop), so no padding
mode enters the result. `ssim_tensor` is the differentiable version for losses.

LPIPS (Zhang et al. 2018, AlexNet variant, v0.1) runs only with local weights, never downloaded;
without them `lpips` returns None and callers report null. Expected files in the models folder
(fluidcore.weights: $FLUIDNEXUS_MODELS, default ./models):
  - lpips/alex.pth: the LPIPS linear heads as published, a state dict with
    `lin{k}.model.1.weight` of shape (1, C_k, 1, 1) for k = 0..4;
  - lpips/alexnet.pth: the AlexNet backbone as torchvision publishes it (e.g. a renamed
    alexnet-owt-7be5be79.pth); its `features.{0,3,6,8,10}.weight/bias` entries are used and the
    classifier is ignored. The backbone entries may instead live in lpips/alex.pth itself.
Channel widths and kernel sizes are read from the state dict, so tests can save a tiny random
network and load it through this same code path.
"""

from __future__ import annotations

import functools
import math
from pathlib import Path
from typing import Iterator, Sequence

import torch
import torch.nn.functional as F
from torch import nn

from fluidcore.errors import InputError
from fluidcore.weights import find

PSNR_CAP_DB = 100.0
RANGE_TOLERANCE = 1e-4  # inputs may overshoot [0, 1] by float rounding, not by a 0..255 mix-up
CHUNK_ELEMENTS = 1 << 22  # SSIM input values per step: ~0.5 GB peak in float64 however long the video
SSIM_WINDOWS = {"gaussian": (11, False), "uniform": (7, True)}  # size, sample covariance
LPIPS_HEADS = "lpips/alex.pth"
LPIPS_BACKBONE = "lpips/alexnet.pth"
LPIPS_BATCH = 8


class MetricError(InputError):
    """Inputs a metric cannot score (shape, range, NaN), or unreadable metric weights."""


def _as_video(pred: torch.Tensor, target: torch.Tensor, check_values: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    """Validate and return (T, H, W, C) views of both inputs.

    `check_values` also requires finite values in [0, 1]; the loss path skips it, because a
    renderer's output may overshoot while it is being optimised (and each check syncs a GPU)."""
    for name, value in (("pred", pred), ("target", target)):
        if not isinstance(value, torch.Tensor) or not value.is_floating_point():
            raise MetricError(f"{name} must be a float tensor, got {type(value).__name__}")
    if pred.shape != target.shape:
        raise MetricError(f"pred and target shapes differ: {tuple(pred.shape)} vs {tuple(target.shape)}")
    if pred.ndim not in (3, 4) or pred.numel() == 0:
        raise MetricError(f"images must be (H, W, C) or (T, H, W, C), got shape {tuple(pred.shape)}")
    if check_values:
        for name, value in (("pred", pred.detach()), ("target", target.detach())):
            if not torch.isfinite(value).all():
                raise MetricError(f"{name} contains NaN or infinite values")
            low, high = float(value.min()), float(value.max())
            if low < -RANGE_TOLERANCE or high > 1 + RANGE_TOLERANCE:
                raise MetricError(f"{name} must lie in [0, 1], got values in [{low:.4g}, {high:.4g}]")
    if pred.ndim == 3:
        return pred[None], target[None]
    return pred, target


def psnr(pred: torch.Tensor, target: torch.Tensor) -> float:
    """Mean over frames of 10 log10(1 / MSE) in dB (data range 1), capped at 100 dB."""
    p, t = _as_video(pred, target)
    mse = (p.double() - t.double()).pow(2).mean(dim=(1, 2, 3))
    floor = 10.0 ** (-PSNR_CAP_DB / 10.0)
    return float((-10.0 * torch.log10(mse.clamp_min(floor))).mean())


# --- SSIM ---------------------------------------------------------------------------------------
def _window_taps(window: str) -> tuple[float, ...]:
    """The 1-D window, normalised to sum 1 (scipy's gaussian_filter normalises its truncated taps)."""
    size, _ = SSIM_WINDOWS[window]
    if window == "uniform":
        return (1.0 / size,) * size
    weights = [math.exp(-((i - (size - 1) / 2) ** 2) / (2 * 1.5**2)) for i in range(size)]
    return tuple(w / sum(weights) for w in weights)


def _correlate_valid(images: torch.Tensor, taps: Sequence[float]) -> torch.Tensor:
    """Separable 'valid' correlation of (..., H, W) images with `taps` along W then H.

    Shifted in-place multiply-adds: for single-channel images with an 11-tap window this is
    several times faster than conv2d on CPU, which matters because SSIM sits in the
    reconstruction loss."""
    for dim in (-1, -2):
        n = images.shape[dim] - len(taps) + 1
        out = images.narrow(dim, 0, n) * taps[0]
        for i in range(1, len(taps)):
            out.add_(images.narrow(dim, i, n), alpha=taps[i])
        images = out
    return images


class _WindowBlur(torch.autograd.Function):
    """`_correlate_valid` with a hand-written backward (a full convolution: zero-pad the gradient
    and correlate with the reversed taps), which avoids autograd's one scatter per tap."""

    @staticmethod
    def forward(ctx, images: torch.Tensor, taps: tuple[float, ...]) -> torch.Tensor:  # noqa: ANN001
        ctx.taps = taps
        return _correlate_valid(images, taps)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad: torch.Tensor) -> tuple[torch.Tensor, None]:  # noqa: ANN001
        k = len(ctx.taps) - 1
        return _correlate_valid(F.pad(grad, (k, k, k, k)), ctx.taps[::-1]), None


def _frame_chunks(video: torch.Tensor) -> Iterator[slice]:
    per_frame = max(1, video[0].numel())
    step = max(1, CHUNK_ELEMENTS // per_frame)
    for start in range(0, video.shape[0], step):
        yield slice(start, start + step)


def ssim_tensor(pred: torch.Tensor, target: torch.Tensor, window: str = "gaussian", check_values: bool = False) -> torch.Tensor:
    """Differentiable mean SSIM (0-dim tensor, dtype of the inputs) for losses; see the module
    docstring. Values are not range-checked unless asked (see `_as_video`)."""
    if window not in SSIM_WINDOWS:
        raise MetricError(f"window must be one of {sorted(SSIM_WINDOWS)}, got {window!r}")
    p, t = _as_video(pred, target, check_values)
    size, sample_covariance = SSIM_WINDOWS[window]
    if min(p.shape[1], p.shape[2]) < size:
        raise MetricError(f"images must be at least {size}x{size} pixels for SSIM, got {p.shape[2]}x{p.shape[1]}")
    taps = _window_taps(window)
    covariance_norm = size * size / (size * size - 1) if sample_covariance else 1.0
    total, count = p.new_zeros(()), 0
    for chunk in _frame_chunks(p):
        ssim_map = _ssim_map(p[chunk], t[chunk], taps, covariance_norm)
        total = total + ssim_map.sum()
        count += ssim_map.numel()
    return total / count


def _ssim_map(x: torch.Tensor, y: torch.Tensor, taps: tuple[float, ...], covariance_norm: float) -> torch.Tensor:
    """SSIM at every pixel where the window fits, for (T, H, W, C) inputs."""
    frames, height, width, channels = x.shape
    x = x.permute(0, 3, 1, 2).reshape(frames * channels, height, width)
    y = y.permute(0, 3, 1, 2).reshape(frames * channels, height, width)
    blurred = _WindowBlur.apply(torch.cat((x, y, x * x, y * y, x * y)), taps)
    mx, my, mxx, myy, mxy = blurred.chunk(5)
    vx = covariance_norm * (mxx - mx * mx)
    vy = covariance_norm * (myy - my * my)
    vxy = covariance_norm * (mxy - mx * my)
    c1, c2 = 0.01**2, 0.03**2
    return ((2 * mx * my + c1) * (2 * vxy + c2)) / ((mx * mx + my * my + c1) * (vx + vy + c2))


def ssim(pred: torch.Tensor, target: torch.Tensor, window: str = "gaussian") -> float:
    """Mean SSIM over frames and channels, computed in float64 (agrees with scikit-image).
    Grey frames stored as RGB are scored on one channel (identical result, a third of the work)."""
    if pred.ndim in (3, 4) and pred.shape == target.shape and _grey_rgb(pred) and _grey_rgb(target):
        pred, target = pred[..., :1], target[..., :1]  # R = G = B: one channel gives the same mean, 3x sooner
    with torch.no_grad():
        value = ssim_tensor(pred.double(), target.double(), window, check_values=True)
    return float(value)


def _grey_rgb(images: torch.Tensor) -> bool:
    """Exactly equal colour channels, as in grey smoke videos decoded to RGB."""
    return images.shape[-1] == 3 and torch.equal(images[..., 0], images[..., 1]) and torch.equal(images[..., 1], images[..., 2])


# --- LPIPS --------------------------------------------------------------------------------------
_CONV_INDICES = (0, 3, 6, 8, 10)  # torchvision AlexNet `features` indices of the five convolutions
_TAP_INDICES = (1, 4, 7, 9, 11)  # the ReLUs after them, where LPIPS compares features
_SHIFT = (-0.030, -0.088, -0.188)  # LPIPS input normalisation (inputs scaled to [-1, 1] first)
_SCALE = (0.458, 0.448, 0.450)


class _Head(nn.Module):
    """One LPIPS linear head; the `model.1` nesting matches the published weight names."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.model = nn.Sequential(nn.Dropout(), nn.Conv2d(channels, 1, 1, bias=False))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.model(x)


class AlexLPIPS(nn.Module):
    """LPIPS with an AlexNet-shaped backbone; `widths`/`kernels` are the five convolutions'."""

    def __init__(self, widths: Sequence[int], kernels: Sequence[int] = (11, 5, 3, 3, 3)) -> None:
        super().__init__()
        if len(widths) != 5 or len(kernels) != 5:
            raise MetricError("AlexLPIPS needs five convolution widths and kernel sizes")
        w, k = list(widths), list(kernels)
        self.features = nn.Sequential(
            nn.Conv2d(3, w[0], k[0], stride=4, padding=2), nn.ReLU(), nn.MaxPool2d(3, 2),
            nn.Conv2d(w[0], w[1], k[1], padding=k[1] // 2), nn.ReLU(), nn.MaxPool2d(3, 2),
            nn.Conv2d(w[1], w[2], k[2], padding=k[2] // 2), nn.ReLU(),
            nn.Conv2d(w[2], w[3], k[3], padding=k[3] // 2), nn.ReLU(),
            nn.Conv2d(w[3], w[4], k[4], padding=k[4] // 2), nn.ReLU(),
        )  # fmt: skip
        for index, width in enumerate(w):
            self.add_module(f"lin{index}", _Head(width))
        self.register_buffer("shift", torch.tensor(_SHIFT).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("scale", torch.tensor(_SCALE).view(1, 3, 1, 1), persistent=False)

    @classmethod
    def from_state_dict(cls, state: dict[str, torch.Tensor]) -> AlexLPIPS:
        """Build the network the state dict describes and load it (strictly)."""
        needed = [f"features.{i}.{p}" for i in _CONV_INDICES for p in ("weight", "bias")]
        needed += [f"lin{k}.model.1.weight" for k in range(5)]
        missing = [key for key in needed if key not in state]
        if missing:
            raise MetricError(f"LPIPS weights lack {', '.join(missing)}")
        convs = [state[f"features.{i}.weight"] for i in _CONV_INDICES]
        model = cls([c.shape[0] for c in convs], [c.shape[-1] for c in convs])
        try:
            model.load_state_dict({key: state[key] for key in needed})
        except RuntimeError as error:
            raise MetricError(f"LPIPS weights do not fit an AlexNet layout: {error}") from None
        return model.eval()

    def forward(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """Distance per image for (B, 3, H, W) batches in [0, 1]."""
        fx, fy = self._taps(x), self._taps(y)
        distance = x.new_zeros(x.shape[0])
        for k, (a, b) in enumerate(zip(fx, fy)):
            head = getattr(self, f"lin{k}")
            distance = distance + head((_unit_channels(a) - _unit_channels(b)) ** 2).mean(dim=(1, 2, 3))
        return distance

    def _taps(self, image: torch.Tensor) -> list[torch.Tensor]:
        h = ((2 * image - 1) - self.shift) / self.scale
        taps = []
        for index, layer in enumerate(self.features):
            h = layer(h)
            if index in _TAP_INDICES:
                taps.append(h)
        return taps


def _unit_channels(features: torch.Tensor, eps: float = 1e-10) -> torch.Tensor:
    return features / (features.pow(2).sum(dim=1, keepdim=True).sqrt() + eps)


def lpips_available(weights_dir: str | Path | None = None) -> bool:
    """Whether LPIPS weights are present (the network is not built; a heads file without a
    separate backbone file is opened to see whether it holds the backbone too)."""
    return _lpips_files(weights_dir) is not None


def _lpips_files(weights_dir: str | Path | None) -> tuple[Path, Path | None] | None:
    heads = find(LPIPS_HEADS, weights_dir)
    if heads is None:
        return None
    backbone = find(LPIPS_BACKBONE, weights_dir)
    if backbone is None and not _has_backbone(heads, heads.stat().st_mtime_ns):
        return None
    return heads, backbone


@functools.lru_cache(maxsize=8)
def _has_backbone(heads: Path, stamp: int) -> bool:
    """Whether the heads file also holds the AlexNet backbone (cached per file version)."""
    return "features.0.weight" in _read_state(heads)


def _read_state(path: Path) -> dict[str, torch.Tensor]:
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # torch raises several unrelated types for a bad file
        raise MetricError(f"{path}: unreadable LPIPS weights ({error})") from None
    if not isinstance(state, dict):
        raise MetricError(f"{path}: expected a state dict, got {type(state).__name__}")
    return state


@functools.lru_cache(maxsize=4)
def _load_lpips(heads: Path, backbone: Path | None, stamp: tuple[int, ...], device: str) -> AlexLPIPS:
    """Cached per file version (`stamp` = modification times) and device."""
    state = dict(_read_state(backbone)) if backbone is not None else {}
    state.update(_read_state(heads))
    return AlexLPIPS.from_state_dict(state).to(device)


def lpips(pred: torch.Tensor, target: torch.Tensor, weights_dir: str | Path | None = None) -> float | None:
    """Mean LPIPS distance over frames (lower is closer), or None when the weights are absent."""
    files = _lpips_files(weights_dir)
    if files is None:
        return None
    p, t = _as_video(pred, target)
    _check_lpips_size(p.shape[1], p.shape[2])
    stamp = tuple(f.stat().st_mtime_ns for f in files if f is not None)
    model = _load_lpips(*files, stamp, str(p.device))
    distances = []
    with torch.no_grad():
        for start in range(0, p.shape[0], LPIPS_BATCH):
            x, y = (_to_rgb_batch(v[start : start + LPIPS_BATCH]) for v in (p, t))
            distances.append(model(x.float(), y.float()))
    value = float(torch.cat(distances).mean())
    if not math.isfinite(value):
        raise MetricError("LPIPS produced a non-finite value; the weights are probably corrupt")
    return value


def _to_rgb_batch(frames: torch.Tensor) -> torch.Tensor:
    images = frames.permute(0, 3, 1, 2)
    if images.shape[1] == 1:
        return images.expand(-1, 3, -1, -1)
    if images.shape[1] != 3:
        raise MetricError(f"LPIPS needs 1 or 3 channels, got {images.shape[1]}")
    return images


def _check_lpips_size(height: int, width: int) -> None:
    """AlexNet's stride-4 stem and two poolings need at least a few pixels to remain."""
    smallest = min(height, width)
    after_stem = (smallest + 4 - 11) // 4 + 1
    after_pools = ((after_stem - 3) // 2 + 1 - 3) // 2 + 1 if after_stem >= 3 else 0
    if after_pools < 1:
        raise MetricError(f"{width}x{height} images are too small for LPIPS (AlexNet needs at least 31 pixels a side)")

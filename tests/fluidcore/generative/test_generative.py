"""Generative priors with tiny random models written in the public layouts (issue 13): the
registry, novel views and video refinement, loaded through the same code as real weights."""

from __future__ import annotations

import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from fluidcore.cameras import Camera, look_at
from fluidcore.generative import models, novel_view, refine

CENTER = np.array([0.0, 0.4, 0.0])
UP = np.array([0.0, 1.0, 0.0])
ZERO123_PARTS = {"unet", "vae", "image_encoder", "feature_extractor", "cc_projection", "scheduler"}
COGVIDEOX_PARTS = {"transformer", "vae", "scheduler"}


def camera_at(angle: float, name: str, distance: float = 1.6, width: int = 48, height: int = 64) -> Camera:
    like = Camera("like", 50.0, 50.0, width / 2, height / 2, width, height, np.eye(4))
    eye = (distance * math.sin(angle), 0.7, -distance * math.cos(angle))
    return look_at(eye, CENTER, UP, like, name)


@pytest.fixture(scope="module")
def zero123(tiny_models: Path) -> novel_view.NovelViewModel:
    return models.load_novel_view(tiny_models)


@pytest.fixture(scope="module")
def cogvideox(tiny_models: Path) -> refine.VideoModel:
    return models.load_video(tiny_models)


def smoke_frames(n: int, height: int = 64, width: int = 48, channels: int = 1, seed: int = 0) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    return 0.8 - 0.5 * torch.rand(n, height, width, channels, generator=generator)


# ---------------------------------------------------------------- registry


def test_tiny_models_use_the_public_folder_layouts(tiny_models: Path) -> None:
    assert {p.name for p in (tiny_models / "zero123").iterdir() if p.is_dir()} == ZERO123_PARTS
    assert {p.name for p in (tiny_models / "cogvideox").iterdir() if p.is_dir()} == COGVIDEOX_PARTS
    assert (tiny_models / "zero123" / "cc_projection" / "diffusion_pytorch_model.safetensors").is_file()
    assert (tiny_models / "zero123" / "unet" / "diffusion_pytorch_model.safetensors").is_file()
    assert (tiny_models / "cogvideox" / "transformer" / "diffusion_pytorch_model.safetensors").is_file()
    entries = {e.name: e for e in models.inventory(tiny_models)}
    assert entries["zero123"].present and entries["cogvideox"].present
    assert models.skip_reason("zero123", tiny_models) is None


def test_the_models_folder_defaults_to_the_environment_variable(tiny_models: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The worker passes no models folder: $FLUIDNEXUS_MODELS (docker-compose mounts /models) decides."""
    monkeypatch.setenv("FLUIDNEXUS_MODELS", str(tiny_models))
    assert models.skip_reason("zero123") is None and models.skip_reason("cogvideox") is None
    monkeypatch.setenv("FLUIDNEXUS_MODELS", str(tiny_models / "absent"))
    assert models.skip_reason("zero123") == f"skipped: no zero123 weights in {tiny_models / 'absent'}"


def test_empty_models_folder_says_why_each_stage_is_skipped(tmp_path: Path) -> None:
    entries = {e.name: e for e in models.inventory(tmp_path)}
    assert not entries["zero123"].present and "unet/config.json" in entries["zero123"].missing
    assert models.skip_reason("cogvideox", tmp_path) == f"skipped: no cogvideox weights in {tmp_path}"
    with pytest.raises(models.MissingWeights, match="no zero123 weights"):
        models.load_novel_view(tmp_path)


def test_incomplete_checkpoint_names_the_missing_parts(tiny_models: Path, tmp_path: Path) -> None:
    shutil.copytree(tiny_models / "zero123", tmp_path / "zero123")
    (tmp_path / "zero123" / "cc_projection" / "diffusion_pytorch_model.safetensors").unlink()
    shutil.copytree(tiny_models / "cogvideox", tmp_path / "cogvideox")
    (tmp_path / "cogvideox" / models.PROMPT_FILE).unlink()
    reason = models.skip_reason("zero123", tmp_path)
    assert reason is not None and "cc_projection/ weights" in reason
    assert "prompt_embeds.safetensors (or text_encoder/ + tokenizer/)" in models.skip_reason("cogvideox", tmp_path)


def test_prompt_file_without_negative_embedding_is_refused(tiny_models: Path, tmp_path: Path) -> None:
    from safetensors.torch import load_file, save_file

    shutil.copytree(tiny_models / "cogvideox", tmp_path / "cogvideox")
    path = tmp_path / "cogvideox" / models.PROMPT_FILE
    save_file({"prompt_embeds": load_file(str(path))["prompt_embeds"]}, str(path))
    with pytest.raises(models.MissingWeights, match="negative_prompt_embeds"):
        models.load_video(tmp_path)


def test_text_encoder_folder_stands_in_for_the_prompt_file(tiny_models: Path, tmp_path: Path) -> None:
    """With text_encoder/ + tokenizer/ instead of the embedding file, T5 encodes the prompt once."""
    from tokenizers import Tokenizer, models as token_models, pre_tokenizers
    from transformers import PreTrainedTokenizerFast, T5Config, T5EncoderModel

    shutil.copytree(tiny_models / "cogvideox", tmp_path / "cogvideox")
    (tmp_path / "cogvideox" / models.PROMPT_FILE).unlink()
    words = ["<pad>", "<unk>", *sorted(set(models.DEFAULT_PROMPT.lower().replace(",", " ").replace(".", " ").split()))]
    core = Tokenizer(token_models.WordLevel({w: i for i, w in enumerate(words)}, unk_token="<unk>"))
    core.pre_tokenizer = pre_tokenizers.Whitespace()
    PreTrainedTokenizerFast(tokenizer_object=core, pad_token="<pad>", unk_token="<unk>").save_pretrained(tmp_path / "cogvideox" / "tokenizer")
    text_width = models.load_video(tiny_models).prompt_embeds.shape[-1]
    T5EncoderModel(T5Config(vocab_size=len(words), d_model=text_width, d_kv=4, d_ff=32, num_layers=1, num_heads=2)).save_pretrained(
        tmp_path / "cogvideox" / "text_encoder"
    )
    assert models.skip_reason("cogvideox", tmp_path) is None
    model = models.load_video(tmp_path)
    assert model.prompt_embeds.shape == model.negative_prompt_embeds.shape == (1, 8, text_width)
    assert not torch.equal(model.prompt_embeds, model.negative_prompt_embeds)


# ---------------------------------------------------------------- novel views


def test_relative_pose_of_known_camera_moves() -> None:
    source = camera_at(0.0, "source")
    assert np.allclose(novel_view.relative_pose(source, source, CENTER, UP), [0.0, 0.0, 1.0, 0.0], atol=1e-6)
    quarter = novel_view.relative_pose(source, camera_at(math.pi / 2, "quarter"), CENTER, UP)
    assert abs(quarter[0]) < 1e-6 and abs(abs(quarter[1]) - 1.0) < 1e-6 and abs(quarter[2]) < 1e-6
    farther = novel_view.relative_pose(source, camera_at(0.0, "far", distance=3.2), CENTER, UP)
    assert farther[3] > 0 and farther[0] > 0  # farther away at the same height: nearer the horizon, polar angle grows
    higher = look_at((0.0, 2.0, -1.0), CENTER, UP, source, "higher")
    assert novel_view.relative_pose(source, higher, CENTER, UP)[0] < 0  # polar angle shrinks going up


def test_square_padding_round_trip_is_exact_at_the_frame_size() -> None:
    frames = smoke_frames(2, height=64, width=48, channels=3)
    squares = novel_view.to_square(frames, 64)
    assert squares.shape == (2, 3, 64, 64) and squares.min() >= -1 and squares.max() <= 1
    back = novel_view.from_square((squares + 1) / 2, 64, 48, 3)
    assert torch.allclose(back, frames, atol=1e-6)
    # the padding takes the border colour, so a uniform frame stays uniform
    flat = novel_view.to_square(torch.full((1, 64, 48, 1), 0.9), 32)
    assert torch.allclose(flat, torch.full_like(flat, 0.8), atol=1e-5)


def test_novel_views_have_each_target_size_and_valid_pixels(zero123: novel_view.NovelViewModel) -> None:
    frames = smoke_frames(2)
    targets = [camera_at(1.0, "left"), camera_at(-1.5, "wide", width=64, height=40)]
    out = novel_view.generate_views(zero123, frames, camera_at(0.0, "in"), targets, CENTER, UP, novel_view.SamplingOptions(steps=3))
    assert set(out) == {"left", "wide"}
    assert out["left"].shape == (2, 64, 48, 1) and out["wide"].shape == (2, 40, 64, 1)
    for views in out.values():
        assert views.dtype == torch.float32 and torch.isfinite(views).all()
        assert views.min() >= 0 and views.max() <= 1 and views.std() > 0


def test_novel_views_are_deterministic_for_a_seed_and_independent_of_batching(zero123: novel_view.NovelViewModel) -> None:
    frames, source, targets = smoke_frames(3), camera_at(0.0, "in"), [camera_at(1.0, "a"), camera_at(2.0, "b")]

    def run(seed: int, batch_size: int) -> dict[str, torch.Tensor]:
        options = novel_view.SamplingOptions(steps=3, seed=seed, batch_size=batch_size)
        return novel_view.generate_views(zero123, frames, source, targets, CENTER, UP, options)

    first, again, batched, other = run(1, 2), run(1, 2), run(1, 6), run(2, 2)
    assert all(torch.equal(first[k], again[k]) for k in first)
    assert all(torch.allclose(first[k], batched[k], atol=1e-4) for k in first)
    assert not torch.allclose(first["a"], other["a"], atol=1e-3)


def test_novel_view_condition_changes_with_the_target_pose(zero123: novel_view.NovelViewModel) -> None:
    """Same input and noise, different target camera: the pose reaches the model."""
    frames, source = smoke_frames(1), camera_at(0.0, "in")
    options = novel_view.SamplingOptions(steps=3, seed=0)
    a = novel_view.generate_views(zero123, frames, source, [camera_at(0.5, "x")], CENTER, UP, options)["x"]
    b = novel_view.generate_views(zero123, frames, source, [camera_at(2.5, "x")], CENTER, UP, options)["x"]
    assert not torch.allclose(a, b, atol=1e-5)


def test_novel_view_batches_report_progress_and_can_be_cancelled(zero123: novel_view.NovelViewModel) -> None:
    calls: list[tuple[int, int]] = []

    def stop_after_first(done: int, total: int) -> None:
        calls.append((done, total))
        raise KeyboardInterrupt

    options = novel_view.SamplingOptions(steps=2, batch_size=2)
    with pytest.raises(KeyboardInterrupt):
        novel_view.generate_views(zero123, smoke_frames(3), camera_at(0.0, "in"), [camera_at(1.0, "a")], CENTER, UP, options, stop_after_first)
    assert calls == [(2, 3)]


def test_bad_sampling_options_are_refused() -> None:
    with pytest.raises(novel_view.NovelViewError, match="steps"):
        novel_view.SamplingOptions(steps=0)
    with pytest.raises(novel_view.NovelViewError, match="guidance_scale"):
        novel_view.SamplingOptions(guidance_scale=0.5)


# ---------------------------------------------------------------- refinement


def test_windows_cover_every_frame_and_blend_to_one() -> None:
    for n_frames, window, overlap in [(5, 9, 2), (9, 9, 2), (20, 9, 3), (100, 49, 8)]:
        starts = refine.window_starts(n_frames, window, overlap)
        covered = np.zeros(n_frames)
        for start in starts:
            weight = refine.blend_weights(window, overlap, start > 0, start + window < n_frames).numpy()
            count = min(window, n_frames - start)
            covered[start : start + count] += weight[:count]
        assert starts[0] == 0 and min(starts[-1] + window, n_frames) == n_frames
        assert covered.min() > 0, (n_frames, starts)
        assert all(b - a <= window - overlap for a, b in zip(starts, starts[1:]))
    with pytest.raises(refine.RefineError, match="overlap"):
        refine.window_starts(20, 9, 9)


def test_refined_video_keeps_shape_and_range_and_is_deterministic(cogvideox: refine.VideoModel) -> None:
    video = smoke_frames(20, channels=1)
    calls: list[tuple[int, int]] = []
    options = refine.RefineOptions(strength=0.5, steps=4, overlap=3, batch_size=2, seed=3)
    out = refine.refine_video(cogvideox, video, options, on_batch=lambda done, total: calls.append((done, total)))
    assert out.shape == video.shape and out.dtype == torch.float32
    assert torch.isfinite(out).all() and out.min() >= 0 and out.max() <= 1
    assert calls == [(2, 3), (3, 3)]  # 20 frames in windows of 9 overlapping by 3: 3 windows
    assert torch.equal(out, refine.refine_video(cogvideox, video, options))
    colour = refine.refine_video(cogvideox, smoke_frames(5, channels=3), refine.RefineOptions(steps=2))
    assert colour.shape == (5, 64, 48, 3)


def test_strength_sets_how_far_refinement_moves_the_video(cogvideox: refine.VideoModel) -> None:
    video = smoke_frames(9)
    gentle = refine.refine_video(cogvideox, video, refine.RefineOptions(strength=0.1, steps=10))
    strong = refine.refine_video(cogvideox, video, refine.RefineOptions(strength=1.0, steps=10))
    assert not torch.allclose(gentle, strong, atol=1e-3)


def test_bad_refine_options_are_refused(cogvideox: refine.VideoModel) -> None:
    with pytest.raises(refine.RefineError, match="strength"):
        refine.RefineOptions(strength=0.0)
    with pytest.raises(refine.RefineError, match="video"):
        refine.refine_video(cogvideox, torch.zeros(4, 8, 8))


def test_full_size_architectures_have_the_public_parameter_counts() -> None:
    """Built on the meta device (no memory): the bench's real-size models are Zero123-XL
    (SD 1.x UNet, 860M; CLIP ViT-L/14 vision tower, 304M) and CogVideoX-2b (1.69B)."""
    from fluidcore.generative import random_weights

    count = lambda module: sum(p.numel() for p in module.parameters()) / 1e6  # noqa: E731
    zero123 = random_weights.build_novel_view("full", device="meta")
    assert 855 < count(zero123.unet) < 865 and 300 < count(zero123.image_encoder) < 308
    assert (zero123.cc_projection.in_features, zero123.cc_projection.out_features) == (772, 768) and zero123.size == 256
    video = random_weights.build_video("full", device="meta")
    assert 1650 < count(video.transformer) < 1750 and video.size == (720, 480) and video.window == 49
    assert video.prompt_embeds.shape == (1, 226, 4096)

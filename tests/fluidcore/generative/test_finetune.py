"""LoRA fine-tuning of the generative priors on a synthetic multi-view scene, with tiny models
(fluidcore.generative.finetune, `fluidnexus finetune`, `fluidnexus models`)."""

from __future__ import annotations

import json
import random
import shutil
from pathlib import Path

import pytest
import torch
from typer.testing import CliRunner

from fluidcore import synth
from fluidcore.generative import finetune, lora, models
from fluidnexus.cli import app


@pytest.fixture(scope="module")
def captures(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A folder holding one synthetic scene (3 cameras, 4 frames) in the transforms.json layout."""
    root = tmp_path_factory.mktemp("captures")
    synth.write(synth.generate(synth.SynthSpec(frames=4, width=24, height=32, views=3)), root / "plume")
    return root


def adapter_weights(folder: Path) -> dict[str, torch.Tensor]:
    from safetensors.torch import load_file

    return load_file(str(folder / lora.WEIGHTS_FILE))


@pytest.mark.parametrize("kind", finetune.KINDS)
def test_a_lora_step_changes_only_adapter_weights(kind: str, tiny_models: Path, captures: Path) -> None:
    if kind == "novel-view":
        model, loss_of = models.load_novel_view(tiny_models), finetune.novel_view_loss
        module, side = model.unet, model.size
    else:
        model, loss_of = models.load_video(tiny_models), finetune.refine_loss
        module, side = model.transformer, max(model.size)
    scene = finetune.load_scene(captures / "plume", side)
    lora.add_new(module, rank=4)
    before = {k: v.clone() for k, v in module.state_dict().items()}
    optimizer = torch.optim.Adam([p for p in module.parameters() if p.requires_grad], lr=1e-2)
    for step in range(2):  # B starts at zero, so A only moves from the second step on
        loss = loss_of(model, scene, random.Random(step), torch.Generator().manual_seed(step))
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    changed = {k for k, v in module.state_dict().items() if not torch.equal(v, before[k])}
    assert changed and all(".lora_" in k for k in changed)
    assert any(".lora_A." in k for k in changed) and any(".lora_B." in k for k in changed)


def test_finetune_writes_adapter_log_and_plot_and_the_adapter_changes_the_model(tiny_models: Path, captures: Path, tmp_path: Path) -> None:
    out = finetune.run("novel-view", captures, tmp_path / "adapter", steps=3, models_root=tiny_models, learning_rate=1e-2, checkpoint_every=2)
    assert lora.is_adapter(out) and (out / finetune.CHECKPOINT).is_file()
    lines = finetune.read_losses(out / finetune.LOSS_LOG)
    assert [line["step"] for line in lines] == [1, 2, 3] and all(line["loss"] > 0 for line in lines)
    assert (out / finetune.LOSS_PLOT).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    models_dir = tmp_path / "models"
    shutil.copytree(tiny_models, models_dir)
    shutil.copytree(out, models_dir / "lora" / "zero123")
    assert models.entry("zero123", models_dir).adapter == models_dir / "lora" / "zero123"
    tuned, base = models.load_novel_view(models_dir), models.load_novel_view(models_dir, use_adapter=False)
    x = torch.randn(1, 8, 16, 16)
    context = torch.randn(1, 1, tuned.unet.config.cross_attention_dim)
    assert not torch.allclose(tuned.unet(x, 10, encoder_hidden_states=context).sample, base.unet(x, 10, encoder_hidden_states=context).sample)


def test_a_resumed_finetune_computes_what_an_uninterrupted_one_does(tiny_models: Path, captures: Path, tmp_path: Path) -> None:
    options = dict(models_root=tiny_models, learning_rate=1e-2, checkpoint_every=2, seed=5)
    straight = finetune.run("refine", captures, tmp_path / "straight", steps=4, **options)
    messages: list[str] = []
    finetune.run("refine", captures, tmp_path / "resumed", steps=2, **options)
    resumed = finetune.run("refine", captures, tmp_path / "resumed", steps=4, progress=messages.append, **options)
    assert messages[0].startswith("resuming at step 2")
    a, b = adapter_weights(straight), adapter_weights(resumed)
    assert a.keys() == b.keys() and all(torch.allclose(a[k], b[k], atol=1e-6) for k in a)
    losses = [[line["loss"] for line in finetune.read_losses(folder / finetune.LOSS_LOG)] for folder in (straight, resumed)]
    assert len(losses[1]) == 4 and losses[0] == pytest.approx(losses[1], rel=1e-5)
    with pytest.raises(finetune.FinetuneError, match="other settings"):
        finetune.run("refine", captures, tmp_path / "resumed", steps=6, **{**options, "seed": 6})


def test_finetune_refuses_data_without_scenes(tiny_models: Path, tmp_path: Path) -> None:
    with pytest.raises(finetune.FinetuneError, match="no transforms.json"):
        finetune.run("refine", tmp_path, tmp_path / "out", steps=1, models_root=tiny_models)
    result = CliRunner().invoke(app, ["finetune", "novel-view", "--data", str(tmp_path), "--out", str(tmp_path / "o"), "--models", str(tiny_models)])
    assert result.exit_code == 2 and "error: --data: no transforms.json" in result.output


def test_models_command_lists_what_each_model_enables(tiny_models: Path, tmp_path: Path) -> None:
    result = CliRunner().invoke(app, ["models", "--models", str(tiny_models), "--json"])
    assert result.exit_code == 0, result.output
    listed = {m["name"]: m for m in json.loads(result.output)["models"]}
    assert listed["zero123"]["present"] and listed["cogvideox"]["present"]
    assert any(stage.startswith("refine-futures") for stage in listed["cogvideox"]["stages"])
    empty = CliRunner().invoke(app, ["models", "--models", str(tmp_path)])
    assert empty.exit_code == 0
    assert "zero123    missing: unet/config.json" in empty.output and "would enable novel-view" in empty.output


def test_excluded_cameras_are_never_trained_on(tiny_models: Path, captures: Path, tmp_path: Path) -> None:
    scene = finetune.load_scene(captures / "plume", 32, exclude=["view_00"])
    assert sorted(scene.videos) == ["view_01", "view_02"]
    args = ["finetune", "refine", "--data", str(captures), "--out", str(tmp_path / "o"), "--models", str(tiny_models), "--steps", "1"]
    result = CliRunner().invoke(app, [*args, "--exclude", "view_00", "--exclude", "view_01"])
    assert result.exit_code == 2 and "has 1 camera(s) with a video; fine-tuning needs at least 2" in result.output

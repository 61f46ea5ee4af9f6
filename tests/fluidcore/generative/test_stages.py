"""The generative stages as jobs run them (fluidcore.generative.stages): run with tiny models,
skipped with their reason without weights."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from fluidcore.cameras import Camera, look_at
from fluidcore.generative import stages
from fluidcore.reconstruct.views import ViewTarget, generated_targets

CENTER = np.array([0.0, 0.4, 0.0])
UP = np.array([0.0, 1.0, 0.0])


def camera_at(angle: float, name: str, width: int = 24, height: int = 32) -> Camera:
    like = Camera("like", 30.0, 30.0, width / 2, height / 2, width, height, np.eye(4))
    return look_at((1.6 * math.sin(angle), 0.7, -1.6 * math.cos(angle)), CENTER, UP, like, name)


def input_view(frames: int = 3) -> ViewTarget:
    images = 0.9 - 0.4 * torch.rand(frames, 32, 24, 1, generator=torch.Generator().manual_seed(0))
    return ViewTarget(camera_at(0.0, "view_00"), images, torch.full((32, 24, 1), 0.9), torch.full((1,), 1.0 / 255.0))


def test_targets_are_the_other_cameras_at_the_working_size_else_turned_copies() -> None:
    source = camera_at(0.0, "view_00")
    cameras = {"view_00": camera_at(0.0, "view_00", 48, 64), "view_01": camera_at(1.0, "view_01", 96, 128), "view_02": camera_at(2.0, "view_02", 96, 128)}
    targets = stages.target_cameras(cameras, source, CENTER, UP, count=4)
    assert [c.name for c in targets] == ["view_01", "view_02"] and all((c.width, c.height) == (24, 32) for c in targets)
    turned = stages.target_cameras({"view_00": source}, source, CENTER, UP, count=3)
    assert [c.name for c in turned] == ["view_00~gen1", "view_00~gen2", "view_00~gen3"]
    assert all(np.isclose(np.linalg.norm(c.center() - CENTER), np.linalg.norm(source.center() - CENTER)) for c in turned)


def test_without_weights_both_steps_say_why_they_were_skipped(tmp_path: Path) -> None:
    source = input_view()
    frames, status = stages.generated_views(source.camera, source.frames, [camera_at(1.0, "b")], CENTER, UP, stages.GenerativeSettings(models_root=tmp_path))
    assert frames == {}
    assert status == {"novel_views": f"skipped: no zero123 weights in {tmp_path}", "view_refinement": "skipped: no generated views to refine"}
    video = {"view_00": input_view().frames}
    refined, line = stages.refine_frames(video, stages.GenerativeSettings(models_root=tmp_path))
    assert refined["view_00"] is video["view_00"] and line == f"skipped: no cogvideox weights in {tmp_path}"


def test_generated_views_are_weighted_below_the_input_and_refined(tiny_models: Path) -> None:
    source = input_view(frames=3)
    targets = [camera_at(1.5, "view_01"), camera_at(3.0, "view_02")]
    calls: list[tuple[str, int, int]] = []
    settings = stages.GenerativeSettings(models_root=tiny_models, novel_view_steps=2, refine_steps=2, novel_view_batch=4)
    frames, status = stages.generated_views(source.camera, source.frames, targets, CENTER, UP, settings, on_batch=lambda *a: calls.append(a))
    views = generated_targets(source, targets, frames, 0.5)
    assert [v.camera.name for v in views] == ["view_01", "view_02"] and {v.kind for v in views} == {"generated"}
    assert sum(v.weight for v in views) == pytest.approx(0.5) and all(v.weight < source.weight for v in views)
    for view in views:
        assert view.frames.shape == (3, 32, 24, 1) and torch.isfinite(view.frames).all()
        assert view.frames.min() >= 0 and view.frames.max() <= 1 and view.background.shape == (1,)
    assert status["novel_views"].startswith("generated 2 views x 3 frames from view_00 (2 DDIM steps, base weights")
    assert status["view_refinement"].startswith("refined 2 videos with cogvideox (strength 0.5, 1 of 2 steps")
    assert ("novel views", 4, 6) in calls and calls[-1] == ("refine views", 2, 2)


def test_cancelling_between_batches_stops_the_stage(tiny_models: Path) -> None:
    class Stop(Exception):
        pass

    def cancel(stage: str, done: int, total: int) -> None:
        raise Stop(stage)

    settings = stages.GenerativeSettings(models_root=tiny_models, novel_view_steps=1, novel_view_batch=1)
    with pytest.raises(Stop, match="novel views"):
        source = input_view()
        stages.generated_views(source.camera, source.frames, [camera_at(1.0, "b")], CENTER, UP, settings, on_batch=cancel)

"""The generative priors inside the jobs, with tiny models: a single-view reconstruction fits
generated views (never fed a held-out frame), a prediction is refined and reconstructed again,
and without weights each stage says in the manifest why it was skipped."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from fluidcore import artifacts, jobs, synth, video
from fluidcore.exports import EXPORTERS
from fluidcore.generative import models, stages
from fluidcore.generative.novel_view import to_square
from fluidcore.generative.refine import to_model_frames
from fluidcore.predict import job as predict_job
from fluidcore.spec.reconstruct import get
from fluidcore.reconstruct import job as reconstruct_job
from fluidcore.runs import Run

QUICK = get("preview").with_overrides(position_iterations=2, appearance_iterations=1, first_frame_factor=1, symmetry_views=2, long_side=32)
INPUT = "view_01"
HELD_OUT = ("view_00", "view_02")


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("scene")
    synth.write(synth.generate(synth.SynthSpec(frames=3, width=24, height=32, views=3)), folder)
    return folder


def settings(root: Path) -> stages.GenerativeSettings:
    return stages.GenerativeSettings(models_root=root, novel_view_steps=2, refine_steps=2, novel_view_batch=3)


class Recorder:
    """Forward pre-hooks on every image encoder of the loaded models: each image tensor a
    generative model receives is kept (in the model's own [-1, 1] pixel space)."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch) -> None:
        self.novel_view: list[torch.Tensor] = []  # (3, S, S) squares given to Zero123's VAE
        self.video: list[torch.Tensor] = []  # (3, h, w) frames given to CogVideoX's VAE
        load_novel_view, load_video = models.load_novel_view, models.load_video

        def novel_view(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
            model = load_novel_view(*args, **kwargs)
            model.vae.encoder.register_forward_pre_hook(lambda _m, a: self.novel_view.extend(a[0].detach().float()))
            model.image_encoder.register_forward_pre_hook(self._clip, with_kwargs=True)
            return model

        def video_model(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
            model = load_video(*args, **kwargs)
            model.pipeline.vae.encoder.register_forward_pre_hook(lambda _m, a: self.video.extend(a[0].detach().float().permute(0, 2, 1, 3, 4).flatten(0, 1)))
            return model

        monkeypatch.setattr(models, "load_novel_view", novel_view)
        monkeypatch.setattr(models, "load_video", video_model)
        self.clip_calls = 0

    def _clip(self, _module, _args, kwargs):  # noqa: ANN001, ANN202
        self.clip_calls += 1


def frames_of(scene: Path, name: str, size: tuple[int, int]) -> torch.Tensor:
    return torch.from_numpy(video.read_frames(scene / "videos" / f"{name}.mp4", size=size)).float() / 255.0


def nearest(images: list[torch.Tensor], references: torch.Tensor) -> float:
    """Smallest mean absolute difference between any recorded image and any reference."""
    return min(float((image - reference).abs().mean()) for image in images for reference in references)


def test_single_view_reconstruction_fits_generated_views_from_the_input_view_only(
    scene: Path, tiny_models: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    recorder = Recorder(monkeypatch)
    seen: list[tuple[float, str]] = []
    out = reconstruct_job.run_reconstruct(
        scene / "transforms.json", {INPUT: scene / "videos" / f"{INPUT}.mp4"}, tmp_path / "run", quality=QUICK,
        generative=settings(tiny_models), context=jobs.JobContext(progress=lambda fraction, stage: seen.append((fraction, stage))),
    )
    manifest = Run.open(out).manifest
    views = manifest["settings"]["views"]
    assert [v["camera"] for v in views] == [INPUT, *HELD_OUT]
    assert [v["kind"] for v in views] == ["input", "generated", "generated"]
    assert all(v["weight"] < views[0]["weight"] for v in views[1:]) and sum(v["weight"] for v in views[1:]) == pytest.approx(0.5)
    # the generated views placed the source (its depth along the input ray), each at its loss weight
    estimate = manifest["settings"]["source_estimate"]
    assert estimate["depth_cue"] == "generated views" and estimate["depth_range"] is not None
    assert estimate["generated"] == {v["camera"]: v["weight"] for v in views[1:]} and set(estimate["pixels"]) == {INPUT}
    assert manifest["novel_views"].startswith(f"generated 2 views x 3 frames from {INPUT}")
    assert manifest["view_refinement"].startswith("refined 2 videos with cogvideox (strength 0.5")
    assert {"novel views", "refine views", "reconstruct"} <= {stage for _, stage in seen}
    assert Run.open(out).frames() == [0, 1, 2]

    # the held-out guard: every image the novel-view model was given is an input-view frame,
    # and no image any model was given is a held-out camera's frame
    working = (24, 32)
    squares = lambda frames: to_square(frames, 32)  # noqa: E731 - the tiny model's size
    inputs = squares(frames_of(scene, INPUT, working))
    assert recorder.novel_view and recorder.clip_calls > 0 and recorder.video
    assert all(min(float((image - frame).abs().max()) for frame in inputs) < 1e-5 for image in recorder.novel_view)
    for name in HELD_OUT:
        held = frames_of(scene, name, working)
        assert nearest(recorder.novel_view, squares(held)) > 1e-3
        as_video_input = to_model_frames(held[None], 64, 48)[0] * 2.0 - 1.0
        assert nearest(recorder.video, as_video_input) > 1e-3


def test_without_weights_reconstruction_keeps_the_symmetry_prior_and_says_why(scene: Path, tmp_path: Path) -> None:
    out = reconstruct_job.run_reconstruct(
        scene / "transforms.json", {INPUT: scene / "videos" / f"{INPUT}.mp4"}, tmp_path / "run", quality=QUICK, frames=(0, 1),
        generative=stages.GenerativeSettings(models_root=tmp_path / "models"),
    )
    manifest = Run.open(out).manifest
    assert manifest["novel_views"] == f"skipped: no zero123 weights in {tmp_path / 'models'}"
    assert [v["kind"] for v in manifest["settings"]["views"]] == ["input", "symmetry", "symmetry"]


def test_cancelling_during_generation_raises_the_jobs_cancel(scene: Path, tiny_models: Path, tmp_path: Path) -> None:
    with pytest.raises(jobs.Cancelled, match="during novel views"):
        reconstruct_job.run_reconstruct(
            scene / "transforms.json", {INPUT: scene / "videos" / f"{INPUT}.mp4"}, tmp_path / "run", quality=QUICK,
            generative=settings(tiny_models), context=jobs.JobContext(should_cancel=lambda: True),
        )


def test_prediction_refines_its_future_and_reconstructs_on_it(scene: Path, tiny_models: Path, tmp_path: Path) -> None:
    parent = reconstruct_job.run_reconstruct(
        scene / "transforms.json", {INPUT: scene / "videos" / f"{INPUT}.mp4"}, tmp_path / "parent", quality=QUICK, frames=(0, 2),
        generative=stages.GenerativeSettings(models_root=tmp_path / "none"),
    )
    seen: list[str] = []
    out = predict_job.run_predict(parent, tmp_path / "pred", frames=3, generative=settings(tiny_models),
                                  context=jobs.JobContext(progress=lambda fraction, stage: seen.append(stage)))
    run = Run.open(out)
    assert run.frames() == [2, 3, 4]
    assert run.manifest["refinement"].startswith("refined 1 videos with cogvideox (strength 0.75, 1 of 2 steps")
    assert run.manifest["refinement"].endswith("reconstructed on them from frame 2 in refined/")
    refined = Run.open(out / "refined")
    assert refined.kind == "reconstruct" and refined.frames() == [2, 3, 4] and refined.manifest["input_views"] == [INPUT]
    assert [v["kind"] for v in refined.manifest["settings"]["views"]] == ["input"]
    np.testing.assert_array_equal(refined.read_frame(2).positions, run.read_frame(2).positions)  # starts from the prediction
    assert not np.array_equal(refined.read_frame(4).gaussians["means"], run.read_frame(4).gaussians["means"])
    assert {"predict", "refine futures", "reconstruct refined"} <= set(seen)
    files = {f.name for f in artifacts.render_artifacts(out, tmp_path / "videos")}
    assert {f"refined_{name}.mp4" for name in (INPUT, *HELD_OUT)} <= files and "orbit.mp4" in files
    assert video.probe(tmp_path / "videos" / f"refined_{INPUT}.mp4").n_frames == 3


def test_only_predictions_are_refined(scene: Path, tiny_models: Path, tmp_path: Path) -> None:
    parent = reconstruct_job.run_reconstruct(
        scene / "transforms.json", {INPUT: scene / "videos" / f"{INPUT}.mp4"}, tmp_path / "parent", quality=QUICK, frames=(0, 2),
        generative=stages.GenerativeSettings(models_root=tmp_path / "none"),
    )
    run = Run.open(predict_job.run_resimulate(parent, tmp_path / "resim"))
    assert run.manifest["refinement"] == predict_job.NOT_REFINED and not (tmp_path / "resim" / "refined").exists()


def test_the_worker_runs_the_generative_stages_from_the_models_variable(
    scene: Path, tiny_models: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The worker's reconstruct runner passes no models folder: $FLUIDNEXUS_MODELS decides, and the
    stages show up in the job's progress (default sampling settings, preview quality)."""
    from service.job_types import JobType
    from worker import runners

    monkeypatch.setenv("FLUIDNEXUS_MODELS", str(tiny_models))
    seen: list[str] = []
    inputs = runners.RunInputs(
        job_id="job", job_type=JobType.RECONSTRUCT, params={"frames": [0, 2]}, run_dir=tmp_path / "run",
        render_dir=tmp_path / "render", device="cpu", progress=lambda fraction, stage: seen.append(stage),
        should_cancel=lambda: False, cameras_path=scene / "transforms.json", videos={INPUT: scene / "videos" / f"{INPUT}.mp4"},
    )
    files = runners.reconstruct(inputs)
    assert {"novel views", "refine views", "reconstruct", "render"} <= set(seen)
    assert seen.index("novel views") < seen.index("refine views") < seen.index("reconstruct") < seen.index("render")
    assert [v["kind"] for v in Run.open(tmp_path / "run").manifest["settings"]["views"]] == ["input", "generated", "generated"]
    videos = sorted(f.name for f in files if f.suffix == ".mp4")
    assert videos == [f"{INPUT}.mp4"]  # the input view; the generated views' cameras and the orbit on request
    frames = len(Run.open(tmp_path / "run").frames())  # the last frame in every export format, every frame of a sequence
    assert len(files) - len(videos) == sum(frames if e.every_frame else 1 for e in EXPORTERS.values())


def test_a_resumed_reconstruction_reads_its_generated_views_back(
    scene: Path, tiny_models: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Stopped after frame 0 and started again, the job samples nothing new and ends where an
    uninterrupted run ends."""
    args = (scene / "transforms.json", {INPUT: scene / "videos" / f"{INPUT}.mp4"})
    straight = reconstruct_job.run_reconstruct(*args, tmp_path / "straight", quality=QUICK, generative=settings(tiny_models))
    stopped = tmp_path / "stopped"
    done_frames = lambda: len(Run.open(stopped).frames()) if (stopped / "manifest.json").exists() else 0  # noqa: E731
    with pytest.raises(jobs.Cancelled):
        reconstruct_job.run_reconstruct(*args, stopped, quality=QUICK, generative=settings(tiny_models),
                                        context=jobs.JobContext(should_cancel=lambda: done_frames() >= 1))
    assert Run.open(stopped).frames() == [0]
    assert sorted(p.name for p in (stopped / stages.GENERATED_DIR).iterdir()) == sorted(["views.json", *(f"{n}.npz" for n in HELD_OUT)])

    def no_sampling(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        raise AssertionError("a resumed job loaded a generative model")

    monkeypatch.setattr(models, "load_novel_view", no_sampling)
    monkeypatch.setattr(models, "load_video", no_sampling)
    reconstruct_job.run_reconstruct(*args, stopped, quality=QUICK, generative=settings(tiny_models))
    resumed = Run.open(stopped)
    assert resumed.frames() == [0, 1, 2] and resumed.manifest["novel_views"].endswith("(read back from generated/)")
    for name in ("positions", "velocities"):
        np.testing.assert_array_equal(getattr(resumed.read_frame(2), name), getattr(Run.open(straight).read_frame(2), name))

"""fluidcore.reconstruct.job.run_reconstruct and fluidcore.artifacts as the worker calls them:
progress, cancel then resume, only the named videos read, and the rendered artifacts of a run."""

from __future__ import annotations

import json

import pytest

from fluidcore import artifacts, jobs, synth, video
from fluidcore.reconstruct import job as reconstruct_job
from fluidcore.reconstruct.pipeline import IDENTIFY_STAGE, PREPARE_SHARE
from fluidcore.spec.reconstruct import get
from fluidcore.runs import Run

QUICK = get("preview").with_overrides(position_iterations=3, appearance_iterations=2, first_frame_factor=1)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    folder = tmp_path_factory.mktemp("scene")
    synth.write(synth.generate(synth.SynthSpec(frames=3, width=32, height=48, views=3)), folder)
    # Another view's file_path now points at garbage: reading it would fail the job.
    (folder / "videos" / "view_02.mp4").write_bytes(b"not a video")
    return folder


def test_cancel_keeps_finished_frames_and_a_rerun_resumes(scene, tmp_path):
    videos = {"view_01": scene / "videos" / "view_01.mp4"}
    # a cancel while the physics is identified is honoured there, before any frame
    with pytest.raises(jobs.Cancelled, match="cancelled during prepare: identifying the physics"):
        reconstruct_job.run_reconstruct(scene / "transforms.json", videos, tmp_path / "early", quality=QUICK,
                                         context=jobs.JobContext(should_cancel=lambda: True))
    assert not (tmp_path / "early").exists() or Run.open(tmp_path / "early").frames() == []
    seen: list[tuple[float, str]] = []
    with pytest.raises(jobs.Cancelled, match="resumes from frame 1"):
        reconstruct_job.run_reconstruct(
            scene / "transforms.json",
            videos,
            tmp_path / "run",
            quality=QUICK,
            context=jobs.JobContext(progress=lambda fraction, stage: seen.append((fraction, stage)),
                                    should_cancel=lambda: any(stage == "reconstruct" for _, stage in seen)),  # after frame 0
        )
    assert Run.open(tmp_path / "run").frames() == [0]
    # issue 48: the prepare stage moves (each of the identification's trial simulations), then the frames fill the rest
    identifying = [fraction for fraction, stage in seen if stage == IDENTIFY_STAGE]
    assert seen[0] == (0.0, "prepare") and len(identifying) > 3
    assert identifying == sorted(identifying) and 0.0 < identifying[0] and identifying[-1] <= PREPARE_SHARE
    assert seen[-1] == (pytest.approx(PREPARE_SHARE + (1 - PREPARE_SHARE) / 3), "reconstruct")
    assert [fraction for fraction, _ in seen] == sorted(fraction for fraction, _ in seen)
    reconstruct_job.run_reconstruct(
        scene / "transforms.json", {"view_01": scene / "videos" / "view_01.mp4"}, tmp_path / "run", quality=QUICK
    )
    run = Run.open(tmp_path / "run")
    assert run.frames() == [0, 1, 2] and run.manifest["complete"]
    # each frame records its fit with its yardstick (fluidcore.reconstruct.yardstick), which the health report reads
    for frame in run.manifest["frames"]:
        record = frame["losses"]
        assert {"input_psnr", "background_psnr", "explained", "smoke_up", "smoke_across"} <= set(record), record
        assert record["explained"] <= 1.0 and record["input_psnr"] > record["background_psnr"]
    assert json.loads((tmp_path / "run" / "manifest.json").read_text())["input_views"] == ["view_01"]


def test_render_artifacts_one_video_per_camera_and_an_orbit(scene, tmp_path):
    reconstruct_job.run_reconstruct(
        scene / "transforms.json", {"view_01": scene / "videos" / "view_01.mp4"}, tmp_path / "run",
        quality=QUICK, frames=(0, 2),
    )
    files = artifacts.render_artifacts(tmp_path / "run", tmp_path / "out")
    assert sorted(f.name for f in files) == ["orbit.mp4", "view_00.mp4", "view_01.mp4", "view_02.mp4"]
    assert video.probe(tmp_path / "out" / "view_00.mp4").n_frames == 2
    assert video.probe(tmp_path / "out" / "orbit.mp4").n_frames == 2  # one turn as long as the run: players stay in step


def test_bad_requests_are_refused_before_any_work(scene, tmp_path):
    with pytest.raises(jobs.JobInputError, match="frames"):
        reconstruct_job.run_reconstruct(
            scene / "transforms.json", {"view_01": scene / "videos" / "view_01.mp4"}, tmp_path / "a", frames=(0, 99)
        )
    with pytest.raises(jobs.JobInputError, match="videos"):
        reconstruct_job.run_reconstruct(scene / "transforms.json", {}, tmp_path / "b")
    with pytest.raises(jobs.JobInputError, match="START:END"):
        jobs.parse_frames("5")
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


@pytest.mark.parametrize("fps", [24.0, 60.0])
def test_the_videos_frame_rate_is_the_runs_and_a_camera_file_that_disagrees_is_reported(scene, tmp_path, fps):
    """The synth's camera file says 30 fps; its view re-encoded at 24 or 60 is read at that rate,
    the run records both, and its health report warns."""
    from fluidcore.health import report

    frames = video.read_frames(scene / "videos" / "view_01.mp4", 0, 3)
    clip = video.write_mp4(tmp_path / "view_01.mp4", frames, fps=fps)
    run = Run.open(reconstruct_job.run_reconstruct(scene / "transforms.json", {"view_01": clip}, tmp_path / "run", quality=QUICK))
    assert run.fps == pytest.approx(fps, rel=1e-3) and run.settings.capture.declared_fps == 30.0
    assert run.settings.capture.up_axis == "+y" and run.settings.capture.up_found == "cameras"
    checks = {check["name"]: check for check in report(run, audience="cli")["checks"]}
    assert checks["frame rate"]["level"] == "warning"
    assert f"play at {fps:g} fps but the camera file says 30 fps" in checks["frame rate"]["message"]
    assert checks["world up"]["level"] == "ok"


def test_videos_of_one_scene_share_a_frame_rate(scene, tmp_path):
    frames = video.read_frames(scene / "videos" / "view_01.mp4", 0, 3)
    videos = {"view_00": scene / "videos" / "view_00.mp4", "view_01": video.write_mp4(tmp_path / "view_01.mp4", frames, fps=25.0)}
    with pytest.raises(jobs.JobInputError, match=r"same frame rate \(view_00.mp4: 30, view_01.mp4: 25\)"):
        reconstruct_job.run_reconstruct(scene / "transforms.json", videos, tmp_path / "run", quality=QUICK)
    assert not (tmp_path / "run").exists()

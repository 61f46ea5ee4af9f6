"""`fluidnexus bench render`: the CLI contract (one JSON object with the timing fields), not speed."""

from __future__ import annotations

import json

import pytest
from typer.testing import CliRunner

from fluidnexus.cli import app


@pytest.mark.parametrize("depth", [[], ["--depth"]])
def test_bench_render_json_reports_one_configuration(depth: list[str]) -> None:
    result = CliRunner().invoke(
        app,
        ["bench", "render", "--gaussians", "300", "--size", "48x64", "--channels", "1", "--repeats", "1", "--threads", "1", "--json", *depth],
    )
    assert result.exit_code == 0, result.output
    report = json.loads(result.stdout)
    assert report["ms_forward_backward"] > 0 and report["ms_composite"] > 0
    assert (report["gaussians"], report["size"], report["channels"], report["threads"]) == (300, "48x64", 1, 1)
    assert report["depth"] is bool(depth)
    assert report["coverage"] > 0.05  # the plume is in view
    assert len(report["rows"]) == 1


def test_bench_render_rejects_bad_choices() -> None:
    for args in (["--channels", "2"], ["--backend", "opengl"], ["--size", "48by64"]):
        result = CliRunner().invoke(app, ["bench", "render", *args, "--gaussians", "10"])
        assert result.exit_code == 2, args


def test_bench_whatif_render_times_a_what_if_and_a_video_on_request(tmp_path) -> None:  # noqa: ANN001
    from tests.support.predict_scenes import plume_run

    parent = plume_run(tmp_path / "parent", frames=3, warmup=10)
    result = CliRunner().invoke(
        app, ["bench", "whatif_render", "--run", str(parent), "--frames", "2", "--repeats", "1", "--threads", "1", "--json"]
    )
    assert result.exit_code == 0, result.output
    report = json.loads(result.stdout)
    assert report["simulate_s"] > 0 and report["render_s"] >= 0 and 0 <= report["render_share"] < 1
    assert report["videos"] == report["video_frames"] == 0  # a what-if renders its videos on request
    assert report["orbit_cpu_s"] > 0 and report["input_view_cpu_s"] > 0  # ... which the functions time
    stages = report["rows"][0]["job_stages"]  # the same what-if as a job: API, worker executor, stage seconds
    assert {"interact", "render", "export", "publish"} <= set(stages) and 0 <= report["job_render_share"] < 1
    assert report["job_s"] >= sum(stages.values()) - 0.1 and report["orbit_job_render_s"] > 0
    assert report["first_request_s"] > 0 and report["second_request_s"] > 0  # the second one served from storage
    from fluidcore.runs import Run

    reconstruction = report["reconstruction"]  # the parent's own videos: all of them, and what it renders before it ends
    assert reconstruction["videos_eager"] == Run.open(parent).input_views and "orbit" in reconstruction["videos_all"]
    assert len(report["rows"]) == 1

"""`fluidnexus bench whatif_render` (= `python bench/whatif_render.py`): where a what-if job's
time goes, simulating against rendering its published videos, and what a video rendered on
request costs.

Two measurements per repeat, on fresh folders, `--repeats` times (medians):

- **functions**: what the worker's interact runner calls: `run_interact` on a reconstruction's
  run folder, then `fluidcore.artifacts.render_artifacts` of the videos a finished job renders
  before it ends (`eager_videos`) at the size the worker asks for (`fit_long_side`); then, as a
  render job would, the orbit on its own. Wall seconds, and CPU seconds of the process (which
  another user's load on a shared machine changes far less). `render_share` is the rendering's
  part of simulating and rendering together (`render_cpu_share` in CPU time).
- **job**: the same what-if through the service, in this process: the API (SQLite, local
  storage) queues it, the worker's `JobExecutor` runs it with fluidcore's runners (the parent run
  fetched from storage, checkpoints, exports, publication), and the job's own stage seconds say
  where its wall time went (`job_render_share`: the `render` stage over the job's run seconds).
  Then the orbit is asked for at `POST /v1/jobs/{id}/videos/orbit`: the first answer queues a
  render job, which the executor runs; the second is served from storage.

Issue 24 asks for rendering to take at most a third of a what-if's wall time at preview quality
on the 2-core machine. On code from before on-request rendering (no `eager_videos`: the job
rendered its input views, the orbit and the side-by-side) the script measures what the job
rendered then and skips the on-request figures; docs/bench_render.md says which commit each row
ran on. `--json` prints one JSON object.
"""

from __future__ import annotations

import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import typer

import fluidcore  # first, before torch: sets OpenMP's passive wait policy (see fluidcore/__init__.py)
import fluidcore.artifacts
from fluidnexus.reporting import echo_json

DEFAULT_WIND = '{"direction": [1, 0, 0], "strength": 0.5}'
KEYS = (  # medians
    "simulate_s", "render_s", "render_share", "simulate_cpu_s", "render_cpu_s", "render_cpu_share",
    "orbit_s", "orbit_cpu_s", "input_view_s", "input_view_cpu_s", "job_s", "job_render_s", "job_render_share", "job_export_s",
    "first_request_s", "orbit_job_s", "orbit_job_render_s", "second_request_s", "second_request_cpu_s",
)


def clocks() -> tuple[float, float]:
    """(wall, CPU of this process) seconds."""
    return time.perf_counter(), time.process_time()


def since(start: tuple[float, float]) -> tuple[float, float]:
    now = clocks()
    return now[0] - start[0], now[1] - start[1]


def measure(parent: Path, frames: int, wind: str, folder: Path) -> dict[str, Any]:
    """One what-if through the functions the worker calls: seconds simulating, rendering what a
    finished job renders, and rendering the orbit on request."""
    from fluidcore import artifacts
    from fluidcore.spec.controls import parse_interaction
    from fluidcore.predict import run_interact
    from fluidcore.runs import Run
    from fluidcore.video import probe

    params = parse_interaction(json.loads(wind), None)
    start = clocks()
    run_dir = run_interact(parent, folder / "run", params, frames=frames)
    simulate_s, simulate_cpu_s = since(start)
    long_side = artifacts.fit_long_side(run_dir)
    start = clocks()
    if hasattr(artifacts, "eager_videos"):
        files = artifacts.render_artifacts(run_dir, folder / "videos", artifacts.eager_videos(Run.open(run_dir)), long_side=long_side)
    else:  # before on-request rendering: everything the job published
        files = artifacts.render_artifacts(run_dir, folder / "videos", long_side=long_side)
    render_s, render_cpu_s = since(start)
    infos = [probe(f) for f in files]
    row = {
        "simulate_s": simulate_s, "render_s": render_s, "render_share": render_s / (simulate_s + render_s),
        "simulate_cpu_s": simulate_cpu_s, "render_cpu_s": render_cpu_s,
        "render_cpu_share": render_cpu_s / (simulate_cpu_s + render_cpu_s),
        "videos": len(files), "video_frames": sum(i.n_frames for i in infos),
        "pixels_per_frame": max((i.width * i.height for i in infos), default=0),
    }
    if hasattr(artifacts, "eager_videos"):  # on request: the orbit, and the input view (what eager rendering would cost)
        for name, video in (("orbit", "orbit"), ("input_view", Run.open(run_dir).input_views[0])):
            start = clocks()
            artifacts.render_artifacts(run_dir, folder / name, [video], long_side=long_side)
            row[f"{name}_s"], row[f"{name}_cpu_s"] = since(start)
    return row


def measure_reconstruction(run: Path, folder: Path) -> dict[str, Any]:
    """The parent reconstruction's own videos: every one (what a reconstruct job rendered before
    on-request rendering) against those it renders before it ends now, CPU seconds, beside the
    seconds its frames took (the manifest's frame log, wall)."""
    from fluidcore import artifacts
    from fluidcore.runs import Run

    record = Run.open(run)
    long_side = artifacts.fit_long_side(run)
    report = {"reconstruct_frames_s": sum(entry["seconds"] for entry in record.manifest["frames"])}
    for key, names in (("all", artifacts.video_names(record)), ("eager", artifacts.eager_videos(record))):
        start = clocks()
        artifacts.render_artifacts(run, folder / key, names, long_side=long_side)
        report[f"render_{key}_s"], report[f"render_{key}_cpu_s"] = since(start)
        report[f"videos_{key}"] = names
    return report


class RecordingQueue:
    """The job queue of the in-process API: records what it sends; the executor is run by hand."""

    owner_share = 1_000_000  # every job is sent: the benchmark runs them by hand, one at a time

    def __init__(self) -> None:
        self.sent: list[str] = []

    def enqueue(self, job_id: str, job_type: str) -> str:
        self.sent.append(job_id)
        return f"bench-{len(self.sent)}"

    def ping(self) -> None:
        return None


def measure_job(parent: Path, frames: int, wind: str, folder: Path) -> dict[str, Any]:
    """One what-if as a job of the service (API and worker executor in this process), then the
    orbit asked for twice."""
    from fastapi.testclient import TestClient

    from api.app import create_app
    from api.auth import create_key
    from fluidcore import artifacts
    from service.database import session_scope
    from service.models import Job, JobState
    from service.settings import Settings
    from service.storage import run_prefix
    from worker.execution import JobExecutor
    from worker.runners import FLUIDCORE_RUNNERS
    from worker.sync import FolderMirror

    settings = Settings(data_dir=folder / "data", database_url=f"sqlite:///{folder / 'service.sqlite3'}")
    with TestClient(create_app(settings, queue=RecordingQueue())) as client:
        sessions, storage = client.app.state.sessionmaker, client.app.state.storage
        with session_scope(sessions) as session:
            auth = {"Authorization": f"Bearer {create_key(session, 'bench')}"}
            reconstruction = Job(owner="bench", type="reconstruct", state=JobState.SUCCEEDED, params={})
            session.add(reconstruction)
            session.flush()
            parent_id = reconstruction.id
        FolderMirror(storage, parent, run_prefix(parent_id)).push()
        body = {"type": "interact", "parent_job_id": parent_id, "params": {"frames": frames, "wind": json.loads(wind)}}
        job = client.post("/v1/jobs", json=body, headers=auth).json()
        executor = JobExecutor(settings, sessions, storage, dict(FLUIDCORE_RUNNERS))
        assert executor.run(job["id"]) == "succeeded", client.get(f"/v1/jobs/{job['id']}", headers=auth).json()["error"]
        job = client.get(f"/v1/jobs/{job['id']}", headers=auth).json()
        stages = job["timings"]["stages"]
        row: dict[str, Any] = {
            "job_s": job["timings"]["run_seconds"], "job_stages": stages, "job_render_s": stages.get("render", 0.0),
            "job_export_s": stages.get("export"),  # absent before on-request rendering: exports ran in the render stage
        }
        row["job_render_share"] = row["job_render_s"] / row["job_s"]
        if not hasattr(artifacts, "eager_videos"):
            return row  # before on-request rendering
        path = f"/v1/jobs/{job['id']}/videos/orbit"
        start = clocks()
        first = client.post(path, headers=auth)
        row["first_request_s"] = since(start)[0]
        render = first.json()["render_job"]["id"]
        start = clocks()
        assert first.status_code == 202 and executor.run(render) == "succeeded"
        row["orbit_job_s"] = since(start)[0]
        row["orbit_job_stages"] = client.get(f"/v1/jobs/{render}", headers=auth).json()["timings"]["stages"]
        row["orbit_job_render_s"] = row["orbit_job_stages"]["render"]
        start = clocks()
        second = client.post(path, headers=auth)
        row["second_request_s"], row["second_request_cpu_s"] = since(start)
        assert second.status_code == 200 and second.json()["render_job"] is None  # served from storage
        client.app.state.engine.dispose()
    return row


def command(
    run: Path = typer.Option(..., "--run", exists=True, file_okay=False, help="A reconstruction's run folder to branch."),
    frames: int = typer.Option(30, "--frames", min=1, max=1000, help="New frames of the what-if."),
    wind: str = typer.Option(DEFAULT_WIND, "--wind", help="The what-if's wind (JSON, as `fluidnexus interact --wind`)."),
    repeats: int = typer.Option(3, "--repeats", min=1, max=20, help="What-ifs to time (medians)."),
    threads: int | None = typer.Option(None, "--threads", min=1, help="CPU threads (default: all cores)."),
    json_output: bool = typer.Option(False, "--json", help="Print one JSON object instead of the table."),
) -> None:
    import torch

    if threads is not None:
        torch.set_num_threads(threads)
    rows = []
    for i in range(repeats):
        with tempfile.TemporaryDirectory(prefix="fluidnexus-bench-whatif-") as tmp:
            row = measure(run, frames, wind, Path(tmp) / "functions")
            row.update(measure_job(run.resolve(), frames, wind, Path(tmp) / "job"))
            rows.append(row)
        print(f"what-if {i + 1}/{repeats}: {row['simulate_s']:.1f} s simulate, {row['render_s']:.1f} s render; "
              f"job {row['job_s']:.1f} s, {row['job_render_s']:.1f} s of it rendering", file=sys.stderr)
    reconstruction = None
    if hasattr(fluidcore.artifacts, "eager_videos"):
        with tempfile.TemporaryDirectory(prefix="fluidnexus-bench-reconstruction-") as tmp:
            reconstruction = measure_reconstruction(run, Path(tmp))
    report: dict[str, Any] = {
        "run": str(run), "frames": frames, "wind": json.loads(wind), "repeats": repeats,
        "threads": torch.get_num_threads(), "cpu_count": os.cpu_count(), "load_average": [round(x, 2) for x in os.getloadavg()],
        **{key: statistics.median(r[key] for r in rows) for key in KEYS if all(r.get(key) is not None for r in rows)},
        **{key: rows[0][key] for key in ("videos", "video_frames", "pixels_per_frame")},
        "rows": rows, "reconstruction": reconstruction,
    }
    if json_output:
        echo_json(report)
        return
    typer.echo(f"threads {report['threads']} of {report['cpu_count']} cores, load average {report['load_average']}")
    typer.echo(table(report))


def table(report: dict[str, Any]) -> str:
    """The medians as markdown rows under their headers: the functions, then the job."""
    def cell(key: str, digits: int = 2) -> str:
        return "-" if report.get(key) is None else f"{report[key]:.{digits}f}"

    functions = ["simulate_s", "render_s", "render_share", "simulate_cpu_s", "render_cpu_s", "render_cpu_share",
                 "input_view_cpu_s", "orbit_cpu_s"]
    job = ["job_s", "job_render_s", "job_render_share", "job_export_s", "first_request_s", "orbit_job_s", "second_request_s"]
    lines = []
    for keys in (functions, job):
        lines += ["| " + " | ".join(k.replace("_", " ") for k in keys) + " |", "|" + "---:|" * len(keys),
                  "| " + " | ".join(cell(k, 3 if k == "second_request_s" else 2) for k in keys) + " |", ""]
    return "\n".join(lines)


if __name__ == "__main__":
    from bench.registry import run_script

    run_script("whatif_render", command)

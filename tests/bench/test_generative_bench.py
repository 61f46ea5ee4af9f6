"""`fluidnexus bench generative --json` with tiny random models, and with a models folder."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def run_bench(*args: str) -> dict:
    done = subprocess.run([sys.executable, str(ROOT / "bench" / "generative.py"), *args, "--steps", "2", "--views", "2",
                           "--frames", "1", "--threads", "1", "--json"], capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)  # fails if anything else reached stdout


def test_bench_times_both_pipelines_on_the_models_folder(tiny_models: Path) -> None:
    result = run_bench("--models", str(tiny_models), "--strength", "0.5")
    assert result["models"] == str(tiny_models) and result["dtype"] == "float32" and result["threads"] == 1
    rows = {row["pipeline"]: row for row in result["rows"]}
    assert rows["novel_view"]["frames_out"] == 2 and rows["novel_view"]["size"] == "32x32"
    assert rows["refine"]["frames_out"] == 9 and rows["refine"]["steps"] == 1 and rows["refine"]["size"] == "64x48"
    for row in rows.values():
        assert row["seconds"] > 0 and row["seconds_per_frame"] == pytest.approx(row["seconds"] / row["frames_out"], abs=1e-3)
        assert row["peak_memory_mb"] >= 0


def test_bench_refuses_an_unknown_size() -> None:
    done = subprocess.run([sys.executable, str(ROOT / "bench" / "generative.py"), "--size", "huge"], capture_output=True, text=True,
                          cwd=ROOT, timeout=120)
    assert done.returncode == 2 and "error: --size must be tiny or full" in done.stderr

"""`fluidnexus bench physics --json`: one JSON object on stdout with the fields the issue names."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def test_single_run_prints_exactly_one_json_object() -> None:
    args = ["--particles", "800", "--iterations", "2", "--steps", "2", "--warmup", "1", "--threads", "1", "--json"]
    done = subprocess.run([sys.executable, str(ROOT / "bench" / "physics.py"), *args], capture_output=True, text=True,
                          cwd=ROOT, timeout=120)
    assert done.returncode == 0, done.stderr
    result = json.loads(done.stdout)  # fails if anything else reached stdout
    assert result["particles"] == 800 and result["iterations"] == 2 and result["iterations_used"] == 2.0
    assert result["steps_per_s"] > 0 and result["machine"]["threads"] == 1
    assert 0.0 <= result["mean_density_error"] <= result["max_density_error"]


def test_tolerance_run_reports_iterations_used() -> None:
    args = ["--particles", "800", "--tolerance", "0.05", "--scene", "violent", "--steps", "1", "--warmup", "0",
            "--threads", "1", "--json"]
    done = subprocess.run([sys.executable, str(ROOT / "bench" / "physics.py"), *args], capture_output=True, text=True,
                          cwd=ROOT, timeout=120)
    assert done.returncode == 0, done.stderr
    result = json.loads(done.stdout)
    assert result["tolerance"] == 0.05 and result["iterations"] is None
    assert 1 <= result["iterations_used"] <= 50


def test_air_rows_time_each_grid_size_against_the_pbf_step(tmp_path: Path) -> None:
    args = ["--air", "--particles", "800", "--steps", "1", "--warmup", "1", "--threads", "1", "--json", "--out", str(tmp_path)]
    done = subprocess.run([sys.executable, str(ROOT / "bench" / "physics.py"), *args], capture_output=True, text=True,
                          cwd=ROOT, timeout=300)
    assert done.returncode == 0, done.stderr
    rows = json.loads(done.stdout)["air"]
    assert json.loads((tmp_path / "physics_air.json").read_text())["air"] == rows
    assert [(r["scene"], r["cells"]) for r in rows] == [(s, c) for s in ("calm", "violent") for c in (32, 48, 64)]
    for r in rows:
        assert max(r["grid"]) == r["cells"] and r["particles"] == 800
        assert r["ratio"] == pytest.approx(r["air_cpu_s_per_step"] / r["pbf_cpu_s_per_step"])
        assert r["pressure_iterations"] >= 1 and r["max_divergence_ratio"] <= 1e-4

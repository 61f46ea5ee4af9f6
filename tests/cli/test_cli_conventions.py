"""Command-line conventions: --version, --json (one JSON object on stdout, logs on stderr),
--device checked before any work, and one data folder for `keys` and `serve` wherever they run."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from typer.testing import CliRunner

import fluidcore
from fluidnexus.cli import app

runner = CliRunner()
CLI = [str(Path(sys.executable).with_name("fluidnexus"))]


def _json(args: list[str]) -> dict:
    result = runner.invoke(app, [*args, "--json"])
    assert result.exit_code == 0, result.output
    return json.loads(result.stdout)  # stdout holds the object and nothing else


def test_version() -> None:
    result = subprocess.run([*CLI, "--version"], capture_output=True, text=True, check=True)
    assert result.stdout == f"fluidnexus {fluidcore.__version__}\n"


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("scene")
    result = runner.invoke(app, ["synth", "--out", str(folder), "--frames", "3", "--width", "32", "--height", "48", "--views", "2"])
    assert result.exit_code == 0, result.output
    return folder


def test_json_on_every_run_command(scene: Path, tmp_path: Path) -> None:
    run = tmp_path / "rec"
    report = _json(["reconstruct", "--cameras", str(scene / "transforms.json"), "--video", f"view_00={scene / 'videos' / 'view_00.mp4'}",
                    "--frames", "0:2", "--out", str(run), "--threads", "1"])
    health = report.pop("health")
    assert report == {"run": str(run), "kind": "reconstruct", "frames": [0, 1], "parent": None, "settings": {}}
    assert {check["name"] for check in health["checks"]} >= {"input fit", "source size"}
    assert all(isinstance(message, str) for message in health["warnings"] + health["notes"])
    predicted = _json(["predict", str(run), "--frames", "2", "--out", str(tmp_path / "pred")])
    assert predicted["kind"] == "predict" and predicted["frames"] == [2, 3]
    assert Path(predicted["parent"]).resolve() == run.resolve()
    wind = '{"direction": [1, 0, 0], "strength": 0.5}'
    interacted = _json(["interact", str(run), "--frames", "1", "--wind", wind, "--out", str(tmp_path / "wind")])
    assert interacted["kind"] == "interact" and interacted["settings"]["wind"]["strength"] == 0.5
    assert _json(["resimulate", str(run), "--out", str(tmp_path / "resim")])["frames"] == [0, 1]
    rendered = _json(["render", str(run), "--camera", "view_01", "--out", str(tmp_path / "v.mp4")])
    assert rendered["mp4"] == str(tmp_path / "v.mp4") and rendered["frames"] == [0, 1]
    exported = _json(["export", str(run), "--frame", "1", "--format", "npz", "--out", str(tmp_path / "f.npz")])
    assert exported == {"run": str(run), "frame": 1, "format": "npz", "out": str(tmp_path / "f.npz")}


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the answer of a torch without CUDA")
def test_device_cuda_without_cuda_is_one_error_line(scene: Path, tmp_path: Path) -> None:
    args = ["reconstruct", "--cameras", str(scene / "transforms.json"), "--video", f"view_00={scene / 'videos' / 'view_00.mp4'}",
            "--out", str(tmp_path / "r"), "--device", "cuda"]
    result = subprocess.run([*CLI, *args], capture_output=True, text=True)
    assert result.returncode == 2
    assert result.stderr.startswith("error: --device cuda: no CUDA device") and result.stderr.count("\n") == 1
    assert not (tmp_path / "r").exists()
    result = subprocess.run([*CLI, "predict", str(tmp_path), "--frames", "1", "--out", str(tmp_path / "p"), "--device", "gpu0"],
                            capture_output=True, text=True)
    assert result.returncode == 2 and "is not a torch device" in result.stderr


def test_keys_and_serve_share_the_data_folder_from_any_folder(tmp_path: Path) -> None:
    env = {k: v for k, v in os.environ.items() if k not in ("FLUIDNEXUS_DATA_DIR", "XDG_DATA_HOME")}
    env["HOME"] = str(tmp_path / "home")
    here, there = tmp_path / "here", tmp_path / "there"
    here.mkdir()
    there.mkdir()
    subprocess.run([*CLI, "keys", "create", "--owner", "alice"], cwd=here, env=env, capture_output=True, check=True)
    listed = subprocess.run([*CLI, "keys", "list"], cwd=there, env=env, capture_output=True, text=True, check=True)
    assert "alice" in listed.stdout
    assert (tmp_path / "home" / ".local" / "share" / "fluidnexus" / "fluidnexus.sqlite3").is_file()
    assert not any(here.iterdir()) and not any(there.iterdir())
    code = "from service.settings import Settings; print(Settings().resolved_data_dir())"  # what serve uses
    served = subprocess.run([sys.executable, "-c", code], cwd=there, env=env, capture_output=True, text=True, check=True)
    assert served.stdout.strip() == str(tmp_path / "home" / ".local" / "share" / "fluidnexus")

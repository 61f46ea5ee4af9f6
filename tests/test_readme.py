"""README.md's examples, run as written: the quickstart (a synthetic scene, reconstructed,
continued, a what-if, a render and an export) in a fresh folder, then the REST walk-through
against a real `fluidnexus serve` with its worker. A README example that stops working fails here."""

from __future__ import annotations

import os
import re
import subprocess
from pathlib import Path

import pytest

from tests.support.service import ROOT, Server

EXAMPLE = re.compile(r"<!-- example: (\w+) -->\n```bash\n(.*?)```", re.S)


def examples() -> dict[str, str]:
    return dict(EXAMPLE.findall((ROOT / "README.md").read_text()))


def run_block(script: str, cwd: Path, env: dict[str, str], timeout: float) -> str:
    """The block in bash, stopping at its first failing command; its stdout."""
    done = subprocess.run(["bash", "-euo", "pipefail", "-c", script], cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=timeout)
    assert done.returncode == 0, f"exit {done.returncode}\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}"
    return done.stdout


def test_the_readme_marks_its_runnable_examples() -> None:
    assert {"quickstart", "rest"} <= set(examples())


def test_the_quickstart_and_the_rest_walk_through_run_as_written(tmp_path: Path) -> None:
    work = tmp_path / "clone"
    work.mkdir()
    (work / ".venv").symlink_to(ROOT / ".venv")  # what `make run` made in the clone
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    run_block(examples()["quickstart"], work, env, timeout=600)
    assert (work / "windy.mp4").stat().st_size > 0
    assert len(list((work / "run_vdb").glob("smoke_*.vdb"))) == 12
    server = Server(tmp_path / "data")
    try:
        out = run_block(examples()["rest"], work,
                        {**env, "API": f"http://127.0.0.1:{server.port}", "FLUIDNEXUS_DATA_DIR": str(tmp_path / "data")},
                        timeout=600)
    except AssertionError as error:
        pytest.fail(f"{error}\nserver log:\n{server.output()}")
    finally:
        server.stop()
    assert "succeeded" in out.splitlines()
    assert (work / "view_02.mp4").stat().st_size > 1000 and (work / "side_by_side.mp4").stat().st_size > 1000

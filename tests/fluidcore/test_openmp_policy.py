"""Every entry point sets OpenMP's passive wait policy before torch loads the runtime.

libgomp reads OMP_WAIT_POLICY once, when torch first loads it; an entry point that imports
torch before fluidcore would leave worker and benchmark threads spinning on shared cores.
"""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

CHECK = (
    "import importlib, os, sys; importlib.import_module(sys.argv[1]); "
    "assert 'torch' not in sys.modules, 'torch imported before the policy could matter'; "
    "print(os.environ.get('OMP_WAIT_POLICY'))"
)


@pytest.mark.parametrize("module", ["fluidnexus.cli", "service.celery_app", "bench.physics", "bench.render"])
def test_entry_point_sets_passive_waits_before_torch(module: str) -> None:
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    result = subprocess.run([sys.executable, "-c", CHECK, module], env=env, capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "PASSIVE"


def test_an_explicit_policy_is_respected() -> None:
    env = {**os.environ, "OMP_WAIT_POLICY": "ACTIVE"}
    result = subprocess.run([sys.executable, "-c", CHECK, "fluidnexus.cli"], env=env, capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "ACTIVE"

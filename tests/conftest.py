"""Shared test settings: one torch thread per test process (the suite runs with xdist on 2 cores),
and `gpu` tests skipped where CUDA is absent."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

os.environ.setdefault("OMP_NUM_THREADS", "1")

SHARED = Path(__file__).resolve().parents[1].parent / "shared"
REALDATA = SHARED / "realdata"


def pytest_configure(config: pytest.Config) -> None:
    import torch

    torch.set_num_threads(1)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    import torch

    if torch.cuda.is_available():
        return
    skip = pytest.mark.skip(reason="needs a CUDA device")
    for item in items:
        if "gpu" in item.keywords:
            item.add_marker(skip)


@pytest.fixture(scope="session")
def realdata() -> Path:
    """The shared real-smoke benchmark folder; tests that need it skip when it is absent."""
    if not REALDATA.is_dir():
        pytest.skip("../shared/realdata not present")
    return REALDATA


@pytest.fixture(scope="session")
def tiny_models(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A models folder holding randomly initialised tiny Zero123 and CogVideoX models, written in
    the public layouts (fluidcore.generative.random_weights) and loaded back like real weights."""
    from fluidcore.generative import random_weights

    root = tmp_path_factory.mktemp("models")
    random_weights.save_novel_view(random_weights.build_novel_view("tiny", seed=0), root)
    random_weights.save_video(random_weights.build_video("tiny", seed=0), root)
    return root

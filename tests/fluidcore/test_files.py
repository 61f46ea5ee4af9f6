"""Atomic output: the final file appears whole with ordinary permissions, or not at all."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import numpy as np
import pytest

from fluidcore.files import atomic_output
from fluidcore.video import write_mp4


def _mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def test_written_file_gets_the_permissions_of_a_plain_open(tmp_path: Path) -> None:
    reference = tmp_path / "plain.bin"
    reference.write_bytes(b"x")
    target = tmp_path / "out" / "atomic.bin"
    with atomic_output(target) as temporary:
        temporary.write_bytes(b"payload")
    assert target.read_bytes() == b"payload"
    assert _mode(target) == _mode(reference)
    assert sorted(p.name for p in target.parent.iterdir()) == ["atomic.bin"]


def test_failed_write_keeps_the_old_file_and_leaves_no_temporary(tmp_path: Path) -> None:
    target = tmp_path / "state.npz"
    target.write_bytes(b"old")
    with pytest.raises(RuntimeError, match="encoder died"):
        with atomic_output(target) as temporary:
            temporary.write_bytes(b"half")
            raise RuntimeError("encoder died")
    assert target.read_bytes() == b"old"
    assert os.listdir(tmp_path) == ["state.npz"]


def test_mp4_is_readable_by_others_under_the_usual_umask(tmp_path: Path) -> None:
    previous = os.umask(0o022)
    try:
        path = write_mp4(tmp_path / "clip.mp4", np.zeros((2, 16, 16, 3), np.uint8))
    finally:
        os.umask(previous)
    assert _mode(path) == 0o644

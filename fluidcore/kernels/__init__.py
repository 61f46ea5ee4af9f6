"""Fused CPU kernels: small C++/OpenMP sources compiled into shared libraries, called through ctypes.

Why ctypes rather than a torch C++ extension: a source without torch headers compiles in a
couple of seconds, so `make` (and the first use on a machine where `make` was skipped) builds
it quickly. Each kernel works on raw float32/int32 buffers of contiguous CPU tensors; the
differentiable torch reference next to it stays the source of truth and tests compare the two.

A library's file name carries a hash of its source and compiler flags, so an edited source is
rebuilt, a build folder shared by different CPUs (a Docker image built on one host and run on
another) never hands one CPU the other's instructions, and two processes never load a
half-written file (builds go to a temporary name and are renamed).
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import shutil
import subprocess
import sys
import warnings
from functools import lru_cache
from pathlib import Path

from fluidcore.files import atomic_output

SOURCE_DIR = Path(__file__).resolve().parent
BUILD_DIR = SOURCE_DIR / "_build"
BASE_FLAGS = ("-O3", "-std=c++17", "-fopenmp", "-fPIC", "-shared", "-ffp-contract=fast")
# Every feature of x86-64-v3 (AVX2, FMA, BMI1/2, F16C, LZCNT, MOVBE, XSAVE) as /proc/cpuinfo names it.
X86_64_V3 = frozenset({"avx", "avx2", "bmi1", "bmi2", "f16c", "fma", "abm", "movbe", "xsave"})


def sources() -> list[str]:
    """Names of the kernel sources shipped with fluidcore (`NAME.cpp` in this folder)."""
    return sorted(p.stem for p in SOURCE_DIR.glob("*.cpp"))


def cpu_flags(cpuinfo: str | None = None) -> tuple[str, ...]:
    """`-march=x86-64-v3` where this CPU (or the given /proc/cpuinfo text) has every feature of
    that level, else nothing: baseline x86-64 (SSE2) code runs anywhere, and other architectures
    build with the compiler's defaults.

    Why: the pixel loops are SIMD loops; 8-wide AVX2 with FMA instead of 4-wide SSE2 takes about
    a quarter off the splatting compositor and 3-8 % off a PBF step (docs/bench_render.md).
    """
    if cpuinfo is None:
        try:
            cpuinfo = Path("/proc/cpuinfo").read_text()
        except OSError:
            return ()
    for line in cpuinfo.splitlines():
        if line.startswith("flags"):
            return ("-march=x86-64-v3",) if X86_64_V3 <= set(line.partition(":")[2].split()) else ()
    return ()


@lru_cache(maxsize=None)
def compiler_flags() -> tuple[str, ...]:
    """The flags this machine's kernels are built with (read /proc/cpuinfo once per process)."""
    return (*BASE_FLAGS, *cpu_flags())


def library_path(name: str, flags: tuple[str, ...] | None = None) -> Path:
    """Where the library built from the current `NAME.cpp` with `flags` (default: this CPU's) lives."""
    flags = compiler_flags() if flags is None else flags
    digest = hashlib.sha256((SOURCE_DIR / f"{name}.cpp").read_bytes() + "\0".join(flags).encode()).hexdigest()[:12]
    return BUILD_DIR / f"{name}-{digest}.so"


def build(name: str) -> Path:
    """Compile `NAME.cpp` unless the library for this exact source and these flags already exists."""
    target = library_path(name)
    if target.exists():
        return target
    compiler = os.environ.get("CXX") or shutil.which("g++") or shutil.which("c++")
    if compiler is None:
        raise RuntimeError("no C++ compiler found (set CXX); fused CPU kernels cannot be built")
    with atomic_output(target, suffix=".so") as tmp_path:
        cmd = [compiler, *compiler_flags(), str(SOURCE_DIR / f"{name}.cpp"), "-o", str(tmp_path)]
        result = subprocess.run(cmd, capture_output=True, text=True)
        if result.returncode != 0:
            raise RuntimeError(f"building kernel {name!r} failed:\n{result.stderr}")
    for stale in BUILD_DIR.glob(f"{name}-*.so"):
        if stale != target:
            stale.unlink(missing_ok=True)
    return target


@lru_cache(maxsize=None)
def load(name: str) -> ctypes.CDLL | None:
    """The compiled kernel library, building it if needed; None (with a warning) if it cannot be built.

    Callers fall back to their torch reference path on None, so a machine without a
    compiler is slower, never wrong.
    """
    try:
        return ctypes.CDLL(str(build(name)))
    except (OSError, RuntimeError) as exc:
        warnings.warn(f"fused CPU kernel {name!r} unavailable, using the torch path: {exc}")
        return None


def pointer(tensor) -> ctypes.c_void_p:
    """Raw data pointer of a contiguous CPU tensor, for passing to a kernel."""
    if tensor.device.type != "cpu" or not tensor.is_contiguous():
        raise ValueError("kernels take contiguous CPU tensors")
    return ctypes.c_void_p(tensor.data_ptr())


def main() -> None:
    """`python -m fluidcore.kernels build`: compile every kernel source (used by `make`)."""
    if sys.argv[1:] != ["build"]:
        raise SystemExit("usage: python -m fluidcore.kernels build")
    for name in sources():
        print(f"kernel {name}: {build(name)}")

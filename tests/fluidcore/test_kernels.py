"""fluidcore.kernels: which instruction set a kernel is built for, and that each build has its own file."""

from __future__ import annotations

from fluidcore import kernels

V3_FLAGS = "fpu sse sse2 avx avx2 bmi1 bmi2 f16c fma abm movbe xsave popcnt"


def _cpuinfo(flags: str) -> str:
    return f"processor\t: 0\nvendor_id\t: GenuineIntel\nflags\t\t: {flags}\n\nprocessor\t: 1\nflags\t\t: {flags}\n"


def test_x86_64_v3_only_with_every_feature_of_the_level() -> None:
    assert kernels.cpu_flags(_cpuinfo(V3_FLAGS)) == ("-march=x86-64-v3",)
    for missing in ("avx2", "fma", "movbe"):
        without = " ".join(f for f in V3_FLAGS.split() if f != missing)
        assert kernels.cpu_flags(_cpuinfo(without)) == (), missing


def test_other_architectures_keep_the_compiler_defaults() -> None:
    arm = "processor\t: 0\nFeatures\t: fp asimd evtstrm aes pmull sha1 sha2 crc32 atomics fphp asimdhp\n"
    assert kernels.cpu_flags(arm) == ()
    assert kernels.cpu_flags("") == ()


def test_each_instruction_set_builds_to_its_own_file() -> None:
    baseline = kernels.library_path("splat", kernels.BASE_FLAGS)
    v3 = kernels.library_path("splat", (*kernels.BASE_FLAGS, "-march=x86-64-v3"))
    assert baseline != v3 and baseline.parent == v3.parent == kernels.BUILD_DIR
    assert kernels.library_path("splat") == kernels.library_path("splat", kernels.compiler_flags())
    assert kernels.library_path("splat", kernels.BASE_FLAGS) != kernels.library_path("pbf", kernels.BASE_FLAGS)

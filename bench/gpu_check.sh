#!/usr/bin/env bash
# Every check this project runs only on a CUDA machine, as one short unattended run: the gpu-marked
# tests (gsplat against the CPU renderer, CUDA physics) and the GPU benchmark figures (gsplat
# render sweep, PBF at 50k particles). Made for a lent device machine, whose image has CUDA
# torch, nvcc and pytest but not gsplat, and which cannot download: gsplat travels as a wheel.
#
# Prepare once, on the development machine (the wheel is pure Python; gsplat JIT-builds its CUDA
# extension on first use):
#   python3 -m pip download --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
#       --platform manylinux2014_x86_64 -d .whl gsplat==1.5.3
# The generative benchmark also needs diffusers and transformers, which such an image lacks too;
# stage them beside gsplat (pure Python except tokenizers, safetensors, regex and hf-xet):
#   python3 -m pip download --only-binary=:all: --python-version 3.12 --implementation cp \
#       --platform manylinux2014_x86_64 --platform manylinux_2_28_x86_64 -d .whl/generative \
#       diffusers==0.42.1 transformers==5.24.0
#   rm -f .whl/generative/numpy-* .whl/generative/pillow-*   # the image's own numpy and Pillow stay
# Then run `bash bench/gpu_check.sh` there with `.whl` carried; its step limits add up to 570 s,
# inside one device command's 600: the last step (the generative benchmark at real sizes,
# CogVideoX-2b and Zero123-XL with random fp16 weights) gets what the earlier steps left of the
# 570 s, at most 150 s, and is skipped with a message when under 60 s are left. One log
# (gpu_check.log) and the benchmark JSON files go to $OUT (the device tool's result folder, which returns at most 8 files), else ./gpu_check_out.
# Each step is time-limited and the run goes on after a failed step, so one broken stage still
# leaves the others' results; the exit status is the number of failed steps.
set -uo pipefail
cd "$(dirname "$0")/.."
out=${OUT:-gpu_check_out}
mkdir -p "$out"
log=$out/gpu_check.log
failed=0
exec > >(tee "$log") 2>&1

step() {  # step NAME SECONDS COMMAND...: run with a time limit; its output goes to the log
    local name=$1 limit=$2
    shift 2
    echo "== $name (limit ${limit}s)"
    local start=$SECONDS
    timeout "$limit" "$@"
    local rc=$?
    echo "== $name: rc=$rc in $((SECONDS - start))s"
    [ "$rc" -eq 0 ] || failed=$((failed + 1))
}

python3 -m pip install -q --disable-pip-version-check --no-index --no-deps --no-compile --no-cache-dir --target /tmp/site .whl/*.whl \
    || { echo "no gsplat wheel in .whl (see the header of this script)"; exit 1; }
if ls .whl/generative/*.whl >/dev/null 2>&1; then
    python3 -m pip install -q --disable-pip-version-check --no-index --no-deps --no-compile --no-cache-dir --target /tmp/site \
        .whl/generative/*.whl || echo "generative wheels in .whl/generative did not install"
fi
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1
export TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-9.0} MAX_JOBS=${MAX_JOBS:-$(nproc)}
if [ -z "${CUDA_HOME:-}" ] && command -v nvcc >/dev/null; then  # torch's JIT builder needs it
    CUDA_HOME=$(dirname "$(dirname "$(command -v nvcc)")")
    export CUDA_HOME
fi

nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv
step kernels 60 python3 -m fluidcore.kernels build  # CPU side of the agreement tests
# gsplat compiles its CUDA extension on first import of its backend (minutes): once, up front.
step gsplat_build 240 python3 -c "from gsplat.cuda._backend import _C; assert _C is not None, 'gsplat CUDA build failed'"
step pytest_gpu 90 python3 -m pytest -p no:cacheprovider -m gpu -q tests/fluidcore/render/test_gpu.py tests/fluidcore/physics/test_physics.py
step bench_render 90 sh -c "python3 bench/render.py --device cuda --backend gsplat --repeats 20 --json >'$out/bench_render_cuda.json'"
for scene in calm violent; do
    step "bench_physics_$scene" 45 sh -c \
        "python3 bench/physics.py --particles 50000 --scene $scene --device cuda --json >'$out/bench_physics_$scene.json'"
done
budget=570
left=$((budget - SECONDS))
if [ "$left" -ge 60 ]; then
    limit=$((left < 150 ? left : 150))
    step bench_generative "$limit" sh -c \
        "python3 bench/generative.py --size full --device cuda --dtype float16 --views 4 --frames 2 --json >'$out/bench_generative_cuda.json'"
else
    echo "== bench_generative: skipped, only ${left}s of the ${budget}s budget left"
fi
echo "failed steps: $failed"
exit "$failed"

#!/usr/bin/env bash
# The checks only a CUDA machine can run, in one go (about 5 minutes on an H100 or H200):
# gsplat's kernels built, the batch render timed against the code at BASELINE (a folder that
# holds an older gensplat_transforms package; skipped when unset), the geometry cache build per
# batch size, and the CUDA tests. Needs the package with the gsplat extra importable
# (pip install -e '.[dev,gsplat]'); results go to OUT (default: benchmarks/results). QUICK=1 is the
# smoke run of tests/benchmarks/test_benchmark_smoke.py (seconds): both scripts with --quick, no baseline and no
# CUDA tests (the test suite runs those itself), results in OUT (default: outputs/benchmarks_quick).
#
#     OUT=/tmp/gpu BASELINE=/tmp/old bash benchmarks/gpu_checks.sh
set -u
cd "$(dirname "$0")/.."
QUICK=${QUICK:-}
q=${QUICK:+--quick}
if [ -n "$QUICK" ]; then
    OUT=${OUT:-outputs/benchmarks_quick}
    BASELINE=
fi
OUT=${OUT:-benchmarks/results}
mkdir -p "$OUT" && OUT=$(cd "$OUT" && pwd)
card=$(python3 -c "import torch; print(torch.cuda.get_device_name().split()[1].lower() if torch.cuda.is_available() else '')")
if [ -z "$card" ]; then
    echo "gpu_checks: no CUDA device (torch.cuda.is_available() is False)" >&2
    exit 2
fi
step() { echo "=== $(date +%T) $*"; }
export PYTHONUNBUFFERED=1 HF_HUB_OFFLINE=1
step "gsplat kernels (built on first use)"
timeout 300 python3 -c "import gsplat; from gsplat.cuda._backend import _C; print('gsplat', gsplat.__version__)"
if [ -n "${BASELINE:-}" ]; then
    step "render_batch, baseline code"
    (cd benchmarks && PYTHONPATH="$BASELINE:${PYTHONPATH:-}" timeout 120 python3 batch_render.py --no-worker \
        --out "$OUT/batch_render_${card}_before.json")
fi
step "render_batch"
(cd benchmarks && timeout 240 python3 batch_render.py --no-worker --profile $q --out "$OUT/batch_render_${card}.json")
step "geometry cache build per batch size"
timeout 240 python3 benchmarks/geometry_build.py $q --out "$OUT/geometry_build_${card}.json"
if [ -z "$QUICK" ]; then
    step "CUDA tests"
    timeout 300 python3 -m pytest -q -p no:cacheprovider -o addopts="-ra" tests/rendering/test_batched.py \
        tests/rendering/test_batched_compiled.py tests/rendering/test_gsplat_backend.py \
        tests/rendering/test_reference.py::test_auto_backend_on_cuda_is_gsplat_when_installed
fi
step done

#!/usr/bin/env bash
# The GPU check, on a machine with CUDA and gsplat (`pip install -e ".[gpu]"`):
#   1. gsplat's CUDA kernels load (the first call builds them, a few minutes);
#   2. the CUDA tests: gsplat against the CPU rasterisers, the fields on both devices, runs trained
#      on CUDA rendered on both devices (tests/test_cuda.py, tests/render/test_render_api.py);
#   3. gsplat's forward / forward + backward times at the CPU table's workloads;
#   4. the default scene trained with `cpu-fast` on CUDA and evaluated (wall time, PSNR).
# Usage: bash benchmarks/gpu_check.sh SCENE OUT [SECONDS]
#   SCENE: a scene folder (e.g. made by `tracegs synth fan`); OUT: where logs and JSON go;
#   SECONDS: time for the whole check (default: no limit); training stops a minute before it ends
#   (its log.jsonl then gives the time per step), and the evaluation still runs.
set -uo pipefail
scene=$1
out=$2
budget=${3:-0}
py=${PYTHON:-python}
mkdir -p "$out"
export PYTHONUNBUFFERED=1
start=$SECONDS
stamp() { echo "[gpu_check +$((SECONDS - start)) s] $*"; }

stamp "environment"
{
    nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
    $py -c "import torch; print('torch', torch.__version__, 'cuda', torch.version.cuda)"
    $py -c "import gsplat; print('gsplat', gsplat.__version__)"
} 2>&1 | tee "$out/env.txt"

stamp "gsplat kernels"
$py -c "
import time
t = time.perf_counter()
from tracegs.render import gsplat_backend
print('gsplat kernels load:', gsplat_backend.is_available(), f'({time.perf_counter() - t:.0f} s)')
" 2>&1 | tail -5 | tee -a "$out/env.txt"

stamp "CUDA tests"
$py -m pytest -q -rs -p no:cacheprovider tests/test_cuda.py tests/render/test_render_api.py 2>&1 |
    tee "$out/pytest.log" | tail -15

stamp "rasteriser timings"
$py -c "
from tracegs.bench import run_raster_bench
run_raster_bench(json_path='$out/raster_cuda.json', backends=['gsplat'], device='cuda')
" 2>&1 | tail -8

stamp "train the scene on CUDA"
run="$out/run"
limit=()
[ "$budget" -gt 0 ] && limit=(timeout $((budget - (SECONDS - start) - 60)))
"${limit[@]}" $py -m tracegs train --data "$scene" --run "$run" --device cuda 2>&1 |
    tr '\r' '\n' | grep -v "it/s\]$" | tail -5
stamp "evaluate"
$py -m tracegs eval --run "$run" --device cuda --no-lpips --no-save-images --json "$out/eval.json" 2>&1 | tail -3
# keep what re-evaluates the run elsewhere (e.g. on a CPU): its config, checkpoint, log and summary
find "$run" -maxdepth 1 -type f ! -name config.json ! -name checkpoint.pt ! -name summary.json \
    ! -name log.jsonl -delete
find "$run" -mindepth 1 -type d -exec rm -rf {} + 2>/dev/null
stamp "done"

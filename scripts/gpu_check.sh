#!/usr/bin/env bash
# The GPU check in one command (`make gpu-check`): the GPU-marked tests (skipped, never failed,
# without CUDA), then the table of benchmarks/bench_scale.py written to docs/gpu_check.md.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PY:-.venv/bin/python}
"$PY" -m pytest -q -m gpu tests/test_gpu.py
if "$PY" -c "import torch, sys; sys.exit(0 if torch.cuda.is_available() else 1)"; then
  "$PY" benchmarks/bench_scale.py --out docs/gpu_check.md
else
  echo "gpu-check: no CUDA device here; the GPU tests were skipped and no table was written"
fi

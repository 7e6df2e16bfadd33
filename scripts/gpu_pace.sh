#!/usr/bin/env bash
# Training and serving at the GPU's pace, measured in one command on a lent GPU (about 8
# minutes on an H100/H200): each rate beside its floor in the same process (the bare step of the
# same network on device tensors; the bare forward replayed as a CUDA graph), then the GPU
# tests of the captured one-step policy and the device-resident batches.
#
#   bash scripts/gpu_pace.sh                 # the GPU: writes $OUT (default docs/data/gpu_pace)
#   bash scripts/gpu_pace.sh --device cpu    # a smoke run of the same rows on the CPU (~2 min)
#
# BEFORE=/path/to/an/older/checkout also times reflow's couplings/s with that checkout's code
# (its "before"), in its own process on the same GPU.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PY:-.venv/bin/python}
DEVICE=auto
if [ "${1:-}" = "--device" ]; then DEVICE=$2; fi
OUT=${OUT:-docs/data/gpu_pace}
mkdir -p "$OUT"
"$PY" -c "import torch; print('torch', torch.__version__, '| cuda', torch.cuda.is_available() and torch.cuda.get_device_name(0)); import datetime; print(datetime.datetime.now(datetime.timezone.utc).isoformat(timespec='seconds'))" | tee "$OUT/machine.txt"
if [ "$DEVICE" = cpu ]; then
  STEPS=(--steps 10)  # the smoke run: every row, a tiny budget
else
  STEPS=(--steps 600)  # the timed 480 steps of each rate: seconds each, once compiled
  nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader | tee -a "$OUT/machine.txt" || true
fi
# ONLY="train serve reflow" / ONLY=compiled: some of bench_scale's parts (a GPU session that must
# split them over calls: the compiled rows spend minutes compiling)
PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH} "$PY" benchmarks/bench_scale.py --device "$DEVICE" --acceptance "${STEPS[@]}" ${ONLY:+--only $ONLY} \
  --out "$OUT/acceptance.md" --json > "$OUT/acceptance.json"
cat "$OUT/acceptance.md"
if [ -n "${BEFORE:-}" ]; then
  PYTHONPATH=$BEFORE${PYTHONPATH:+:$PYTHONPATH} "$PY" benchmarks/bench_scale.py --device "$DEVICE" --acceptance --only reflow \
    "${STEPS[@]}" --out "$OUT/reflow_before.md" > /dev/null
  echo "before ($BEFORE):"; cat "$OUT/reflow_before.md"
fi
if [ "$DEVICE" != cpu ] && [ "${TESTS:-1}" = 1 ]; then  # TESTS=0: the numbers alone (~2.5 min less)
  "$PY" -m pytest -q -m gpu tests/test_gpu.py -k "captured or device_batches" 2>&1 | tail -5 | tee "$OUT/tests.txt"
fi

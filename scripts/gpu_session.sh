#!/usr/bin/env bash
# sefa's GPU checks on a lent GPU machine, in the device tool's `run` (its $OUT comes back), after
# `bash scripts/gpu_prepare.sh` here:
#
#   run(command="bash scripts/gpu_session.sh check", carry=[".gpu"], timeout_s=...)
#
# Parts (one or more, in order; default: check pace compiled):
#   check     `make gpu-check`: the GPU-marked tests, then bench_scale's table into
#             docs/gpu_check.md between its markers (that page comes back in $OUT)
#   pace      scripts/gpu_pace.sh $PACE_ARGS ("--device cpu": its smoke run): eager training
#             and serving against their floors, reflow captured and eager (into $OUT/pace;
#             TESTS=0, since `check` runs the same tests)
#   compiled  the same script's torch.compile training rows (into $OUT/compiled): minutes of
#             compiling, so a part of its own
#   latency   one decision at 1, 4, 16 and 64 samples on the GPU (`sefa bench latency --samples`):
#             the Push-T low-dim networks (pusht_lowdim_train.yaml, trained 20 steps here: a
#             latency depends on the network, not its weights) at one Euler step (the one-step
#             student's cost), Euler-10 and DDIM-10, into $OUT/latency.json and
#             its table, latency.txt
#             ($LATENCY_DEVICE, default cuda; "cpu" for its smoke run)
#
# The machine's image has PyTorch with CUDA and no package registry: the wheels sefa needs
# beyond it are installed from .gpu/whl into /tmp/site, the checkout is installed editable (its
# import names sefa_cli and sefa_pipelines), and the Push-T copy is linked where
# ../shared/data would be. Each part's seconds are printed, to plan the next session's calls.
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${OUT:-/tmp/sefa-gpu-out}
mkdir -p "$OUT"
PARTS=("$@")
[ ${#PARTS[@]} -gt 0 ] || PARTS=(check pace compiled latency)
PYTHON=${PYTHON:-python3}  # the image's Python, which holds PyTorch with CUDA
export PY=$PYTHON PYTHONUNBUFFERED=1
started=$SECONDS
"$PYTHON" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
  --target /tmp/site .gpu/whl/*.whl
export PYTHONPATH=/tmp/site${PYTHONPATH:+:$PYTHONPATH}
"$PYTHON" -m pip install -q --no-index --no-deps --no-build-isolation --no-cache-dir -e . > /dev/null
mkdir -p ../shared/data
[ -e ../shared/data/pusht_cchi_v7_replay.zarr ] || \
  ln -s "$PWD/.gpu/data/pusht_cchi_v7_replay.zarr" ../shared/data/pusht_cchi_v7_replay.zarr
"$PYTHON" -c "import torch, sefa_cli, zarr; print('torch', torch.__version__, torch.cuda.is_available() and torch.cuda.get_device_name(0))"
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader || true
echo "setup: $((SECONDS - started)) s"
latency_part() {
  local dev=${LATENCY_DEVICE:-cuda} ws log
  ws=$(mktemp -d)/ws
  log=$(dirname "$ws")/latency.log
  local sefa=("$PYTHON" -m sefa_cli.main)
  {
    "${sefa[@]}" ingest ../shared/data/pusht_cchi_v7_replay.zarr --fps 10 --key keypoint \
      --key state --key action -w "$ws"
    for objective in flow ddpm; do
      "${sefa[@]}" train pipelines/pusht_lowdim_train.yaml --objective $objective \
        --out "$ws/$objective" --device "$dev" training.max_steps=20 training.val_every=20 \
        training.checkpoint_every=20 training.lr_warmup_steps=2 -w "$ws"
    done
    "${sefa[@]}" bench latency flow@euler-1 flow@euler-10 ddpm@ddim-10 --samples 1,4,16,64 \
      --calls 100 --device "$dev" --json -w "$ws" > "$OUT/latency.json"
  } > "$log" 2>&1 || { tail -n 30 "$log"; return 1; }
  "$PYTHON" scripts/latency_table.py "$OUT/latency.json" | tee "$OUT/latency.txt"
}

for part in "${PARTS[@]}"; do
  t=$SECONDS
  case $part in
    check) bash scripts/gpu_check.sh 2>&1 | tee "$OUT/check.log"
           cp docs/gpu_check.md "$OUT/gpu_check.md" ;;
    # (no logs of their own: the tool brings back 8 files at most, and these write 3 each)
    pace)  ONLY="train serve reflow" TESTS=0 OUT="$OUT/pace" bash scripts/gpu_pace.sh ${PACE_ARGS:-} ;;
    compiled) ONLY=compiled TESTS=0 OUT="$OUT/compiled" bash scripts/gpu_pace.sh ${PACE_ARGS:-} ;;
    latency) latency_part ;;
    *)     echo "gpu_session: unknown part '$part' (check, pace, compiled, latency)"; exit 2 ;;
  esac
  echo "$part: $((SECONDS - t)) s"
done

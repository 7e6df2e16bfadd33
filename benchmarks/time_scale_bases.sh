#!/usr/bin/env bash
# The time-embedding study's base flows (issue 26): the `cpu` profile's base
# (pipelines/pusht_lowdim_train.yaml: MLP head, 30,000 steps of a 50,000-step cosine schedule) once
# per flow.time_scale, in fp32 and with the same seed, so the rows differ only in the scale. The
# rows train side by side on DEVICE (one process each, THREADS CPU threads each).
#
#   bash benchmarks/time_scale_bases.sh WS DEVICE [SCALE...]      (default scales: 999 100 10 1)
#
# WS gets the Push-T store (ingested once) and WS/bases/ts<SCALE>/, a run directory per row with
# its log beside it (ts<SCALE>.log). EXTRA="key=value ..." adds overrides to every row (a quick
# check: EXTRA="training.max_steps=20 training.val_every=20 training.checkpoint_every=20").
# The rows are then measured by benchmarks/time_scale_study.py.
set -euo pipefail
cd "$(dirname "$0")/.."
ws=$1; device=$2; shift 2
scales=("$@"); [ ${#scales[@]} -gt 0 ] || scales=(999 100 10 1)
PY=${PY:-.venv/bin/python}
THREADS=${THREADS:-4}
DATA=${DATA:-../shared/data/pusht_cchi_v7_replay.zarr}

mkdir -p "$ws/bases"
[ -d "$ws/dataset.zarr" ] || "$PY" -m sefa_cli.main ingest "$DATA" --fps 10 --key keypoint --key state \
  --key action -w "$ws"
pids=()
for s in "${scales[@]}"; do
  # shellcheck disable=SC2086  # EXTRA is a list of overrides
  "$PY" -m sefa_cli.main train pipelines/pusht_lowdim_train.yaml "flow.time_scale=$s" \
    training.mixed_precision=false ${EXTRA:-} --device "$device" --threads "$THREADS" \
    --out "$ws/bases/ts$s" -w "$ws" > "$ws/bases/ts$s.log" 2>&1 &
  pids+=($!)
done
rc=0
for i in "${!pids[@]}"; do
  wait "${pids[$i]}" || { echo "time_scale ${scales[$i]}: training failed (see $ws/bases/ts${scales[$i]}.log)" >&2; rc=1; }
done
exit $rc

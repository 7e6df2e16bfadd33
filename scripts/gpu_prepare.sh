#!/usr/bin/env bash
# Prepares, on this machine, what a lent GPU machine needs to run sefa's GPU checks: it has
# PyTorch with CUDA but no package registry and no ../shared, so the wheels of sefa's
# dependencies missing from its image (Python 3.12, x86-64) and the Push-T store travel with the
# working tree in .gpu/ (ignored by git through .git/info/exclude; about 30 MiB, with the
# checkout's 4, of the 64 MiB a call may carry). Then, there, one call: run `bash scripts/gpu_session.sh` with carry [".gpu"].
#
#   bash scripts/gpu_prepare.sh        # idempotent: downloads only what .gpu/whl lacks
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PY:-.venv/bin/python}
SHARED=${SHARED:-../shared/data}
mkdir -p .gpu/whl .gpu/data
grep -qxF "/.gpu/" .git/info/exclude 2>/dev/null || { mkdir -p .git/info; echo "/.gpu/" >> .git/info/exclude; }

# sefa's runtime and test dependencies that the GPU image lacks (the device tool's KINDS.md lists
# the image's packages), at the versions this checkout's environment runs: the closure of
# `sefa[test]`'s requirements minus the image's list, computed by scripts/gpu_missing.py
mapfile -t WANT < <("$PY" scripts/gpu_missing.py)
for spec in "${WANT[@]}"; do
  name=${spec%%==*}
  if ls .gpu/whl | grep -qi "^$(echo "$name" | tr '-' '_')-${spec##*==}-"; then continue; fi
  "$PY" -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 \
    --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 --platform manylinux1_x86_64 \
    -d .gpu/whl "$spec"
done
# Push-T without its camera frames (29 of its 32 MiB): the GPU checks train on the low-dim keys;
# bench_scale's table then leaves out its image-loader row and says so
if [ ! -d .gpu/data/pusht_cchi_v7_replay.zarr ]; then
  cp -r "$SHARED/pusht_cchi_v7_replay.zarr" .gpu/data/.pusht.tmp
  rm -rf .gpu/data/.pusht.tmp/data/img
  mv .gpu/data/.pusht.tmp .gpu/data/pusht_cchi_v7_replay.zarr
fi
du -sh .gpu

#!/usr/bin/env bash
# Create .venv and install sefa with everything the README commands need.
# On a machine without an NVIDIA GPU, PyTorch's CPU build is installed first (from a local wheel
# that pip's configured find-links offers, else from PyTorch's CPU index), so the resolver never
# pulls the multi-GB CUDA build. With a GPU, pip takes the newest CUDA build: nothing is pinned.
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-python3}

[ -x .venv/bin/python ] || "$PYTHON" -m venv .venv
PIP=".venv/bin/python -m pip"

if ! .venv/bin/python -c "import torch" 2>/dev/null; then
  if command -v nvidia-smi >/dev/null 2>&1 && nvidia-smi -L >/dev/null 2>&1; then
    $PIP install torch
  elif $PIP install --no-index --no-deps torch >/dev/null 2>&1; then
    echo "setup: installed the local CPU build of torch"
  else
    $PIP install --no-deps torch --index-url https://download.pytorch.org/whl/cpu
  fi
fi
# Resolves torch's own dependencies too; an installed torch satisfies `torch>=...` as it is.
$PIP install -e ".[test,sim,bench,deploy,docs]"
# robomimic's own loader checks our `sefa collect` output in the tests. Its declared
# dependencies (tensorboard, torchvision, egl_probe, which builds with cmake) are not needed by
# the SequenceDataset the tests use (numpy, h5py, torch, tqdm, termcolor: all in the test extra).
$PIP install --no-deps "robomimic==0.3.0"
touch .venv/.sefa-installed

#!/usr/bin/env bash
# The real client for sefa's LeRobot plugin: LeRobot 0.6.1's own loaders and programs
# (lerobot-eval on gym-pusht, lerobot-rollout, the async policy_server and robot_client) running
# `sefa export --format lerobot` folders, in LeRobot's own environment.
#   scripts/lerobot_plugin_check.sh [PYTEST ARGS]
# LeRobot 0.5+ needs Python >= 3.12 and sefa's .venv runs 3.11, so the check has a venv of its
# own: ${SEFA_LEROBOT_VENV:-$HOME/.cache/sefa-lerobot-check} (the LeRobot 0.6.1 environment the
# shared dataset check uses too; built here when missing: CPU torch when there is no NVIDIA GPU,
# then lerobot[pusht,async]==0.6.1 and pytest). Every run then installs this checkout's sefa
# (no extras) and integrations/lerobot into it and runs integrations/lerobot/tests.
# Exit: pytest's; 2 when the environment cannot be built or installed into (no Python >= 3.12,
# no package index, ...): the reason is the last line.
set -euo pipefail
cd "$(dirname "$0")/.."
venv=${SEFA_LEROBOT_VENV:-$HOME/.cache/sefa-lerobot-check}
log="$venv.plugin-install.log"
lerobot='lerobot[pusht,async]==0.6.1'   # integrations/lerobot/pyproject.toml's tested version
probe='import lerobot, gym_pusht, grpc, pytest, sys; from importlib.metadata import version; sys.exit(version("lerobot") != "0.6.1")'

if ! "$venv/bin/python" -c "$probe" 2>/dev/null; then
  if [ ! -x "$venv/bin/python" ]; then
    py=""   # a Python >= 3.12 that really runs (a pyenv shim answers "command not found" unless selected)
    for c in python3.12 python3.13 $(ls -d "$(pyenv root 2>/dev/null || echo "$HOME/.pyenv")"/versions/3.1[2-9]*/bin/python3 2>/dev/null); do
      if "$c" -c 'import sys; sys.exit(sys.version_info < (3, 12))' 2>/dev/null; then py=$c; break; fi
    done
    [ -n "$py" ] || { echo "lerobot_plugin_check: no working Python >= 3.12 (LeRobot 0.6.1 needs it; e.g. pyenv install 3.12): the LeRobot plugin was not checked"; exit 2; }
    "$py" -m venv "$venv" >"$log" 2>&1 || { echo "lerobot_plugin_check: cannot create a venv at $venv, see $log"; exit 2; }
    if ! { command -v nvidia-smi >/dev/null 2>&1 && nvidia-smi -L >/dev/null 2>&1; }; then
      # LeRobot pins torch >= 2.7, < 2.12; the CPU build, not the multi-GB CUDA one
      "$venv/bin/python" -m pip install -q "torch>=2.7,<2.12" "torchvision<0.27" \
        --index-url https://download.pytorch.org/whl/cpu >>"$log" 2>&1 \
        || echo "lerobot_plugin_check: no CPU torch from PyTorch's index; pip will pick one" >>"$log"
    fi
  fi
  echo "lerobot_plugin_check: installing $lerobot into $venv (once; a few minutes)"
  "$venv/bin/python" -m pip install -q "$lerobot" pytest >>"$log" 2>&1 \
    || { echo "lerobot_plugin_check: pip could not install $lerobot, see $log"; exit 2; }
fi
# this checkout's sefa (no extras: the plugin imports none of sefa's simulators or ROS readers)
# and the plugin; gym-pusht is LeRobot's pusht extra, which the tests' sefa_sim checks also use.
# setuptools' build folders are removed first: they keep modules the checkout no longer has
rm -rf build integrations/lerobot/build
"$venv/bin/python" -m pip install -q --no-build-isolation . ./integrations/lerobot >>"$log" 2>&1 \
  || { echo "lerobot_plugin_check: pip could not install sefa and integrations/lerobot into $venv, see $log"; exit 2; }
cd integrations/lerobot
HF_HUB_OFFLINE=1 exec "$venv/bin/python" -m pytest -q -p no:cacheprovider tests "$@"

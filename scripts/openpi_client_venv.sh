#!/usr/bin/env bash
# The real openpi client (openpi-client 0.1.2 from PyPI) in a venv of its own, for the tests that
# drive `sefa serve` with it (tests/sefa_deploy_tests/test_serve_openpi.py):
#   scripts/openpi_client_venv.sh        -> prints the venv's python on its last line
# Its own venv, not sefa's: the wheel pins numpy < 2 (sefa runs numpy 2), pulls dm-tree, pillow
# and absl, and forgets to declare typing_extensions (installed here beside it). The first call
# builds ${SEFA_OPENPI_CLIENT_VENV:-$HOME/.cache/sefa-openpi-client} (about 40 s, 60 MB) with the
# Python that runs sefa (PYTHON, default python3); later calls reuse it.
# Exit 0: ready; 2: it could not be built (no package index, ...): the reason is the last line.
set -euo pipefail
venv=${SEFA_OPENPI_CLIENT_VENV:-$HOME/.cache/sefa-openpi-client}
probe='import openpi_client.websocket_client_policy, openpi_client.action_chunk_broker'
if ! "$venv/bin/python" -c "$probe" 2>/dev/null; then
  if [ -e "$venv" ] && [ ! -e "$venv/pyvenv.cfg" ]; then
    echo "openpi_client_venv: $venv exists and is not a venv; not touching it"; exit 2
  fi
  "${PYTHON:-python3}" -m venv --clear "$venv" >"$venv.install.log" 2>&1 \
    || { echo "openpi_client_venv: cannot create a venv at $venv, see $venv.install.log"; exit 2; }
  "$venv/bin/python" -m pip install -q "openpi-client==0.1.2" typing_extensions >>"$venv.install.log" 2>&1 \
    || { echo "openpi_client_venv: pip could not install openpi-client==0.1.2 (no package index, or no numpy < 2 wheel for this Python?), see $venv.install.log"; exit 2; }
  "$venv/bin/python" -c "$probe" >>"$venv.install.log" 2>&1 \
    || { echo "openpi_client_venv: openpi-client installed but does not import, see $venv.install.log"; exit 2; }
fi
echo "$venv/bin/python"

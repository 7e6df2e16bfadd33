"""Runs in the openpi client's own venv (scripts/openpi_client_venv.sh), never in sefa's: the
unmodified openpi-client 0.1.2 times its calls against `sefa serve` for bench_serve.py.

    python openpi_bench_client.py HOST PORT OBS.npz
        OBS.npz: the observation keys (To, ...) and `noise`. Prints one JSON line with the first
        reply's actions, then for each line N read from stdin, one JSON line: N call times (s).
"""

import json
import sys
import time

import numpy as np
from openpi_client.websocket_client_policy import WebsocketClientPolicy


def main(host: str, port: int, obs_file: str) -> None:
    obs = dict(np.load(obs_file))
    policy = WebsocketClientPolicy(host, port)  # blocks until the metadata frame
    print(json.dumps({"actions": policy.infer(obs)["actions"].tolist()}), flush=True)
    for line in sys.stdin:
        times = []
        for _ in range(int(line)):
            start = time.perf_counter()
            policy.infer(obs)
            times.append(time.perf_counter() - start)
        print(json.dumps(times), flush=True)


if __name__ == "__main__":
    main(sys.argv[1], int(sys.argv[2]), sys.argv[3])

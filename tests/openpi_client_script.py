"""Runs in the openpi client's own venv (scripts/openpi_client_venv.sh), never in sefa's: the
unmodified openpi-client 0.1.2 drives a `sefa serve` process. tests/sefa_deploy_tests/test_serve_openpi.py writes
the inputs and reads what the client got.

    python openpi_client_script.py MODE HOST PORT DIR
        DIR/in.npz holds the observations; the results go to DIR/out.npz and DIR/out.json.
"""

import json
import sys
from pathlib import Path

import numpy as np
from openpi_client import msgpack_numpy
from openpi_client.action_chunk_broker import ActionChunkBroker
from openpi_client.websocket_client_policy import WebsocketClientPolicy


def error_of(policy, obs):
    try:
        policy.infer(obs)
    except RuntimeError as e:  # the client's own reaction to a text frame
        return str(e)
    return None


def main(mode: str, host: str, port: int, work: Path) -> None:
    data = dict(np.load(work / "in.npz"))
    arrays, facts = {}, {}
    policy = WebsocketClientPolicy(host, port)  # blocks until the metadata frame
    facts["metadata"] = policy.get_server_metadata()
    obs = {"observation/keypoint": data["keypoint0"], "observation/state": data["state0"],
           "prompt": "push the T"}
    if mode == "nan":
        facts["error"] = error_of(policy, {**obs, "noise": data["noise0"]})
    else:
        reply = policy.infer({**obs, "noise": data["noise0"]})
        arrays["actions"] = reply["actions"]
        facts["reply_keys"] = sorted(reply)
        facts["server_timing"] = reply["server_timing"]
        # nested maps: their names join with "/"
        nested = {"observation": {"keypoint": data["keypoint0"], "state": data["state0"]},
                  "noise": data["noise0"]}
        arrays["nested"] = policy.infer(nested)["actions"]
        facts["timing2"] = policy.infer(obs)["server_timing"]
        facts["errors"] = {
            "missing": error_of(policy, {"observation/keypoint": data["keypoint0"]}),
            "unexpected": error_of(policy, {**obs, "observation/wrist": data["state0"]}),
            "batch": error_of(policy, {"observation/keypoint": data["keypoint0"][None],
                                       "observation/state": data["state0"][None]}),
            "noise": error_of(policy, {**obs, "noise": data["noise0"][:, :1]}),
            "nan": error_of(policy, {**obs, "observation/state": data["state0"] * np.nan}),
        }
        # the broker: one request per chunk, then a step of it per call
        broker = ActionChunkBroker(policy, action_horizon=int(data["horizon"]))
        steps = []
        for chunk in range(2):
            o = {**obs, "observation/keypoint": data[f"keypoint{chunk}"],
                 "observation/state": data[f"state{chunk}"], "noise": data[f"noise{chunk}"]}
            for _ in range(int(data["horizon"])):
                steps.append(broker.infer(o)["actions"])
        arrays["broker"] = np.stack(steps)
        # the codec itself: what openpi's msgpack_numpy writes, byte for byte
        sample = {"a": np.arange(6, dtype=np.float32).reshape(2, 3), "i": np.arange(3),
                  "s": np.float32(1.5), "u": np.zeros((2, 2), np.uint8)}
        (work / "openpi_packed.bin").write_bytes(msgpack_numpy.packb(sample))
        ours = msgpack_numpy.unpackb((work / "sefa_packed.bin").read_bytes())
        facts["decoded_ours"] = {k: [type(v).__name__, str(v.dtype), list(np.shape(v)),
                                     np.asarray(v).ravel().tolist()] for k, v in ours.items()}
    np.savez(work / "out.npz", **arrays)
    (work / "out.json").write_text(json.dumps(facts, default=str))


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], int(sys.argv[3]), Path(sys.argv[4]))

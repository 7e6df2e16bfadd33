"""Issue 24: an unmodified openpi client (openpi-client 0.1.2 from PyPI, in a venv of its own:
scripts/openpi_client_venv.sh) drives a real `sefa serve` process over a real socket. Its
`WebsocketClientPolicy` gets the metadata on connect, its actions equal `predict_action`'s with
the same noise, its `ActionChunkBroker` steps through them, errors reach it as the RuntimeError
it raises for a text frame, a NaN policy never reaches it, `GET /healthz` is 200, and our own
client is served on the same port at the same time. Skipped, with the reason, only when the
client's venv cannot be built (no package index)."""

from __future__ import annotations

import json
import subprocess
import sys
import urllib.error
import urllib.request
from pathlib import Path

import msgpack
import numpy as np
import pytest
import torch

from deploy_helpers import REPO, Server, connect_sefa, validation_windows
from sefa_deploy.client import PolicyClient, pack, unpack
from sefa_deploy.server import RequestError, check_openpi, parse_key_map
from sefa_model.policy.artifact import Policy

KEY_MAP = ["--key-map", "observation/keypoint=keypoint", "--key-map", "observation/state=state",
           "--key-map", "prompt="]


@pytest.fixture(scope="module")
def openpi_python() -> str:
    r = subprocess.run(["bash", str(REPO / "scripts" / "openpi_client_venv.sh")],
                       capture_output=True, text=True, env={**__import__("os").environ,
                                                            "PYTHON": sys._base_executable})
    lines = (r.stdout + r.stderr).strip().splitlines() or ["(no output)"]
    if r.returncode == 2:
        pytest.skip(lines[-1])
    assert r.returncode == 0, "\n".join(lines[-20:])
    return lines[-1]


@pytest.fixture(scope="module")
def ws(deploy_workspace) -> Path:
    return deploy_workspace


@pytest.fixture(scope="module")
def windows(ws) -> dict[str, np.ndarray]:
    return validation_windows(Policy.load(ws / "distill"), ws / "dataset.zarr", 10)


def inputs(windows: dict, work: Path) -> dict:
    rng = np.random.default_rng(24)
    data = {"horizon": np.int64(8)}
    for i in range(2):
        data[f"keypoint{i}"], data[f"state{i}"] = windows["keypoint"][3 + i], windows["state"][3 + i]
        data[f"noise{i}"] = rng.standard_normal((16, 2), dtype=np.float32)
    np.savez(work / "in.npz", **data)
    return data


def run_client(python: str, mode: str, port: int, work: Path) -> tuple[dict, dict]:
    r = subprocess.run([python, str(REPO / "tests" / "openpi_client_script.py"), mode,
                        "127.0.0.1", str(port), str(work)], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0, r.stderr[-3000:]
    return json.loads((work / "out.json").read_text()), dict(np.load(work / "out.npz"))


def predicted(ws: Path, keypoint, state, noise) -> np.ndarray:
    out = Policy.load(ws / "distill").predict_action(
        {"keypoint": keypoint[None], "state": state[None]}, noise=torch.from_numpy(noise[None]))
    return out.action.numpy()[0]


def test_the_openpi_client_gets_predict_actions_and_our_client_still_works(
        ws, windows, openpi_python, tmp_path):
    server = Server(ws / "distill", *KEY_MAP)
    try:
        data = inputs(windows, tmp_path)
        sample = {"a": np.arange(6, dtype=np.float32).reshape(2, 3), "i": np.arange(3),
                  "s": np.float32(1.5), "u": np.zeros((2, 2), np.uint8)}
        (tmp_path / "sefa_packed.bin").write_bytes(pack(sample))
        facts, got = run_client(openpi_python, "main", server.port, tmp_path)

        meta = facts["metadata"]  # the frame it waited for on connect
        assert meta["n_action_steps"] == 8 and list(meta["obs"]) == ["keypoint", "state"]
        assert meta["key_map"] == {"observation/keypoint": "keypoint",
                                   "observation/state": "state", "prompt": ""}

        want = [predicted(ws, data[f"keypoint{i}"], data[f"state{i}"], data[f"noise{i}"])
                for i in range(2)]
        assert got["actions"].shape == (8, 2)  # the steps to execute now, the step first
        np.testing.assert_allclose(got["actions"], want[0], rtol=0, atol=1e-5)
        np.testing.assert_allclose(got["nested"], want[0], rtol=0, atol=1e-5)
        assert facts["reply_keys"] == ["actions", "server_timing"]
        assert facts["server_timing"]["infer_ms"] > 0 and "prev_total_ms" not in facts["server_timing"]
        assert facts["timing2"]["prev_total_ms"] > 0
        # ActionChunkBroker: 8 steps of the first chunk, then 8 of the second
        np.testing.assert_allclose(got["broker"], np.concatenate(want), rtol=0, atol=1e-5)

        errors = {k: v.split("\n") for k, v in facts["errors"].items()}
        assert all(v[0] == "Error in inference server:" and len(v) == 2 for v in errors.values()), errors
        assert errors["missing"][1].startswith("observation 'state' missing (the policy needs: "
                                               "keypoint, state); sefa serve --key-map NAME=KEY")
        assert errors["unexpected"][1].startswith("unexpected observation 'observation/wrist'")
        assert errors["batch"][1].startswith("an openpi request is one observation, not a batch")
        assert errors["noise"][1].startswith("noise: shape (16, 1)")
        assert errors["nan"][1] == "observation 'state': contains NaN or Inf"

        # openpi's msgpack_numpy and ours write the same bytes and read each other's
        assert (tmp_path / "openpi_packed.bin").read_bytes() == pack(sample)
        theirs = unpack((tmp_path / "openpi_packed.bin").read_bytes())
        for k, v in sample.items():
            assert type(theirs[k]) is type(v) and theirs[k].dtype == v.dtype
            np.testing.assert_array_equal(theirs[k], v)
        assert facts["decoded_ours"]["a"] == ["ndarray", "float32", [2, 3], [0, 1, 2, 3, 4, 5]]
        assert facts["decoded_ours"]["s"] == ["float32", "float32", [], [1.5]]

        # the same port, our own protocol, meanwhile
        with PolicyClient(server.url) as ours:
            noise = data["noise0"]
            obs = {"keypoint": data["keypoint0"], "state": data["state0"]}
            np.testing.assert_allclose(ours.infer(obs, noise=noise)["action"], want[0], atol=1e-5)
            health = ours.health()
            assert health["errors"] == 5 and health["requests"] >= 3 + 5 + 2

        # openpi's health check: a plain GET, 200
        with urllib.request.urlopen(f"http://127.0.0.1:{server.port}/healthz", timeout=10) as r:
            assert r.status == 200 and r.read() == b"OK\n"
        with pytest.raises(urllib.error.HTTPError) as other:  # any other path: a websocket only
            urllib.request.urlopen(f"http://127.0.0.1:{server.port}/", timeout=10)
        assert other.value.code == 426
    finally:
        code, _, err = server.stop()
    assert code == 0 and "Traceback" not in err, err[-2000:]


def test_a_nan_policy_reaches_the_openpi_client_as_an_error_never_as_actions(
        deploy_exports, windows, openpi_python, tmp_path):
    server = Server(deploy_exports("one-step", "torchscript"), *KEY_MAP, fault="nan")
    try:
        inputs(windows, tmp_path)
        facts, got = run_client(openpi_python, "nan", server.port, tmp_path)
        assert facts["error"].startswith("Error in inference server:\nthe policy produced "
                                         "non-finite actions (NaN or Inf in 'action')")
        assert got == {}
    finally:
        code, out, err = server.stop()
    assert code == 0 and "non-finite actions" in out, err[-2000:]


def test_a_bare_socket_is_openpi_and_draws_the_seeded_noise(ws, deploy_exports, windows):
    """A bare websocket is an openpi client: the metadata frame comes first, errors are text;
    one that offers the subprotocol gets sefa's protocol, the array in openpi's encoding. A
    request without `noise` gets the server's first draw of its `--seed`ed generator."""
    from websockets.sync.client import connect

    server = Server(deploy_exports("one-step", "torchscript"), "--seed", "7")
    try:
        with connect(server.url) as bare:
            meta = unpack(bare.recv(timeout=10))
            assert meta["n_action_steps"] == 8 and meta["key_map"] == {}
            bare.send(pack({"type": "metadata", "id": 1}))  # sefa's words on an openpi connection
            assert bare.recv(timeout=10).startswith("observation 'keypoint' missing")
            bare.send(b"\xc1 not msgpack")
            assert "not a msgpack message" in bare.recv(timeout=10)
            obs = {k: v[0] for k, v in windows.items()}
            bare.send(pack(obs))
            reply = unpack(bare.recv(timeout=10))
            drawn = np.random.default_rng(7).standard_normal((1, 16, 2), dtype=np.float32)
            np.testing.assert_allclose(reply["actions"], predicted(
                ws, obs["keypoint"], obs["state"], drawn[0]), atol=1e-3)
        with connect_sefa(server.url) as raw:
            raw.send(pack({"type": "metadata", "id": 1}))
            raw_reply = raw.recv(timeout=10)
            assert isinstance(raw_reply, bytes) and unpack(raw_reply)["protocol"] == 2
            assert msgpack.unpackb(raw_reply, raw=False, strict_map_key=False)["ok"] is True
    finally:
        code, _, err = server.stop()
    assert code == 0, err[-2000:]


def test_key_map_and_openpi_request_checks():
    meta = {"obs": {"keypoint": {"shape": [1, 9, 2], "dtype": "float32"},
                    "state": {"shape": [1, 2], "dtype": "float32"}},
            "noise": {"shape": [16, 2]}}
    assert parse_key_map(["a/b=state", "prompt="]) == {"a/b": "state", "prompt": ""}
    for bad in (["state"], ["=state"], ["a=state", "a=keypoint"]):
        with pytest.raises(ValueError, match="is not NAME=KEY"):
            parse_key_map(bad)
    kp, st = np.zeros((9, 2), np.float32), np.zeros(2, np.float32)
    # a To = 1 policy takes the bare frame, as openpi's policies do
    obs, noise = check_openpi({"keypoint": kp, "s": st, "prompt": "x"}, meta,
                              {"s": "state", "prompt": ""})
    assert obs["keypoint"].shape == (1, 1, 9, 2) and obs["state"].shape == (1, 1, 2) and noise is None
    with pytest.raises(RequestError, match="observation 'state' given twice"):
        check_openpi({"keypoint": kp, "s": st, "state": st}, meta, {"s": "state"})
    with pytest.raises(RequestError, match="a msgpack map of observation name"):
        check_openpi([kp], meta, {})


@pytest.mark.parametrize("args,line", [
    (["--key-map", "observation/state"], "error: --key-map: 'observation/state' is not NAME=KEY"),
    (["--key-map", "a=state", "--key-map", "a=keypoint"], "error: --key-map: 'a=keypoint' is not NAME=KEY"),
    (["--key-map", "observation/state=gripper"],
     "error: --key-map: 'observation/state=gripper': the policy has no observation 'gripper' "
     "(it takes: keypoint, state)"),
])
def test_a_bad_key_map_is_one_line_and_no_server(deploy_exports, args, line, monkeypatch, capsys):
    from sefa_cli.main import main

    monkeypatch.setattr("sys.argv", ["sefa", "serve", str(deploy_exports("one-step", "torchscript")),
                                     "--port", "0", *args])
    with pytest.raises(SystemExit) as e:
        main()
    err = capsys.readouterr().err
    assert e.value.code == 1 and err.count("\n") == 1 and err.startswith(line), err



def test_eval_parses_its_key_map_as_serve_does_naming_the_simulator(tmp_path, monkeypatch, capsys):
    """`sefa eval --key-map` takes serve's NAME=KEY items, where NAME is the simulator's: a bad
    one is one line before any work (the workspace does not exist)."""
    from sefa_cli.main import main

    monkeypatch.setattr("sys.argv", ["sefa", "eval", "--env", "pusht", "--key-map", "img",
                                     "-w", str(tmp_path / "none")])
    with pytest.raises(SystemExit) as e:
        main()
    err = capsys.readouterr().err
    assert e.value.code == 1 and err == (
        "error: --key-map: 'img' is not NAME=KEY (a simulator's observation name, '=', the "
        "policy's key or nothing to drop it; each name once)\n")

def test_our_client_refuses_a_server_that_does_not_choose_the_subprotocol():
    """An openpi server, or a `sefa serve` from before protocol 2: one clear line, not a reply
    that answers the wrong request."""
    import threading

    from websockets.sync.server import serve

    from sefa_deploy.client import PolicyServerError

    with serve(lambda conn: conn.recv(), "127.0.0.1", 0) as other:
        threading.Thread(target=other.serve_forever, daemon=True).start()
        port = other.socket.getsockname()[1]
        with pytest.raises(PolicyServerError, match="does not speak sefa protocol 2 .no 'sefa.v2' "
                                                    "subprotocol"):
            PolicyClient(f"ws://127.0.0.1:{port}", open_timeout=5)
        other.shutdown()

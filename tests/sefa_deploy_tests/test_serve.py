"""`sefa serve` (issue 13) as a separate process on a free loopback port, spoken to with the
package's client: answers equal to the artifact's and the checkpoint's with the same noise,
metadata and health, the receding-horizon mode, bad requests answered with errors while the
server keeps serving, a client vanishing mid-request, two clients at once, and a clean exit on
SIGINT and SIGTERM."""

from __future__ import annotations

import signal
import socket
import threading
import time
from pathlib import Path

import msgpack
import numpy as np
import pytest
import torch
from websockets.exceptions import ConnectionClosed

from deploy_helpers import Server, connect_sefa, port_is_free, validation_windows, wait_for
from sefa_data.errors import SefaInputError
from sefa_deploy.backends import load_backend
from sefa_deploy.client import PolicyClient, PolicyServerError, pack, unpack
from sefa_model.policy.artifact import Policy


@pytest.fixture(scope="module")
def ws(deploy_workspace) -> Path:
    return deploy_workspace


@pytest.fixture(scope="module")
def server(deploy_exports):
    """The one-step policy's TorchScript export, served for the protocol tests."""
    s = Server(deploy_exports("one-step", "torchscript"), "--max-message-mb", "1")
    yield s
    code, _, err = s.stop(signal.SIGINT)
    assert code == 0, err[-2000:]
    assert "Traceback" not in err


@pytest.fixture(scope="module")
def windows(ws) -> dict[str, np.ndarray]:
    return validation_windows(Policy.load(ws / "distill"), ws / "dataset.zarr", 10)


def noise_for(batch: int | None, seed: int) -> np.ndarray:
    shape = (16, 2) if batch is None else (batch, 16, 2)
    return np.random.default_rng(seed).standard_normal(shape, dtype=np.float32)


def expected(ws: Path, obs: dict, noise: np.ndarray, checkpoint: str = "distill", **kw) -> np.ndarray:
    out = Policy.load(ws / checkpoint).predict_action(obs, noise=torch.from_numpy(noise), **kw)
    return out.action.numpy()


def test_infer_answers_what_the_policy_answers(ws, server, windows):
    with PolicyClient(server.url) as client:
        one = {k: v[3] for k, v in windows.items()}  # (To, ...): one observation history
        noise = noise_for(None, 0)
        reply = client.infer(one, noise=noise)
        assert reply["action"].shape == (8, 2) and reply["action_pred"].shape == (16, 2)
        want = expected(ws, {k: v[None] for k, v in one.items()}, noise[None])[0]
        np.testing.assert_allclose(reply["action"], want, atol=1e-3)
        assert reply["infer_ms"] > 0
        batch = client.infer(windows, noise=noise_for(10, 1))  # (B, To, ...): a batch
        np.testing.assert_allclose(batch["action"], expected(ws, windows, noise_for(10, 1)), atol=1e-3)
        # float64 observations (numpy's default) are accepted and cast
        as64 = client.infer({k: v.astype(np.float64) for k, v in one.items()}, noise=noise)
        np.testing.assert_allclose(as64["action"], reply["action"], atol=1e-4)
        # without a noise the server draws one: a fresh sample each call
        a, b = client.infer(one)["action"], client.infer(one)["action"]
        assert a.shape == (8, 2) and np.abs(a - b).max() > 1e-3


def test_the_client_file_alone_drives_a_robot_loop(server, windows, tmp_path):
    """client.py copied next to a robot script, in an interpreter that cannot import torch or
    any sefa module: numpy, msgpack and websockets are all it needs."""
    import shutil
    import subprocess
    import sys
    import textwrap

    shutil.copy(Path(__file__).resolve().parents[2] / "sefa_deploy" / "client.py", tmp_path)
    np.savez(tmp_path / "obs.npz", **{k: v[0] for k, v in windows.items()})
    (tmp_path / "robot.py").write_text(textwrap.dedent(f"""
        import sys
        class Blocker:
            def find_spec(self, name, path=None, target=None):
                top = name.split(".")[0]
                if top == "torch" or top.startswith("sefa") or top in ("cli", "pipelines"):
                    raise ImportError("blocked: " + name)
        sys.meta_path.insert(0, Blocker())
        sys.path.insert(0, {str(tmp_path)!r})
        import numpy as np
        from client import PolicyClient
        obs = dict(np.load("obs.npz"))
        with PolicyClient({server.url!r}) as policy:
            n = policy.metadata()["n_action_steps"]
            chunk = policy.infer(obs)["action"]
            policy.reset()
            steps = [policy.step({{k: v[-1] for k, v in obs.items()}}) for _ in range(n + 1)]
        print(chunk.shape, len(steps), steps[0].shape, "torch" in sys.modules)
    """))
    r = subprocess.run([sys.executable, "-I", str(tmp_path / "robot.py")], cwd=tmp_path,
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr[-3000:]
    assert r.stdout.split() == ["(8,", "2)", "9", "(2,)", "False"]


def test_metadata_and_health(server):
    with PolicyClient(server.url) as client:
        meta = client.metadata()
        assert meta["format"] == "torchscript" and meta["kind"] == "sefa_one_step"
        assert meta["inputs"] == ["keypoint", "state", "noise"] and meta["fps"] == 10.0
        assert meta["execute"] == {"start": 1, "stop": 9}
        health = client.health()
        assert health["status"] == "ok" and health["backend"] == "torchscript"
        assert health["device"] == "cpu" and health["clients"] >= 1 and health["uptime_s"] > 0
        reply = client.request({"type": "health", "id": "robot-7"})
        assert reply["id"] == "robot-7"  # request ids are echoed, strings too


def test_receding_horizon_steps_through_the_chunk(ws, server, windows):
    frames = [{k: v[i, -1] for k, v in windows.items()} for i in range(10)]
    noise = noise_for(None, 5)
    with PolicyClient(server.url) as client:
        client.reset()
        got = [client.step(f, noise=noise) for f in frames[:9]]
        # the first chunk: predicted from frame 0 repeated (the episode's start), 8 steps of it
        first = {k: np.stack([frames[0][k]] * 2)[None] for k in windows}
        np.testing.assert_allclose(np.stack(got[:8]), expected(ws, first, noise[None])[0], atol=1e-3)
        # step 9 replans from the last two frames seen
        second = {k: np.stack([frames[7][k], frames[8][k]])[None] for k in windows}
        np.testing.assert_allclose(got[8], expected(ws, second, noise[None])[0, 0], atol=1e-3)
        reply = client.request({"type": "step", "obs": frames[9]})
        assert not reply["replanned"] and reply["queued"] == 6
        client.reset()  # a new episode: the next step plans again
        assert client.request({"type": "step", "obs": frames[0]})["replanned"]


def test_ensemble_execution_averages_the_overlapping_chunks(ws, deploy_exports, windows):
    """`sefa serve --execution ensemble`: every step predicts, and step t's action is the mean
    (k = 0) of the predictions made at steps <= t that cover it, each from its own frames."""
    s = Server(deploy_exports("one-step", "torchscript"), "--execution", "ensemble",
               "--ensemble-k", "0")
    try:
        frames = [{k: v[i, -1] for k, v in windows.items()} for i in range(3)]
        noise = noise_for(None, 5)
        with PolicyClient(s.url) as client:
            replies = [client.request({"type": "step", "obs": f, "noise": noise}) for f in frames]
            health = client.health()
        seen = [[0, 0], [0, 1], [1, 2]]  # the two frames each step's prediction sees
        chunks = [expected(ws, {k: np.stack([frames[a][k], frames[b][k]])[None] for k in windows},
                           noise[None])[0] for a, b in seen]
        for t, reply in enumerate(replies):
            want = np.mean([chunks[j][t - j] for j in range(t + 1)], axis=0)
            np.testing.assert_allclose(reply["action"], want, atol=1e-3)
            assert reply["replanned"] and reply["queued"] == t + 1 and reply["step_ms"] > 0
        assert health["execution"] == "ensemble" and health["steps"] == 3
        assert health["step_jitter_ms"] >= 0 and health["step_ms_p99"] >= health["step_ms_p50"]
    finally:
        assert s.stop(signal.SIGINT)[0] == 0


def test_a_replan_every_longer_than_the_chunk_is_one_line(deploy_exports):
    from deploy_helpers import sefa

    r = sefa("serve", deploy_exports("one-step", "torchscript"), "--replan-every", "9",
             check=False)
    assert r.returncode == 1 and r.stderr == ("error: --replan-every: 9 is outside 1..8 (the "
                                              "policy predicts n_action_steps = 8 actions a "
                                              "chunk)\n")


def bad(client: PolicyClient, message: dict) -> str:
    with pytest.raises(PolicyServerError) as e:
        client.request(message)
    return str(e.value)


def test_bad_requests_get_an_error_naming_the_problem_and_the_server_keeps_serving(server, windows):
    obs = {k: v[0] for k, v in windows.items()}
    with PolicyClient(server.url) as client:
        assert "observation 'state' missing (the policy needs: keypoint, state)" in bad(
            client, {"type": "infer", "obs": {"keypoint": obs["keypoint"]}})
        assert "unexpected observation 'gripper'" in bad(
            client, {"type": "infer", "obs": {**obs, "gripper": np.zeros(1)}})
        assert "observation 'keypoint': shape (3, 9, 2), expected (2, 9, 2)" in bad(
            client, {"type": "infer", "obs": {**obs, "keypoint": np.zeros((3, 9, 2))}})
        assert "observation 'state': dtype int64, expected a float type" in bad(
            client, {"type": "infer", "obs": {**obs, "state": np.zeros((2, 5), np.int64)}})
        nan = obs["state"].copy()
        nan[1, 0] = np.nan
        assert "observation 'state': contains NaN or Inf" in bad(
            client, {"type": "infer", "obs": {**obs, "state": nan}})
        assert "noise: shape (16, 3)" in bad(
            client, {"type": "infer", "obs": obs, "noise": np.zeros((16, 3), np.float32)})
        assert "disagree on the batch axis" in bad(
            client, {"type": "infer", "obs": {**obs, "state": obs["state"][None]}})
        assert "'obs' must be a map" in bad(client, {"type": "infer", "obs": [1, 2]})
        assert "unknown request type 'fly'" in bad(client, {"type": "fly"})
        assert "a step takes the newest frame only" in bad(client, {"type": "step", "obs": obs})
        # not msgpack, a text frame, a malformed array, from another websocket library: errors
        # too, and the connection stays open
        with connect_sefa(server.url) as raw:
            raw.send(b"\xc1\xff not msgpack")
            reply = unpack(raw.recv(timeout=10))
            assert not reply["ok"] and "not a msgpack message" in reply["error"]
            raw.send("a text message")
            assert "text message" in unpack(raw.recv(timeout=10))["error"]
            raw.send(msgpack.packb({"type": "infer", "id": 3, "obs": {"state": {
                b"__ndarray__": True, b"dtype": "<f4", b"shape": [1000], b"data": b"\0" * 8}}}))
            reply = unpack(raw.recv(timeout=10))
            assert reply["id"] is None and "malformed array" in reply["error"]
            # str marker keys (protocol 1) are not openpi's encoding: a map, not an array
            v1 = {k: {"__ndarray__": True, "dtype": v.dtype.str, "shape": list(v.shape),
                      "data": v.tobytes()} for k, v in obs.items()}
            raw.send(msgpack.packb({"type": "infer", "id": 5, "obs": v1}))
            reply = unpack(raw.recv(timeout=10))
            assert "observation 'keypoint': expected an array, got dict" in reply["error"]
            raw.send(pack({"type": "health", "id": 4}))
            assert unpack(raw.recv(timeout=10))["ok"]
        assert client.infer(obs)["action"].shape == (8, 2)  # still serving this client
        assert client.health()["errors"] >= 14


def test_oversized_message_is_refused_and_others_are_served(server, windows):
    obs = {k: v[0] for k, v in windows.items()}
    huge = {"type": "infer", "id": 1, "obs": {**obs, "state": np.zeros((300_000,), np.float32)}}
    with PolicyClient(server.url) as other:
        # the server cannot answer what it will not read: it closes with 1009 and the reason
        with connect_sefa(server.url) as raw:
            raw.send(pack(huge))  # 1.2 MB against --max-message-mb 1
            with pytest.raises(ConnectionClosed) as closed:
                raw.recv(timeout=10)
        assert closed.value.rcvd.code == 1009
        assert "exceeds limit of 1048576 bytes" in closed.value.rcvd.reason
        # the package's client knows the limit from the metadata call and says so itself
        assert "exceeds the server's limit of 1048576 bytes" in bad(other, huge)
        assert other.infer(obs)["action"].shape == (8, 2)
    with PolicyClient(server.url) as again:
        assert again.health()["status"] == "ok"


def test_two_clients_at_once_each_get_their_own_answers(ws, server, windows):
    one = {k: v[None, 2] for k, v in windows.items()}
    noises = [noise_for(1, 100 + i) for i in range(40)]
    want = {i: expected(ws, one, n) for i, n in enumerate(noises)}
    errors, done = [], []

    def robot(offset: int):
        try:
            with PolicyClient(server.url) as client:
                for i in range(offset, 40, 2):
                    reply = client.infer(one, noise=noises[i])
                    np.testing.assert_allclose(reply["action"], want[i], atol=1e-3)
                    done.append(i)
        except Exception as e:  # reported below: a thread's assertion would be lost
            errors.append(repr(e))

    threads = [threading.Thread(target=robot, args=(k,)) for k in (0, 1)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    assert errors == [] and sorted(done) == list(range(40))


def stop_and_check(server: Server, sig: int, client: PolicyClient) -> None:
    """A clean shutdown: exit 0, no traceback, the connected client told, the port free."""
    code, out, err = server.stop(sig)
    assert code == 0, err[-2000:]
    assert "Traceback" not in err and f"{signal.Signals(sig).name}: closing" in out
    with pytest.raises(PolicyServerError, match="closed"):
        client.health()
    assert wait_for(lambda: port_is_free(server.port))


def test_a_client_vanishing_mid_request_does_not_stop_the_server_then_sigterm(ws, windows):
    """The base flow's own RK45 (hundreds of network evaluations) keeps the server busy; a
    client closes its socket without a goodbye while its request is in flight, and the server
    answers the next client. SIGTERM then shuts it down cleanly with a client connected."""
    server = Server(ws / "flow")
    try:
        with connect_sefa(server.url) as raw:
            raw.send(pack({"type": "infer", "id": 1, "obs": {k: v[5] for k, v in windows.items()}}))
            time.sleep(0.01)
            raw.socket.shutdown(socket.SHUT_RDWR)  # gone, mid-request, without a goodbye
        with PolicyClient(server.url) as after:
            obs = {k: v[0] for k, v in windows.items()}
            reply = after.infer(obs, noise=noise_for(None, 3))
            want = expected(ws, {k: v[None] for k, v in obs.items()}, noise_for(None, 3)[None],
                            checkpoint="flow")
            np.testing.assert_allclose(reply["action"], want[0], atol=1e-2)
            assert after.health()["requests"] >= 2
            stop_and_check(server, signal.SIGTERM, after)
    finally:
        server.stop()


def test_serving_an_onnx_export_bad_paths_then_sigint(ws, deploy_exports, windows):
    from deploy_helpers import sefa

    server = Server(deploy_exports("euler-4", "onnx"))
    try:
        with PolicyClient(server.url) as client:
            assert client.health()["backend"] == "onnx" and client.metadata()["nfe"] == 4
            obs = {k: v[:2] for k, v in windows.items()}
            reply = client.infer(obs, noise=noise_for(2, 9))
            want = expected(ws, obs, noise_for(2, 9), checkpoint="flow", solver="euler", steps=4)
            np.testing.assert_allclose(reply["action"], want, atol=1e-3)
            r = sefa("serve", ws / "flow", "--port", str(server.port), check=False)
            assert r.returncode == 1 and "cannot listen on 127.0.0.1" in r.stderr  # port taken
            stop_and_check(server, signal.SIGINT, client)
    finally:
        server.stop()
    r = sefa("serve", ws / "nothing", "--port", "0", check=False)
    assert r.returncode == 1 and r.stderr.count("\n") == 1 and "no such checkpoint" in r.stderr
    with pytest.raises(SefaInputError, match="apply to checkpoints"):
        load_backend(deploy_exports("euler-4", "onnx"), solver="rk45")


def test_bench_time_blocks_takes_turns_in_blocks():
    from sefa_deploy.bench import time_blocks

    order = []
    seconds = time_blocks({"a": lambda: order.append("a"), "b": lambda: order.append("b")},
                          calls=4, block=2, warmup=1, max_seconds=10)
    assert order == ["a", "b"] + ["a", "a", "b", "b"] * 2  # warm-up, then blocks in turn
    assert len(seconds["a"]) == len(seconds["b"]) == 4 and (seconds["a"] >= 0).all()


def test_bench_time_blocks_takes_a_self_timed_client_in_turn():
    # the openpi client's row: a child process makes n calls and reports their times itself
    from sefa_deploy.bench import time_blocks

    order = []

    def other_process(n):
        order.append(("c", n))
        return [0.5] * n

    seconds = time_blocks({"a": lambda: order.append("a")}, calls=4, block=2, warmup=1,
                          max_seconds=10, block_fns={"c": other_process})
    assert order == ["a", ("c", 1)] + ["a", "a", ("c", 2)] * 2
    assert seconds["c"].tolist() == [0.5] * 4 and len(seconds["a"]) == 4


def test_serve_says_at_startup_which_executions_fit_the_control_period(ws, deploy_exports):
    """Before the port opens the server times a few decisions and says, at the control rate
    (--fps, else the policy's), which executions fit its period; a served execution that does
    not is a warning. With --json it is in the first line; with --no-timing, nothing runs."""
    from sefa_deploy.timing import example_request, served_decisions
    from sefa_model.policy.execution import ExecutionSettings

    backend = load_backend(ws / "distill", device="cpu")
    obs, noise = example_request(backend.metadata, 3)
    assert obs["keypoint"].shape == (3, 2, 9, 2) and noise.shape == (3, 16, 2)
    t = served_decisions(backend, ExecutionSettings("coherent", 1, 4).resolved(8), 1e6)
    assert t["served"]["execution"] == "coherent K=1 N=4" and t["served"]["fits"] is False
    assert {e["execution"] for e in t["executions"]} >= {"receding K=8", "ensemble K=1"}
    assert t["lines"][0].startswith("this policy at 1e+06 Hz (0.001 ms a step): no execution fits")
    s = Server(deploy_exports("one-step", "torchscript"), "--fps", "1000000")
    try:
        timing = s.ready["timing"]
        assert timing["fps"] == 1e6 and timing["fits"] == [] and timing["served_fits"] is False
        assert "receding K=8" in timing["over_period"] and timing["decision_ms"] > 0
        assert any(line.startswith("warning: step requests run receding K=8, whose worst step")
                   for line in timing["lines"])
    finally:
        assert s.stop()[0] == 0
    s = Server(deploy_exports("one-step", "torchscript"), "--no-timing")
    try:
        assert s.ready["timing"] is None
    finally:
        assert s.stop()[0] == 0

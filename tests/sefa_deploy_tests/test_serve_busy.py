"""Issue 23, the server: slow work cannot stall `sefa serve`, and what a policy answers is checked
before it reaches a robot. The faults are injected (tests/serve_with_fault.py) into a real
`sefa serve` process: a policy held inside its call until the test releases it, and a policy
that answers NaN. Nothing rests on timing luck: the policy is held for as long as the test
needs, and "answered while it runs" means within FAST_S."""

from __future__ import annotations

import json
import signal
import time
from pathlib import Path

import numpy as np
import pytest
from websockets.exceptions import ConnectionClosed

from deploy_helpers import REPO, Server, connect_sefa, sefa, wait_for
from sefa_deploy.client import PolicyClient, PolicyServerError, pack, unpack
from sefa_deploy.metadata import load_metadata
from sefa_deploy.server import SHUTDOWN_GRACE_S, PolicyOutputError, check_output

FAST_S = 1.0
# the stop's bound, and what an interpreter takes to flush and leave after it
EXIT_BOUND_S = SHUTDOWN_GRACE_S + 3.0


@pytest.fixture(scope="module")
def export(deploy_exports) -> Path:
    return deploy_exports("one-step", "torchscript")


@pytest.fixture(scope="module")
def obs(export) -> dict[str, np.ndarray]:
    """One observation history of the policy's shape (the values do not matter here)."""
    return {k: np.zeros(spec["shape"], np.float32) for k, spec in load_metadata(export)["obs"].items()}


def started(control: Path) -> int:
    """How many policy calls have begun."""
    path = control / "started"
    return len(path.read_text().splitlines()) if path.exists() else 0


def answered_at_once(fn):
    start = time.monotonic()
    out = fn()
    assert time.monotonic() - start < FAST_S, "answered only after the policy's call"
    return out


def test_a_held_policy_stalls_nothing_and_sigterm_exits_within_the_bound(export, obs, tmp_path):
    server = Server(export, "--max-queue", "1", "--request-timeout", "4", fault=f"hold:{tmp_path}")
    try:
        with connect_sefa(server.url) as held, connect_sefa(server.url) as waiting, \
                connect_sefa(server.url) as over:
            sent = time.monotonic()
            held.send(pack({"type": "infer", "id": 1, "obs": obs}))
            assert wait_for(lambda: started(tmp_path) == 1, 30)
            # a new client: handshake, metadata and health, each answered while the policy runs
            client = answered_at_once(lambda: PolicyClient(server.url, timeout=FAST_S))
            with client:
                assert answered_at_once(client.health)["status"] == "ok"
                assert answered_at_once(client.metadata)["kind"] == "sefa_one_step"
            # the queue: one request may wait (--max-queue 1), the next is refused at once
            waiting.send(pack({"type": "infer", "id": 2, "obs": obs}))
            over.send(pack({"type": "infer", "id": 3, "obs": obs}))
            busy = answered_at_once(lambda: unpack(over.recv(timeout=FAST_S)))
            assert not busy["ok"] and busy["error"] == (
                "server busy: the policy is running a request and 1 more wait for it "
                "(serve --max-queue 1); retry later")
            # standard websocket keepalive: the pings are answered, the client is not dropped
            with connect_sefa(server.url, ping_interval=0.1, ping_timeout=FAST_S) as keepalive:
                time.sleep(1.0)
                keepalive.send(pack({"type": "health", "id": 4}))
                assert unpack(keepalive.recv(timeout=FAST_S))["ok"]
            # the held request and the one behind it: an error reply at --request-timeout
            for ws in (held, waiting):
                reply = unpack(ws.recv(timeout=10))
                assert not reply["ok"] and "no answer within 4 s (serve --request-timeout" in reply["error"]
            assert 3.5 < time.monotonic() - sent < 9
            assert started(tmp_path) == 1  # the request that waited never ran
            # SIGTERM with the policy still held: the process leaves within the stated bound
            signalled = time.monotonic()
            code, out, err = server.stop(signal.SIGTERM, timeout=30)
            assert time.monotonic() - signalled < EXIT_BOUND_S
    finally:
        (tmp_path / "release").touch()
        code, out, err = server.stop()
    assert code == 0 and "Traceback" not in err, err[-2000:]
    logs = [json.loads(line).get("log") for line in out.splitlines()]
    assert "SIGTERM: closing connections" in logs and "stopped" in logs
    assert f"a request still running after {SHUTDOWN_GRACE_S:g} s is abandoned" in logs


def test_sigterm_lets_the_running_request_finish_within_the_grace(export, obs, tmp_path):
    """...and the request waiting behind it is answered with an error, not run."""
    server = Server(export, fault=f"hold:{tmp_path}")
    try:
        with connect_sefa(server.url) as ws, connect_sefa(server.url) as waiting:
            ws.send(pack({"type": "infer", "id": 1, "obs": obs}))
            assert wait_for(lambda: started(tmp_path) == 1, 30)
            waiting.send(pack({"type": "infer", "id": 2, "obs": obs}))
            time.sleep(0.3)  # queued by then, most likely; arriving after the signal, it gets
            server.proc.send_signal(signal.SIGTERM)  # the same reply
            refused = unpack(waiting.recv(timeout=FAST_S))
            assert refused == {"id": 2, "ok": False,
                               "error": "the server is stopping; request not run"}
            (tmp_path / "release").touch()
            reply = unpack(ws.recv(timeout=10))  # answered before the connection closes
            assert reply["ok"] and reply["action"].shape == (8, 2)
            with pytest.raises(ConnectionClosed) as closed:
                ws.recv(timeout=10)
            assert closed.value.rcvd.code == 1001
        server.proc.wait(10)  # already signalled: stop() only collects
        code, out, err = server.stop()
    finally:
        (tmp_path / "release").touch()
        server.stop()
    assert code == 0 and "Traceback" not in err, err[-2000:]
    assert "abandoned" not in out and started(tmp_path) == 1


def test_a_second_signal_ends_the_wait_at_once(export, obs, tmp_path):
    server = Server(export, fault=f"hold:{tmp_path}")
    try:
        with connect_sefa(server.url) as ws:
            ws.send(pack({"type": "infer", "id": 1, "obs": obs}))
            assert wait_for(lambda: started(tmp_path) == 1, 30)
            server.proc.send_signal(signal.SIGTERM)
            time.sleep(0.2)
            signalled = time.monotonic()
            code, out, err = server.stop(signal.SIGINT, timeout=30)
            assert time.monotonic() - signalled < SHUTDOWN_GRACE_S
    finally:
        (tmp_path / "release").touch()
        server.stop()
    assert code == 0 and "Traceback" not in err, err[-2000:]
    assert "abandoned" in out


def test_a_policy_answering_nan_gets_an_error_never_nan(export, obs):
    server = Server(export, fault="nan")
    try:
        with PolicyClient(server.url) as client:
            for request in ({"type": "infer", "obs": obs},
                            {"type": "step", "obs": {k: v[-1] for k, v in obs.items()}}):
                with pytest.raises(PolicyServerError, match=r"the policy produced non-finite "
                                   r"actions \(NaN or Inf in 'action'\); nothing sent"):
                    client.request(request)
            health = client.health()  # still serving
            assert health["status"] == "ok" and health["errors"] == 2
    finally:
        code, out, err = server.stop()
    assert code == 0 and "Traceback" not in err, err[-2000:]
    logged = [line for line in out.splitlines() if "non-finite" in line]
    assert len(logged) == 2  # one line per refused answer


def test_check_output_refuses_wrong_shapes_and_non_finite_values(export):
    meta = load_metadata(export)
    action, chunk = np.zeros((3, 8, 2), np.float32), np.zeros((3, 16, 2), np.float32)
    check_output(action, chunk, meta, 3)
    bad_chunk = chunk.copy()
    bad_chunk[2, 15, 1] = np.inf
    cases = [((action, bad_chunk, 3), "NaN or Inf in 'action_pred'"),
             ((action * np.nan, chunk, 3), "NaN or Inf in 'action'"),
             ((action, chunk, 2), "'action' of shape (3, 8, 2), expected (2, 8, 2)"),
             ((action, chunk[:, :8], 3), "'action_pred' of shape (3, 8, 2), expected (3, 16, 2)"),
             ((None, chunk, 3), "'action' of shape NoneType")]
    for (a, c, b), message in cases:
        with pytest.raises(PolicyOutputError) as e:
            check_output(a, c, meta, b)
        assert message in str(e.value)


BAD_OPTIONS = [  # the ranges are pipelines/options.py's
    (["--max-message-mb", "nan"], "--max-message-mb: nan is not a finite number (valid: a finite number > 0)"),
    (["--max-message-mb", "0"], "--max-message-mb: 0 is too small (valid: a finite number > 0)"),
    (["--steps", "0"], "--steps: 0 is too small (valid: an integer in [1, 100000])"),
    (["--port", "99999"], "--port: 99999 is too large (valid: an integer in [0, 65535])"),
    (["--port", "-1"], "--port: -1 is too small"),
    (["--max-queue", "-1"], "--max-queue: -1 is too small (valid: an integer >= 0)"),
    (["--request-timeout", "inf"], "--request-timeout: inf is not a finite number"),
    (["--request-timeout", "0"], "--request-timeout: 0 is too small"),
    (["--seed", "-1"], "--seed: -1 is too small"),
    # the execution's settings (sefa_model/policy/execution.py checks them)
    (["--execution", "act"], "--execution: not one of receding, ensemble, coherent, bid: 'act'"),
    (["--execution", "ensemble", "--ensemble-k", "-0.5"],
     "--ensemble-k: -0.5 is too small (valid: a finite number >= 0)"),
    (["--execution", "ensemble", "--ensemble-k", "nan"], "--ensemble-k: nan is not a finite number"),
    (["--replan-every", "0"], "--replan-every: 0 is too small"),
    (["--samples", "4"], "--samples: 4 samples need the coherent or bid mode"),
    (["--execution", "bid"], "--weak: bid contrasts against a weaker policy"),
]


@pytest.mark.parametrize("args,line", BAD_OPTIONS, ids=[" ".join(a) for a, _ in BAD_OPTIONS])
def test_bad_serve_options_are_one_line_before_any_work(args, line, monkeypatch, capsys):
    """In-process through sefa_cli.main.main (the CLI's error path); the policy path does not
    exist, so an option checked only after loading would report that instead."""
    from sefa_cli.main import main

    monkeypatch.setattr("sys.argv", ["sefa", "serve", "no-such-policy", *args])
    with pytest.raises(SystemExit) as e:
        main()
    err = capsys.readouterr().err
    assert e.value.code == 1 and err.count("\n") == 1 and "Traceback" not in err
    assert err.startswith(f"error: {line}")


def test_bad_serve_option_in_a_real_process():
    r = sefa("serve", REPO / "no-such-policy", "--max-message-mb", "nan", check=False)
    assert r.returncode == 1 and r.stderr == ("error: --max-message-mb: nan is not a finite "
                                              "number (valid: a finite number > 0)\n")


# ---- the worker itself, in-process (issue 24 replaced its thread pool with a thread of its own)

def test_worker_keeps_order_queue_limit_timeouts_and_stop():
    import asyncio
    import threading

    from sefa_deploy.server import RequestError, Worker

    release, ran = threading.Event(), []

    def held(name):
        ran.append(name)
        assert release.wait(10)
        return name

    async def scenario():
        worker = Worker(max_queue=1, timeout_s=0.3)
        first = asyncio.ensure_future(worker.run(held, "first"))
        await asyncio.sleep(0.05)
        waiting = asyncio.ensure_future(worker.run(held, "waiting"))
        await asyncio.sleep(0)
        with pytest.raises(RequestError, match="server busy"):  # one running, one waiting
            await worker.run(held, "over")
        # the waiting request times out: it never runs and its place is free at once
        with pytest.raises(RequestError, match="no answer within 0.3 s"):
            await waiting
        assert worker.pending == 1
        with pytest.raises(RequestError, match="no answer within"):  # the running one too
            await first
        assert worker.pending == 1  # it runs on, and still holds the policy
        worker.timeout_s, worker.max_queue = 10, 4
        later = asyncio.ensure_future(worker.run(held, "later"))
        queued = asyncio.ensure_future(worker.run(held, "queued"))
        await asyncio.sleep(0.05)
        release.set()  # "first" returns (its result dropped), then "later" runs
        assert await later == "later"
        assert await queued == "queued"
        # the policy's own TimeoutError is its failure, not the request's timeout
        def slow_io():
            raise TimeoutError("camera read timed out")
        with pytest.raises(TimeoutError, match="camera read"):
            await worker.run(slow_io)
        release.clear()
        running = asyncio.ensure_future(worker.run(held, "at stop"))
        behind = asyncio.ensure_future(worker.run(held, "behind"))
        await asyncio.sleep(0.05)
        left = await worker.stop(0.1, asyncio.sleep(10))
        assert left == 1  # the held call is abandoned
        with pytest.raises(RequestError, match="stopping; request not run"):
            await behind
        with pytest.raises(RequestError, match="stopped before the policy answered"):
            await running
        with pytest.raises(RequestError, match="stopping"):
            await worker.run(held, "after")
        release.set()

    asyncio.run(scenario())
    assert ran == ["first", "later", "queued", "at stop"]

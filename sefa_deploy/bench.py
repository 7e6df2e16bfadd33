"""What serving and exporting cost, measured in one run (benchmarks/bench_serve.py).

* **Server round trip**: `PolicyClient.infer` against `sefa serve` in another process over
  loopback, next to `Policy.predict_action` in this process on the same observation and noise,
  the two taking turns in blocks of calls (`time_blocks`), for the one-step policy
  and for the base flow with its own RK45. Their p50 difference is what the server adds:
  message packing, the websocket round trip, the request checks. For the one-step policy the
  unmodified openpi client (its own venv, a child process timing its own calls:
  benchmarks/openpi_bench_client.py) takes its turns on the same server (openpi's protocol).
* **Where the served call's time goes** (`bench_phases`): the one-step policy served by a
  process whose functions (decode, checks, the policy call, encode) are wrapped with
  perf_counter_ns marks, and a client that marks its encode, send, receive and decode; the
  clock is CLOCK_MONOTONIC, one for both processes, so the wire and the thread hand-offs are
  phases too. The server's own code is the code `sefa serve` runs; only the wrappers are added.
* **Exported artifacts**: the one-step policy's ONNX file in onnxruntime and its TorchScript
  file, next to the same computation in eager PyTorch (the `ExportedPolicy` module the artifacts
  were traced from, same inputs) and next to `predict_action`, in turns likewise.
* **The server's own work around the call**: the one-step policy's call (the checkpoint backend
  `sefa serve` runs) awaited on an event loop inline, and through the server's `Worker` (the
  thread hand-off every request pays so that a slow call cannot stall the loop); and
  `check_output` (shapes, finite values: what the server does to every answer before sending
  it) on that call's answer; in turns likewise.
* **Load**: several clients, each in its own thread with its own connection, send a fixed number
  of requests as fast as they get answers; every reply is checked, and the run stops by itself.

Servers run as child processes on 127.0.0.1 with a port the OS picks, and are stopped with
SIGTERM at the end. The observation is a real validation window when a store is given.
"""

from __future__ import annotations

import multiprocessing
import os
import tempfile
import threading
import time
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from sefa_model.eval.latency import example_observation, percentiles_ms, time_calls
from sefa_model.policy.artifact import Policy


def _serve_child(path: str, solver: str | None, steps: int | None, conn) -> None:
    """A child process: load, serve on a free loopback port, report the port through `conn`."""
    from sefa_deploy.backends import load_backend
    from sefa_deploy.server import serve

    torch.set_num_threads(torch.get_num_threads())
    backend = load_backend(path, device="cpu", solver=solver, steps=steps)
    serve(backend, "127.0.0.1", 0, log=lambda _: None, on_ready=lambda h, p: conn.send(p))


class ServerProcess:
    """`serve()` in a spawned child process on a free loopback port, stopped by SIGTERM."""

    def __init__(self, path: Path, solver: str | None = None, steps: int | None = None):
        ctx = multiprocessing.get_context("spawn")  # a fresh interpreter, as `sefa serve` is
        parent, child = ctx.Pipe()
        self.proc = ctx.Process(target=_serve_child, args=(str(path), solver, steps, child),
                                daemon=True)
        self.proc.start()
        deadline = time.monotonic() + 120
        while not parent.poll(0.1):
            if not self.proc.is_alive() or time.monotonic() > deadline:
                self.proc.kill()
                raise RuntimeError(f"the server for {path} did not start (exit code "
                                   f"{self.proc.exitcode})")
        self.url = f"ws://127.0.0.1:{parent.recv()}"

    def stop(self) -> int:
        self.proc.terminate()  # SIGTERM: the server's clean shutdown
        self.proc.join(30)
        return self.proc.exitcode

    def __enter__(self) -> "ServerProcess":
        return self

    def __exit__(self, *exc) -> None:
        self.stop()


def time_blocks(fns: dict[str, Callable[[], object]], *, calls: int, block: int, warmup: int,
                max_seconds: float,
                block_fns: dict[str, Callable[[int], list[float]]] | None = None
                ) -> dict[str, np.ndarray]:
    """Seconds per call of each function, taking turns block by block (`block` calls of one,
    then of the next): load changes on the machine hit all alike, and a function that leaves
    threads spinning (torch's OpenMP pool after predict_action) does not slow the next one's
    calls but the first of its block, as it would not in a robot's process either.
    `block_fns` take their turn likewise but time themselves: fn(n) makes n calls and returns
    their times (a client in another process)."""
    timed = {name: (lambda n, fn=fn: _timed(fn, n)) for name, fn in fns.items()}
    timed.update(block_fns or {})
    for fn in timed.values():
        fn(warmup)
    out: dict[str, list[float]] = {name: [] for name in timed}
    first = next(iter(timed))
    end = time.perf_counter() + max_seconds
    while len(out[first]) < calls:
        for name, fn in timed.items():
            out[name].extend(fn(block))
        if time.perf_counter() > end and len(out[first]) >= min(calls, 20):
            break
    return {name: np.asarray(v) for name, v in out.items()}


def _timed(fn: Callable[[], object], n: int) -> list[float]:
    out = []
    for _ in range(n):
        start = time.perf_counter()
        fn()
        out.append(time.perf_counter() - start)
    return out


class OpenpiClientProcess:
    """The unmodified openpi client (its own venv's `python`) timing its calls against a
    server, driven block by block through its stdin (benchmarks/openpi_bench_client.py)."""

    SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "openpi_bench_client.py"

    def __init__(self, python: str, url: str, obs: dict, noise: np.ndarray, work: Path):
        import json
        import subprocess

        host, _, port = url.removeprefix("ws://").rpartition(":")
        np.savez(work / "openpi_obs.npz", **obs, noise=noise)
        self.proc = subprocess.Popen([python, str(self.SCRIPT), host, port,
                                      str(work / "openpi_obs.npz")],
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        line = self.proc.stdout.readline()
        if not line:
            self.proc.kill()
            raise RuntimeError(f"the openpi client ({python}) did not start")
        self.actions = np.asarray(json.loads(line)["actions"], np.float32)

    def __call__(self, n: int) -> list[float]:
        import json

        self.proc.stdin.write(f"{n}\n")
        self.proc.stdin.flush()
        return json.loads(self.proc.stdout.readline())

    def close(self) -> None:
        self.proc.stdin.close()
        self.proc.wait(30)


def _row(name: str, seconds: np.ndarray, **extra) -> dict:
    p50, p90, p99 = percentiles_ms(seconds)
    return {"name": name, "calls": len(seconds), "p50_ms": p50, "p90_ms": p90, "p99_ms": p99,
            **extra}


def bench_round_trip(policy_path: Path, *, solver: str | None, steps: int | None, obs: dict,
                     noise: np.ndarray, calls: int, warmup: int, max_seconds: float,
                     label: str, served_path: Path | None = None,
                     openpi_python: str | None = None) -> dict:
    """`served_path` (default: the checkpoint itself) is what the server loads, e.g. an export
    of the checkpoint. With `openpi_python` (the openpi client venv's interpreter) the
    unmodified openpi client calls the same server too, in turns with the others."""
    from sefa_deploy.client import PolicyClient

    policy = Policy.load(policy_path)
    batched = {k: v[None] for k, v in obs.items()}
    noise_t = torch.from_numpy(noise[None])
    nfe = policy.predict_action(batched, solver=solver, steps=steps, noise=noise_t).nfe
    with ServerProcess(served_path or policy_path, solver, steps) as server, \
            PolicyClient(server.url) as client, tempfile.TemporaryDirectory() as tmp:
        served = client.infer(obs, noise=noise)["action"]
        local = policy.predict_action(batched, solver=solver, steps=steps, noise=noise_t).action[0]
        inside: list[float] = []  # the server's own timing of its backend call, per request

        def remote():
            inside.append(client.infer(obs, noise=noise)["infer_ms"] / 1e3)

        openpi = (OpenpiClientProcess(openpi_python, server.url, obs, noise, Path(tmp))
                  if openpi_python else None)
        try:
            times = time_blocks({
                "in-process": lambda: policy.predict_action(batched, solver=solver, steps=steps,
                                                            noise=noise_t),
                "served": remote,
                "health": client.health},
                calls=calls, block=min(50, max(1, calls // 10)), warmup=warmup,
                max_seconds=max_seconds, block_fns={"openpi": openpi} if openpi else None)
        finally:
            if openpi:
                openpi.close()
    inside_t = np.asarray(inside[-len(times["served"]):])
    rows = [_row(f"{label}: predict_action in-process", times["in-process"], nfe=nfe),
            _row(f"{label}: served{' ' + served_path.name if served_path else ''}, loopback "
                 "round trip", times["served"], nfe=nfe),
            _row(f"{label}:   of which predict_action in the server", inside_t, nfe=nfe),
            _row(f"{label}:   of which outside it (wire, checks)", times["served"] - inside_t,
                 nfe=nfe),
            _row(f"{label}: a health call's round trip (no model)", times["health"], nfe=0)]
    out = {"label": label, "nfe": nfe, "rows": rows,
           "added_p50_ms": rows[1]["p50_ms"] - rows[0]["p50_ms"],
           "max_abs_diff": float(np.abs(served - local.cpu().numpy()).max())}
    if openpi:
        row = _row(f"{label}: served, openpi-client 0.1.2, loopback round trip", times["openpi"],
                   nfe=nfe)
        rows.insert(2, row)
        out["openpi_added_p50_ms"] = row["p50_ms"] - rows[0]["p50_ms"]
        out["openpi_max_abs_diff"] = float(np.abs(openpi.actions - local.cpu().numpy()).max())
    for row in rows:
        row["x_in_process"] = row["p50_ms"] / rows[0]["p50_ms"]
    return out


def bench_exports(policy_path: Path, export_dirs: dict[str, Path], *, obs: dict,
                  noise: np.ndarray, calls: int, warmup: int, max_seconds: float) -> dict:
    from sefa_deploy.backends import OnnxBackend, TorchScriptBackend
    from sefa_deploy.export import ExportedPolicy, export_solver
    from sefa_deploy.metadata import load_metadata

    policy = Policy.load(policy_path)
    solver, steps = export_solver(policy, None, None)
    eager = ExportedPolicy(policy, solver, steps).eval()
    batched = {k: v[None].astype(np.float32) for k, v in obs.items()}
    noise_b = noise[None]
    backends = {"onnxruntime": OnnxBackend(export_dirs["onnx"], load_metadata(export_dirs["onnx"])),
                "torchscript": TorchScriptBackend(export_dirs["torchscript"],
                                                  load_metadata(export_dirs["torchscript"]))}
    keys = list(policy.cfg.shape_meta.obs)

    @torch.inference_mode()
    def run_eager():  # the same numpy in, numpy out as the backends
        action, chunk = eager(*[torch.from_numpy(batched[k]) for k in keys], torch.from_numpy(noise_b))
        return action.numpy(), chunk.numpy()

    fns = {"eager PyTorch (the traced module)": run_eager,
           **{name: (lambda b=b: b(batched, noise_b)) for name, b in backends.items()},
           "predict_action": lambda: policy.predict_action(batched, noise=torch.from_numpy(noise_b))}
    want = run_eager()[1]
    diffs = {name: float(np.abs(b(batched, noise_b)[1] - want).max()) for name, b in backends.items()}
    times = time_calls(fns, warmup=warmup, calls=calls, max_seconds=max_seconds,
                       sync=lambda: None, warmup_seconds=1.0)
    rows = [_row(name, t) for name, t in times.items()]
    eager_p50 = rows[0]["p50_ms"]
    for r in rows:
        r["x_eager"] = r["p50_ms"] / eager_p50
    return {"rows": rows, "max_abs_diff_vs_eager": diffs}


def bench_server_work(policy_path: Path, *, obs: dict, noise: np.ndarray, calls: int,
                      warmup: int, max_seconds: float) -> dict:
    import asyncio

    from sefa_deploy.backends import CheckpointBackend
    from sefa_deploy.server import Worker, check_output

    backend = CheckpointBackend(policy_path, device="cpu")
    batched = {k: v[None].astype(np.float32) for k, v in obs.items()}
    noise_b = noise[None]
    action, chunk = backend(batched, noise_b)
    loop, worker = asyncio.new_event_loop(), Worker()

    async def inline():
        return backend(batched, noise_b)

    try:
        times = time_blocks({
            "inline": lambda: loop.run_until_complete(inline()),
            "worker": lambda: loop.run_until_complete(worker.run(backend, batched, noise_b)),
            "check": lambda: check_output(action, chunk, backend.metadata, 1),
            "empty": lambda: loop.run_until_complete(worker.run(_nothing))},
            calls=calls, block=min(50, max(1, calls // 10)), warmup=warmup,
            max_seconds=max_seconds)
    finally:
        loop.run_until_complete(worker.stop(1.0, asyncio.sleep(1.0)))
        loop.close()
    rows = [_row("one-step call, inline on the event loop", times["inline"]),
            _row("the same through the server's worker thread", times["worker"]),
            _row("the output check of its answer", times["check"]),
            _row("an empty call through the worker thread (the hand-off alone)", times["empty"])]
    return {"rows": rows, "handoff_p50_ms": rows[1]["p50_ms"] - rows[0]["p50_ms"],
            "check_percent_of_call": 100 * rows[2]["p50_ms"] / rows[0]["p50_ms"]}


def _nothing() -> None:
    return None


def bench_load(policy_path: Path, *, obs: dict, clients: int, requests: int,
               timeout: float = 60.0) -> dict:
    """`clients` connections at once, `requests` each, as fast as answers come; bounded."""
    from sefa_deploy.client import PolicyClient

    latencies: list[list[float]] = [[] for _ in range(clients)]
    errors: list[str] = []
    with ServerProcess(policy_path) as server:
        start_line = threading.Barrier(clients)

        def robot(i: int) -> None:
            try:
                with PolicyClient(server.url, timeout=timeout) as client:
                    meta = client.metadata()
                    expected = (meta["n_action_steps"], meta["action_dim"])
                    start_line.wait(timeout)
                    for _ in range(requests):
                        t = time.perf_counter()
                        action = client.infer(obs)["action"]
                        latencies[i].append(time.perf_counter() - t)
                        if action.shape != expected or not np.isfinite(action).all():
                            errors.append(f"client {i}: bad action {action.shape}")
            except Exception as e:  # counted and reported, not raised: the load test goes on
                errors.append(f"client {i}: {type(e).__name__}: {e}")

        began = time.perf_counter()
        threads = [threading.Thread(target=robot, args=(i,)) for i in range(clients)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(timeout * requests)
        wall = time.perf_counter() - began
    done = np.asarray([x for per in latencies for x in per])
    p50, p90, p99 = percentiles_ms(done) if len(done) else (float("nan"),) * 3
    return {"clients": clients, "requests_per_client": requests, "answered": int(len(done)),
            "errors": errors, "p50_ms": p50, "p90_ms": p90, "p99_ms": p99,
            "requests_per_s": len(done) / wall, "seconds": wall}


def bench_serve(one_step: Path, flow: Path, *, store: Path | None = None, calls: int = 500,
                rk45_calls: int = 30, warmup: int = 50, max_seconds: float = 20.0,
                load_clients: int = 4, load_requests: int = 250,
                openpi_python: str | None = None,
                log: Callable[[str], None] = lambda _: None) -> dict:
    """Every measurement of this module in one run; returns the rows (see the docstring).
    `openpi_python`: the openpi client's venv interpreter, for the openpi protocol's row."""
    from sefa_data.bench.throughput import machine_description
    from sefa_deploy.export import export_policy

    policy = Policy.load(one_step)
    batch_obs, source = example_observation(policy, store)
    obs = {k: np.asarray(v[0]) for k, v in batch_obs.items()}
    cfg = policy.cfg
    noise = np.random.default_rng(0).standard_normal(
        (cfg.policy.horizon, cfg.shape_meta.action.shape[-1]), dtype=np.float32)
    out = {"machine": machine_description(), "observation": source, "one_step": str(one_step),
           "flow": str(flow), "load_average_start": os.getloadavg()}
    log("round trip: one-step policy (in-process, our client, " +
        ("openpi's client)" if openpi_python else "no openpi client)"))
    out["one_step_round_trip"] = bench_round_trip(one_step, solver=None, steps=None, obs=obs,
                                                  noise=noise, calls=calls, warmup=warmup,
                                                  max_seconds=max_seconds, label="one-step",
                                                  openpi_python=openpi_python)
    log("where a served one-step call's time goes (probes)")
    out["phases"] = bench_phases(one_step, obs=obs, noise=noise, calls=calls, warmup=warmup,
                                 max_seconds=max_seconds * 2)
    log("round trip: base flow, RK45")
    out["rk45_round_trip"] = bench_round_trip(flow, solver="rk45", steps=None, obs=obs,
                                              noise=noise, calls=rk45_calls, warmup=2,
                                              max_seconds=max_seconds, label="RK45")
    log("the server's work around the one-step call: the worker hand-off, the output check")
    out["server_work"] = bench_server_work(one_step, obs=obs, noise=noise, calls=calls * 2,
                                           warmup=warmup, max_seconds=max_seconds)
    with tempfile.TemporaryDirectory() as tmp:
        dirs = {}
        for fmt in ("onnx", "torchscript"):
            log(f"exporting the one-step policy: {fmt}")
            dirs[fmt] = Path(tmp) / fmt
            export_policy(one_step, dirs[fmt], fmt=fmt)
        log("exported artifacts against eager PyTorch")
        out["exports"] = bench_exports(one_step, dirs, obs=obs, noise=noise, calls=calls,
                                       warmup=warmup, max_seconds=max_seconds)
        log("round trip: the one-step policy's ONNX export served")
        out["onnx_round_trip"] = bench_round_trip(
            one_step, solver=None, steps=None, obs=obs, noise=noise, calls=calls, warmup=warmup,
            max_seconds=max_seconds, label="one-step", served_path=dirs["onnx"])
    log(f"load: {load_clients} clients x {load_requests} requests")
    out["load"] = bench_load(one_step, obs=obs, clients=load_clients, requests=load_requests)
    out["load_average_end"] = os.getloadavg()
    return out


# ---- where a served call's time goes (benchmark-only probes; the server itself is unchanged)

PHASES = (  # (name, from mark, to mark); the marks are CLOCK_MONOTONIC ns, one clock for both processes
    ("client: encode the request", "c_start", "c_packed"),
    ("client: send (websockets framing, the syscall)", "c_packed", "c_sent"),
    ("wire in: loopback, server wake-up, frame parsing", "c_sent", "s_unpack"),
    ("server: decode the request (msgpack)", "s_unpack", "s_unpacked"),
    ("server: check the request", "s_unpacked", "s_checked"),
    ("hand-off to the worker thread", "s_checked", "s_call"),
    ("the policy call (predict_action)", "s_call", "s_called"),
    ("server: check the answer (shapes, finite)", "s_called", "s_output_checked"),
    ("hand-back to the event loop", "s_output_checked", "s_pack"),
    ("server: encode the reply", "s_pack", "s_packed"),
    ("wire out: send, loopback, client wake-up", "s_packed", "c_received"),
    ("client: decode the reply", "c_received", "c_end"),
)


class _ProbedBackend:
    """The backend with a mark at the start and end of each call (on the worker thread)."""

    def __init__(self, backend, mark):
        self._backend, self._mark = backend, mark

    def __getattr__(self, name):
        return getattr(self._backend, name)

    def __call__(self, obs, noise):
        self._mark("s_call")
        try:
            return self._backend(obs, noise)
        finally:
            self._mark("s_called")


def _probe_child(path: str, records_file: str, conn) -> None:
    """A child process serving with probes: each request's marks go to `records_file` (JSON)
    when the server stops. Module functions the server calls are wrapped in place, so the
    server's own code runs as `sefa serve` runs it, plus a perf_counter_ns per mark."""
    import json

    import sefa_deploy.server as server
    from sefa_deploy.backends import load_backend

    records: list[dict] = []

    def mark(name: str) -> None:
        if records:
            records[-1][name] = time.perf_counter_ns()

    def wrap(fn, before: str | None, after: str | None, new_record: bool = False):
        def probed(*args, **kwargs):
            if new_record and len(records) < 100_000:
                records.append({})
            if before:
                mark(before)
            out = fn(*args, **kwargs)
            if after:
                mark(after)
            return out
        return probed

    unpack, pack = server.unpack, server.pack
    server.unpack = wrap(unpack, "s_unpack", "s_unpacked", new_record=True)
    server.check_infer = wrap(server.check_infer, None, "s_checked")
    server.check_output = wrap(server.check_output, None, "s_output_checked")

    def probed_pack(message):
        # the metadata and health replies are packed too: only an infer reply is marked
        if "action" in message or "actions" in message:
            mark("s_pack")
            out = pack(message)
            mark("s_packed")
            return out
        return pack(message)

    server.pack = probed_pack
    backend = _ProbedBackend(load_backend(path, device="cpu"), mark)
    server.serve(backend, "127.0.0.1", 0, log=lambda _: None, on_ready=lambda h, p: conn.send(p))
    Path(records_file).write_text(json.dumps(records))


def _probed_infer(client, obs: dict, noise: np.ndarray) -> dict:
    """PolicyClient.infer with marks around its encode, send, receive and decode."""
    from sefa_deploy.client import pack, unpack

    marks = {"c_start": time.perf_counter_ns()}
    data = pack({"type": "infer", "obs": obs, "noise": noise, "id": 0})
    marks["c_packed"] = time.perf_counter_ns()
    client._protocol.send_binary(data)
    client._flush()
    marks["c_sent"] = time.perf_counter_ns()
    raw = client._recv_message()
    marks["c_received"] = time.perf_counter_ns()
    reply = unpack(raw)
    marks["c_end"] = time.perf_counter_ns()
    if not reply.get("ok"):
        raise RuntimeError(reply.get("error"))
    return marks


def bench_phases(policy_path: Path, *, obs: dict, noise: np.ndarray, calls: int, warmup: int,
                 block: int = 25, max_seconds: float = 60.0) -> dict:
    """The one-step policy served with probes, in blocks of calls taking turns with the same
    call in-process: each phase's p50 (us), the served and in-process p50, and the p50 of the
    paired differences (the i-th served call of a block against the i-th in-process call)."""
    import json

    from sefa_deploy.client import PolicyClient

    policy = Policy.load(policy_path)
    batched = {k: v[None] for k, v in obs.items()}
    noise_t = torch.from_numpy(noise[None])
    with tempfile.TemporaryDirectory() as tmp:
        records_file = Path(tmp) / "records.json"
        ctx = multiprocessing.get_context("spawn")
        parent, child = ctx.Pipe()
        proc = ctx.Process(target=_probe_child, args=(str(policy_path), str(records_file), child),
                           daemon=True)
        proc.start()
        if not parent.poll(120):
            proc.kill()
            raise RuntimeError("the probed server did not start")
        client_marks: list[dict] = []
        local: list[float] = []
        try:
            with PolicyClient(f"ws://127.0.0.1:{parent.recv()}") as client:
                for _ in range(warmup):
                    client_marks.append(_probed_infer(client, obs, noise))
                    policy.predict_action(batched, noise=noise_t)
                end = time.perf_counter() + max_seconds
                while len(local) < calls and (time.perf_counter() < end or len(local) < 2 * block):
                    for _ in range(block):
                        client_marks.append(_probed_infer(client, obs, noise))
                    for _ in range(block):
                        t = time.perf_counter()
                        policy.predict_action(batched, noise=noise_t)
                        local.append(time.perf_counter() - t)
        finally:
            proc.terminate()
            proc.join(30)
        server_marks = json.loads(records_file.read_text())
    # the server's first records are the client's metadata request (unmarked beyond decoding)
    served = [{**s, **c} for s, c in zip([r for r in server_marks if "s_call" in r], client_marks)]
    served = served[warmup:]
    phases = []
    for name, a, b in PHASES:
        us = np.asarray([(r[b] - r[a]) / 1e3 for r in served])
        phases.append({"name": name, "p50_us": float(np.median(us)),
                       "p90_us": float(np.percentile(us, 90))})
    total = np.asarray([(r["c_end"] - r["c_start"]) / 1e9 for r in served])
    local_t = np.asarray(local)
    n = min(len(total), len(local_t))
    outside = np.asarray([(r["c_end"] - r["c_start"] - r["s_called"] + r["s_call"]) / 1e3
                          for r in served])
    return {"calls": n, "phases": phases,
            "served": _row("one-step: served (probed), loopback round trip", total),
            "in_process": _row("one-step: predict_action in-process", local_t),
            "paired_added_p50_ms": float(np.median(total[:n] - local_t[:n]) * 1e3),
            "outside_call_p50_us": float(np.median(outside)),
            "sum_of_phase_p50_us": float(sum(p["p50_us"] for p in phases))}

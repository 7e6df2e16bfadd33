"""`sefa export` and `sefa serve`: a trained policy out of Python and into a robot's loop.
Registered on the main app by cli/main.py; the work is in sefa_deploy."""

from __future__ import annotations

import json
import os
import shlex
import sys
from pathlib import Path
from typing import Annotated, Callable, List, Optional

import typer

from sefa_cli.console import Reporter
from sefa_cli.params import Decay, EnsembleK, Execution, ReplanEvery, Samples, Weak
from sefa_cli.paths import in_workspace
from sefa_data.errors import SefaInputError

JsonFlag = Annotated[bool, typer.Option("--json", help="Print a JSON summary on stdout.")]
Solver = Annotated[Optional[str], typer.Option(help="Fixed-step solver to use instead of the checkpoint's (euler, midpoint, rk4; serving a checkpoint also takes rk45).")]
Steps = Annotated[Optional[int], typer.Option(help="Steps of that solver.")]
RawWeights = Annotated[bool, typer.Option("--raw-weights", help="Use the checkpoint's raw weights instead of its EMA weights (by default a missing ema.safetensors is an error).")]
Workspace = Annotated[Path, typer.Option("--workspace", "-w", help="Workspace directory: a relative checkpoint (e.g. distill) is looked for there first.")]


def export(
    checkpoint: Annotated[Path, typer.Argument(help="A checkpoint or run directory (e.g. distill, train).")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Directory for the artifact and metadata.json (replaced if it is an earlier export).")],
    fmt: Annotated[str, typer.Option("--format", "-f", help="onnx, torchscript, or lerobot (a policy folder for LeRobot's lerobot-eval, lerobot-rollout and policy server, with the lerobot_policy_sefa plugin).")] = "onnx",
    solver: Solver = None,
    steps: Steps = None,
    fps: Annotated[Optional[float], typer.Option(help="Control rate to record in the metadata (default: the training store's).")] = None,
    opset: Annotated[int, typer.Option(help="ONNX opset, 18 to 21: 18 loads in onnxruntime >= 1.14, 19 >= 1.16, 20 >= 1.17, 21 >= 1.18 (metadata.json records it).")] = 20,
    raw_weights: RawWeights = False,
    tolerance: Annotated[float, typer.Option(help="Largest difference allowed between the artifact's actions and the checkpoint's on a real window, as a fraction of the action's range (the normalizer's limits).")] = 1e-3,
    key_map: Annotated[Optional[List[str]], typer.Option("--key-map", help="lerobot: NAME=KEY makes LeRobot's observation NAME (e.g. observation.state) feed the policy's KEY. Repeatable; by default observation.* keys keep their names, state is observation.state, keypoint observation.environment_state, a camera observation.image(s.KEY).")] = None,
    execution: Execution = None,
    replan_every: ReplanEvery = None,
    samples: Samples = None,
    decay: Decay = None,
    ensemble_k: EnsembleK = None,
    workspace: Workspace = Path("."),
    as_json: JsonFlag = False,
) -> None:
    """Export a policy as one ONNX or TorchScript file: raw observation + noise in, action chunk out.

    One-step policies export as they are; a flow needs a fixed-step setting, e.g. --solver euler --steps 4.
    --format lerobot writes a folder LeRobot loads with the lerobot_policy_sefa plugin. The
    --execution options (default: the execution chosen for the policy) are what `sefa serve`
    runs for the export (metadata.json), or LeRobot's select_action."""
    from sefa_pipelines.options import check_options, export_execution
    from sefa_deploy.export import export_policy

    check_options("export", {"--steps": steps, "--fps": fps, "--opset": opset,
                             "--tolerance": tolerance})
    checkpoint = in_workspace(workspace, checkpoint)
    rep = Reporter(quiet=as_json)
    if fmt == "lerobot":
        from sefa_pipelines.lerobot_names import lerobot_execution

        asked = lerobot_execution(execution, replan_every, samples, decay, ensemble_k)
        _export_lerobot(checkpoint, out, solver, steps, fps, raw_weights, tolerance, key_map,
                        asked, rep, as_json)
        return
    asked = export_execution(execution, replan_every, samples, decay, ensemble_k,
                             "an export")
    with rep.status(f"exporting {checkpoint} to {fmt}"):
        meta = export_policy(checkpoint, out, fmt=fmt, solver=solver, steps=steps, fps=fps,
                             ema=not raw_weights, opset=opset, tolerance=tolerance,
                             execution=asked, log=rep.line)
    from sefa_pipelines.exports import record_export

    # `sefa status` then says when a retraining has made this export stale
    record_export(workspace, checkpoint, out, "sefa " + shlex.join(sys.argv[1:]))
    if as_json:
        print(json.dumps({"out": str(out), **meta}, indent=2))


def _export_lerobot(checkpoint, out, solver, steps, fps, raw_weights, tolerance, key_map,
                    execution, rep, as_json) -> None:
    from sefa_pipelines.lerobot_names import export_for_lerobot
    from sefa_pipelines.options import key_map_option

    names = key_map_option(key_map, names="a LeRobot observation name")
    with rep.status(f"exporting {checkpoint} for LeRobot"):
        config = export_for_lerobot(checkpoint, out, key_map=names, solver=solver, steps=steps,
                                    fps=fps, ema=not raw_weights, tolerance=tolerance,
                                    execution=execution, log=rep.line)
    if as_json:
        print(json.dumps({"out": str(out), **config}, indent=2))


def serve(
    policy: Annotated[Path, typer.Argument(help="A checkpoint, run directory, or `sefa export` directory.")],
    host: Annotated[str, typer.Option(help="Address to bind (no authentication: loopback or a trusted network).")] = "127.0.0.1",
    port: Annotated[int, typer.Option(help="TCP port; 0 picks a free one (printed).")] = 8765,
    device: Annotated[str, typer.Option(help="cpu, cuda, cuda:N or auto (a GPU when there is one and the backend can use it; TorchScript exports run on the CPU).")] = "auto",
    solver: Solver = None,
    steps: Steps = None,
    seed: Annotated[int, typer.Option(help="Seed of the noise drawn for requests that send none.")] = 0,
    max_message_mb: Annotated[float, typer.Option(help="Largest request accepted, MiB.")] = 16.0,
    max_queue: Annotated[int, typer.Option(help="Requests that may wait while the policy runs one; one more gets a 'server busy' error at once.")] = 16,
    request_timeout: Annotated[float, typer.Option(help="Seconds a request may take, its wait in the queue included, before it gets a 'no answer within' error.")] = 60.0,
    execution: Execution = None,
    replan_every: ReplanEvery = None,
    samples: Samples = None,
    decay: Decay = None,
    ensemble_k: EnsembleK = None,
    weak: Weak = None,
    raw_weights: RawWeights = False,
    fps: Annotated[Optional[float], typer.Option(help="The robot's control rate, Hz, for the check at startup of which executions fit its period (default: the policy's, metadata.json's fps).")] = None,
    timing: Annotated[bool, typer.Option("--timing/--no-timing", help="Time a few decisions at startup (at most about 3 s) and say which executions fit the control period.")] = True,
    key_map: Annotated[Optional[List[str]], typer.Option("--key-map", help="For openpi clients: NAME=KEY sends the observation an openpi client calls NAME (e.g. observation/state) to the policy's KEY; NAME= drops it (e.g. prompt=). Repeatable.")] = None,
    workspace: Workspace = Path("."),
    as_json: Annotated[bool, typer.Option("--json", help="Log as JSON lines on stdout (the first one: host and port).")] = False,
) -> None:
    """Serve a policy over websockets (msgpack + numpy): observation in, action chunk out.

    The policy runs on a worker thread, so health and metadata requests, new clients and
    signals are answered while it computes. Runs until SIGINT or SIGTERM, then waits at most
    2 s for the request running (a second signal: not at all), closes its connections and
    exits 0. Robot side: sefa_deploy/client.py (numpy, msgpack and websockets only), or an
    unmodified openpi client (openpi_client.websocket_client_policy.WebsocketClientPolicy)."""
    from sefa_pipelines.options import (check_options, check_serving, execution_option,
                                        key_map_option)

    check_options("serve", {"--port": port, "--steps": steps, "--seed": seed, "--fps": fps,
                            "--max-message-mb": max_message_mb, "--max-queue": max_queue,
                            "--request-timeout": request_timeout})
    asked = execution_option(execution, replan_every, samples, decay, ensemble_k, weak)
    source = None
    if asked is None:  # the workspace's sefa.yaml, when it sets one
        from sefa_pipelines.stages import load_pipeline

        asked, source = load_pipeline(workspace).execution, "sefa.yaml"
    from sefa_deploy.backends import load_backend
    from sefa_deploy.server import served_execution
    from sefa_deploy.server import serve as run_serve

    names = key_map_option(key_map)
    policy = in_workspace(workspace, policy)
    log = _ServeLog(as_json)
    backend = load_backend(policy, device=device, solver=solver, steps=steps, ema=not raw_weights)
    check_serving(backend.metadata, names)
    settings = served_execution(backend.metadata, asked, source)
    weak_backend = _weak_backend(settings.weak, workspace, device) if settings.mode == "bid" else None
    origin = _execution_origin(asked, source, backend.metadata)
    timed = (_what_fits(log, backend, settings, fps or backend.metadata.get("fps"), weak_backend)
             if timing else None)
    if host not in ("127.0.0.1", "localhost", "::1"):
        log(f"note: listening on {host} without authentication: whoever reaches this port "
            "drives this policy")
    try:
        abandoned = run_serve(backend, host, port, seed=seed,
                              max_message_bytes=int(max_message_mb * 2 ** 20),
                              max_queue=max_queue, request_timeout_s=request_timeout,
                              execution=settings, weak=weak_backend, key_map=names, log=log,
                              on_ready=log.ready(policy, backend, settings.label + origin, timed))
    except OSError as e:  # the port is taken, the address is not this machine's, ...
        raise SefaInputError(f"cannot listen on {host}:{port} ({e.strerror or e})",
                             key="--port") from None
    log("stopped")
    sys.stdout.flush()
    if abandoned:
        # the worker thread is inside the policy and cannot be interrupted; a normal exit
        # would join it (minutes for a slow sampler), so leave now: the stop is still clean
        sys.stderr.flush()
        os._exit(0)


def _execution_origin(asked, source: Optional[str], meta: dict) -> str:
    """Where the served execution came from, as the ready line says it."""
    if asked is not None:
        return f" (from {source})" if source else ""
    if not meta.get("execution"):
        return ""
    return {"given": " (given at export)"}.get(meta.get("execution_source"),
                                               " (chosen for this policy)")


def _what_fits(log, backend, settings, fps: Optional[float], weak) -> dict:
    """One decision timed here, and which executions fit the control period (said before the
    port opens; with --json, in the line that says where it listens): a served execution that
    does not fit is a warning (a camera policy, a slow solver)."""
    from sefa_deploy.timing import served_decisions

    t = served_decisions(backend, settings, fps, weak)
    lines = [f"one decision here: {t['decision_ms']:.3g} ms (p99 {t['worst_ms']:.3g} ms), "
             "timed on a made-up observation"]
    lines += t["lines"] or ["no control rate known (the policy's store has none): --fps F says "
                            "which executions fit F Hz"]
    served = t["served"]
    if served is not None and served["fits"] is False:
        lines.append(f"warning: step requests run {settings.label}, whose worst step takes "
                     f"{served['worst_step_ms']:.3g} ms, over the {served['period_ms']:.3g} ms "
                     f"period at {fps:g} Hz: a robot stepping at that rate waits on this policy")
    if not log.as_json:
        for line in lines:
            log(line)
    return {"decision_ms": t["decision_ms"], "worst_ms": t["worst_ms"], "fps": fps,
            "fits": [e["execution"] for e in t["executions"] if e["fits"]],
            "over_period": [e["execution"] for e in t["executions"] if e["fits"] is False],
            "served_fits": None if served is None else served["fits"], "lines": lines}


def _weak_backend(weak: str, workspace: Path, device: str):
    """bid's weaker policy, CHECKPOINT[@SOLVER-STEPS], as a backend."""
    from sefa_deploy.backends import load_backend
    from sefa_model.eval.latency import parse_target

    path, solver, steps = parse_target(weak)
    try:
        return load_backend(in_workspace(workspace, Path(path)), device=device, solver=solver,
                            steps=steps)
    except SefaInputError as e:
        raise SefaInputError(f"the weaker policy '{weak}': {e}", key="--weak") from None


class _ServeLog:
    """What `sefa serve` says while it runs: lines on stderr, or with --json JSON lines on
    stdout (the first one where it listens, for a script to connect to)."""

    def __init__(self, as_json: bool):
        self.as_json = as_json
        self.rep = Reporter()

    def __call__(self, text: str) -> None:
        if self.as_json:
            print(json.dumps({"log": text}), flush=True)
        else:
            self.rep.line(text)

    def ready(self, policy: Path, backend, execution: str, timing: dict | None = None
              ) -> Callable[[str, int], None]:
        """The line once the port is open (port 0: the one picked); with --json it carries the
        startup timing too."""
        meta = backend.metadata

        def ready(h: str, p: int) -> None:
            if self.as_json:
                print(json.dumps({"serving": f"ws://{h}:{p}", "host": h, "port": p,
                                  "execution": execution, "timing": timing}), flush=True)
            else:
                self.rep.line(f"serving {policy} ({backend.name}, {meta['solver']}"
                              f"{'' if meta['steps'] is None else '-' + str(meta['steps'])}"
                              f", {backend.device}) on ws://{h}:{p}; step requests: {execution}; "
                              "Ctrl-C to stop")
        return ready

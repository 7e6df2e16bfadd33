"""Serving and export latency, in one run (issue 13, acceptance 3).

    python benchmarks/bench_serve.py [--one-step CKPT --flow CKPT] [--store STORE] [--json]
                                     [--openpi-python PY | --no-openpi]

Without checkpoints it makes them first on the Push-T low-dim task, at the network size of the
cpu profile (pipelines/pusht_lowdim_train.yaml: MLP head 3 x 512, time embedding 128): a base
flow trained `--train-steps` steps and a one-step student distilled from it the way `sefa
distill` does (reflow couplings, then training at t = 0), shortened. Their weights are barely
trained: that leaves every timing of the one-step policy as it is (one network evaluation of
the same size), but RK45's number of evaluations depends on the flow, so its row states it.

Prints, on this machine:
  * the loopback round trip of `sefa serve` (p50, p99, x in-process) against in-process
    predict_action, for the one-step policy (with our client and with the unmodified
    openpi-client 0.1.2 on the same server, in turns), for the base flow with RK45, and for
    the one-step policy's ONNX export served; goal: the server adds <= 0.3 ms p50 to the
    one-step policy. The openpi client runs in its own venv (scripts/openpi_client_venv.sh,
    made on first use) as a child process timing its own calls
    (benchmarks/openpi_bench_client.py); without that venv the row is left out, saying why;
  * where a served one-step call's time goes: per phase p50 (us), from perf_counter_ns marks in
    the client and in a server process whose functions are wrapped with marks (one clock for
    both processes: CLOCK_MONOTONIC);
  * the one-step policy exported to ONNX (onnxruntime) and TorchScript against eager PyTorch;
    goal: each at most as slow as eager;
  * the server's work around the one-step call: the hand-off to its worker thread, and its check
    of every answer (shapes, finite values);
  * a bounded load test: several clients at once, a fixed number of requests each.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
NETWORK = ["shape_meta.obs.keypoint.type=low_dim", "shape_meta.obs.state.dims=[0,2]",
           "policy.head=mlp", "policy.mlp_hidden_dims=[512,512,512]", "policy.time_embed_dim=128"]
GOAL_ADDED_MS = 0.3
OPENPI_VENV_SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "openpi_client_venv.sh"


def openpi_python() -> tuple[str | None, str]:
    """The openpi client venv's interpreter (made on first use), or None and why not."""
    import subprocess
    import sys

    done = subprocess.run(["bash", str(OPENPI_VENV_SCRIPT)], capture_output=True, text=True,
                          env={**__import__("os").environ, "PYTHON": sys.executable})
    last = (done.stdout.strip().splitlines() or ["(no output)"])[-1]
    return (last, "") if done.returncode == 0 else (None, last)


def make_checkpoints(root: Path, store: Path | None, train_steps: int) -> tuple[Path, Path, Path]:
    from sefa_data.ingest import IngestOptions, ingest
    from sefa_model.config import load_train_config
    from sefa_model.policy.artifact import Policy
    from sefa_model.sefa.reflow import CouplingConfig, generate_couplings
    from sefa_model.data.couplings import PairSource
    from sefa_model.train.loop import train
    from sefa_pipelines.stages import student_config

    if store is None:
        store = root / "pusht.zarr"
        ingest([SHARED / "pusht_cchi_v7_replay.zarr"], store,
               IngestOptions(fps=10, keys=["keypoint", "state", "action"]))
    common = [f"training.max_steps={train_steps}", "training.batch_size=256", "training.lr=1e-3",
              f"training.lr_warmup_steps={max(1, train_steps // 10)}", f"training.val_every={train_steps}",
              "training.val_sample_windows=8", "training.val_batches=1"]
    train(load_train_config(None, NETWORK + common + ["flow.solver=rk45"]), root / "flow", store)
    flow = root / "flow" / "checkpoints" / "latest"
    generate_couplings(Policy.load(flow), store, root / "couplings.zarr",
                       CouplingConfig(samples_per_window=4, solver="euler", steps=8, max_windows=256))
    # the one-step student exactly as `sefa distill` builds it (t = 0 only, one Euler step,
    # the base encoder frozen)
    train(student_config(load_train_config(None, NETWORK + common), []), root / "one_step", store,
          init_from=flow, couplings=PairSource.couplings(root / "couplings.zarr", "sefa_one_step"))
    return root / "one_step", root / "flow", store


def render(r: dict) -> None:
    from sefa_data.bench.throughput import machine_summary

    print(f"machine: {machine_summary(r['machine'])}")
    print(f"observation: {r['observation']}; batch 1; one-step: {r['one_step']}; flow: {r['flow']}")
    print(f"load average {r['load_average_start'][0]:.1f} at the start, "
          f"{r['load_average_end'][0]:.1f} at the end (1-minute)")
    print(f"\n{'loopback round trip vs in-process, ms':60s} {'NFE':>4s} {'p50':>8s} {'p90':>8s} "
          f"{'p99':>8s} {'x in-pr':>7s} {'calls':>6s}")
    for key in ("one_step_round_trip", "rk45_round_trip", "onnx_round_trip"):
        rt = r[key]
        for row in rt["rows"]:
            print(f"{row['name']:60s} {row['nfe']:4d} {row['p50_ms']:8.3f} {row['p90_ms']:8.3f} "
                  f"{row['p99_ms']:8.3f} {row['x_in_process']:7.2f} {row['calls']:6d}")
        print(f"{'  the server adds (p50 difference)':60s} {'':4s} {rt['added_p50_ms']:8.3f}"
              f"   (served vs in-process max |diff| {rt['max_abs_diff']:.1e})")
        if "openpi_added_p50_ms" in rt:
            print(f"{'  the server adds, openpi client (p50 difference)':60s} {'':4s} "
                  f"{rt['openpi_added_p50_ms']:8.3f}   (max |diff| {rt['openpi_max_abs_diff']:.1e})")
    if r.get("openpi_skipped"):
        print(f"(no openpi-client row: {r['openpi_skipped']})")
    added = r["one_step_round_trip"]["added_p50_ms"]
    print(f"goal: the server adds <= {GOAL_ADDED_MS} ms p50 to the one-step policy: "
          f"{added:.3f} ms, {'met' if added <= GOAL_ADDED_MS else 'MISSED'} "
          f"(margin {GOAL_ADDED_MS - added:+.3f} ms)")
    ph = r["phases"]
    print(f"\n{'where a served one-step call goes (probed), us':60s} {'p50':>8s} {'p90':>8s}")
    for p in ph["phases"]:
        print(f"{p['name']:60s} {p['p50_us']:8.1f} {p['p90_us']:8.1f}")
    print(f"{'sum of the p50s':60s} {ph['sum_of_phase_p50_us']:8.1f}")
    print(f"probed run: served p50 {ph['served']['p50_ms']:.3f} ms, in-process p50 "
          f"{ph['in_process']['p50_ms']:.3f} ms, p50 of paired differences "
          f"{ph['paired_added_p50_ms']:.3f} ms, outside the policy call p50 "
          f"{ph['outside_call_p50_us']:.0f} us ({ph['calls']} calls each)")
    e = r["exports"]
    print(f"\n{'one-step policy, exported vs eager, ms':52s} {'p50':>8s} {'p90':>8s} {'p99':>8s} {'x eager':>8s}")
    for row in e["rows"]:
        print(f"{row['name']:52s} {row['p50_ms']:8.3f} {row['p90_ms']:8.3f} {row['p99_ms']:8.3f} "
              f"{row['x_eager']:8.2f}")
    worst = max(row["x_eager"] for row in e["rows"] if row["name"] in ("onnxruntime", "torchscript"))
    print(f"goal: each export at least as fast as eager (x eager <= 1): worst {worst:.2f}, "
          f"{'met' if worst <= 1 else 'MISSED'}; max |diff| vs eager "
          + ", ".join(f"{k} {v:.1e}" for k, v in e["max_abs_diff_vs_eager"].items()))
    sw = r["server_work"]
    print(f"\n{'the server around the one-step call, ms':52s} {'p50':>8s} {'p90':>8s} {'p99':>8s} {'calls':>6s}")
    for row in sw["rows"]:
        print(f"{row['name']:52s} {row['p50_ms']:8.4f} {row['p90_ms']:8.4f} {row['p99_ms']:8.4f} "
              f"{row['calls']:6d}")
    check = sw["rows"][2]["p50_ms"]
    print(f"the worker hand-off adds {sw['handoff_p50_ms']:.3f} ms p50; the output check costs "
          f"{check * 1e3:.1f} us, {sw['check_percent_of_call']:.2f} % of the call (p50)")
    ld = r["load"]
    print(f"\nload: {ld['clients']} clients x {ld['requests_per_client']} requests, one-step policy: "
          f"{ld['answered']} answered, {len(ld['errors'])} errors, p50 {ld['p50_ms']:.3f} ms, "
          f"p99 {ld['p99_ms']:.3f} ms, {ld['requests_per_s']:.0f} requests/s over {ld['seconds']:.1f} s")
    for err in ld["errors"][:5]:
        print(f"  {err}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--one-step", type=Path, help="a one-step checkpoint (default: made first)")
    ap.add_argument("--flow", type=Path, help="a base flow checkpoint, timed with RK45")
    ap.add_argument("--store", type=Path, help="a Push-T store (default: import ../shared/data's)")
    ap.add_argument("--train-steps", type=int, default=50)
    ap.add_argument("--calls", type=int, default=500)
    ap.add_argument("--rk45-calls", type=int, default=30)
    ap.add_argument("--clients", type=int, default=4)
    ap.add_argument("--requests", type=int, default=250, help="per client in the load test")
    ap.add_argument("--openpi-python", help="the openpi client venv's python (default: "
                    "scripts/openpi_client_venv.sh's, made on first use)")
    ap.add_argument("--no-openpi", action="store_true", help="leave the openpi client's row out")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    if (args.one_step is None) != (args.flow is None):
        ap.error("give both --one-step and --flow, or neither")

    from sefa_deploy.bench import bench_serve

    log = (lambda _: None) if args.json else (lambda s: print(f"... {s}", flush=True))
    openpi, skipped = args.openpi_python, ""
    if openpi is None and not args.no_openpi:
        log("the openpi client's venv (scripts/openpi_client_venv.sh)")
        openpi, skipped = openpi_python()
    elif args.no_openpi:
        skipped = "--no-openpi"
    started = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        one_step, flow, store = args.one_step, args.flow, args.store
        if one_step is None:
            log(f"making the checkpoints ({args.train_steps} training steps each)")
            one_step, flow, store = make_checkpoints(Path(tmp), store, args.train_steps)
        result = bench_serve(one_step, flow, store=store, calls=args.calls,
                             rk45_calls=args.rk45_calls, load_clients=args.clients,
                             load_requests=args.requests, openpi_python=openpi, log=log)
        result["openpi_skipped"] = skipped
    result["seconds"] = time.perf_counter() - started
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        render(result)
        print(f"\n(whole run {result['seconds']:.0f} s)")


if __name__ == "__main__":
    main()

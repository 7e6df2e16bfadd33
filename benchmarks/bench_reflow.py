"""Reflow coupling generation vs the reference approach, at equal accuracy, in one run.

    python benchmarks/bench_reflow.py [--workspace DIR | --checkpoint CKPT --store STORE]
        [--windows 128] [--samples 10] [--ref-batch 64] [--rtol 1e-5] [--atol 1e-5]
        [--tight-tol 1e-10] [--tight-windows 32] [--repeat 3] [--threads N] [--json] [--save F]

One policy, the same training windows and the same noise for every method:

- reference (SeFA's gen_data): for each dataloader batch of --ref-batch windows and for each
  of the K samples separately, the batch is flattened into one float64 numpy vector and
  integrated by `scipy.integrate.solve_ivp(method="RK45", rtol, atol)`, the velocity network
  evaluated under torch.no_grad on the CPU at every call (numpy -> torch -> numpy);
- ours: `sefa_model.sefa.reflow.generate_couplings` (each window encoded once, all N*K chunks in
  one batched torch solve) with each solver configuration: "rk45" (one shared step, the
  reference's controller), "rk45-ps" / "dop853-ps" (a step size per chunk; finished chunks
  leave the batch), fixed-step "rk4" / "midpoint" with N steps.

Accuracy: every method's couplings against a tight solve of the same ODE from the same noise
(a float64 copy of the network, dop853-ps at rtol = atol = --tight-tol, per chunk): mean and max
|x - x_tight| over the couplings of --tight-windows evenly spread windows, normalized action
units. A configuration is at *equal accuracy* when its mean AND its max error are <= the
reference's. Calibration: each solver family's candidates (CANDIDATES, tolerances relative to
--rtol, from loose to tight, or step counts from few to many) run once until one is at equal
accuracy; that one is timed. Timing: the reference, ours at the reference's own setting (rk45,
--rtol/--atol) and each family's calibrated configuration run --repeat times, interleaved
(load on a shared host shifts them alike), fastest kept; the cost counted is the network's:
calls, and sample-evaluations per coupling (rows evaluated over all calls / couplings).

The levers are reported as ratios of those times: batching (ours at the reference's setting vs
the reference), tolerance calibration, per-sample step control, the method (dop853), fixed
steps. Diagnostics: the tight solve against one 100x looser; a per-sample chunk solved alone vs
inside the batch; how much of the velocity's variation along t is fast oscillation (what sets
the number of evaluations any solver needs here).

Without --checkpoint/--store, a Push-T low-dim store is imported from ../shared/data and a
small MLP base policy is trained for --train-steps steps (so the velocity field is a realistic,
trained one); with --workspace DIR those are kept in DIR (DIR/dataset.zarr, DIR/train) and
reused on the next run.
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import platform
import shutil
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy
import torch
import zarr
from scipy.integrate import solve_ivp

from sefa_data.ingest import IngestOptions, ingest
from sefa_data.store.zarr_store import EpisodeStore
from sefa_model.config import load_train_config
from sefa_model.nets.networks import SinusoidalPosEmb
from sefa_model.policy.artifact import Policy
from sefa_model.sefa.reflow import CouplingConfig, generate_couplings, window_subset
from sefa_model.flow.solvers import solve
from sefa_model.data.windows import PolicyData
from sefa_model.train.loop import train

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"

PUSHT_LOWDIM = [
    "shape_meta.obs.keypoint.type=low_dim",
    "shape_meta.obs.state.dims=[0,2]",
    "policy.head=mlp", "policy.mlp_hidden_dims=[256,256,256]", "policy.time_embed_dim=64",
    "training.batch_size=256", "training.lr=1e-3", "training.lr_warmup_steps=50",
    "training.val_batches=2", "training.val_sample_windows=128", "training.log_every=50",
]


def build(workdir: Path, train_steps: int) -> tuple[Path, Path]:
    """(checkpoint, store) in `workdir`, imported and trained unless already there."""
    store, run = workdir / "dataset.zarr", workdir / "train"
    if not (store / ".zgroup").exists():
        ingest([SHARED / "pusht_cchi_v7_replay.zarr"], store,
               IngestOptions(fps=10, keys=["keypoint", "state", "action"]))
    if not (run / "checkpoints" / "latest" / "config.json").exists():
        cfg = load_train_config(None, PUSHT_LOWDIM + [f"training.max_steps={train_steps}",
                                                      f"training.val_every={train_steps}",
                                                      f"training.checkpoint_every={train_steps}"])
        train(cfg, run, store)
    return run, store


@dataclass(frozen=True)
class Setting:
    """One solver configuration of ours: adaptive with rtol = atol = tol, or fixed with steps."""

    solver: str
    tol: float | None = None
    steps: int | None = None

    @property
    def label(self) -> str:
        return f"{self.solver} tol {self.tol:.2g}" if self.steps is None else f"{self.solver} N={self.steps}"


# Per family, from cheapest to most expensive: tolerances as multiples of the reference's
# rtol (adaptive), or step counts (fixed). Calibration stops at the first at equal accuracy.
# The loose ends matter for a teacher that is smooth in t (a small flow.time_scale, issue 26):
# there a few fixed steps can already be as accurate as the reference's RK45.
CANDIDATES: dict[str, tuple[float, ...]] = {
    "rk45": (30.0, 10.0, 5.0, 2.0, 1.4, 1.0, 0.7, 0.5, 0.35, 0.25),
    "rk45-ps": (30.0, 10.0, 5.0, 2.0, 1.4, 1.0, 0.7, 0.5, 0.35, 0.25),
    "dop853-ps": (300.0, 100.0, 30.0, 10.0, 3.0, 1.0, 0.5),
    "rk4": (6, 8, 12, 16, 24, 32, 50, 75, 100, 150, 200),
    "midpoint": (12, 16, 24, 32, 50, 75, 100, 150, 200, 300, 400),
}


def candidates(family: str, rtol: float) -> list[Setting]:
    if family in ("rk4", "midpoint"):
        return [Setting(family, steps=int(n)) for n in CANDIDATES[family]]
    return [Setting(family, tol=rtol * m) for m in CANDIDATES[family]]


def run_ours(policy: Policy, store: Path, out: Path, n: int, k: int, s: Setting,
             ) -> tuple[dict, np.ndarray, np.ndarray]:
    """generate_couplings with one solve of all n*k chunks; (timing, noise, action)."""
    tol = 1e-5 if s.tol is None else s.tol
    cfg = CouplingConfig(samples_per_window=k, solver=s.solver, rtol=tol, atol=tol, steps=s.steps,
                         batch_windows=n, max_windows=n, seed=0)
    if policy.device.type == "cuda":
        torch.cuda.synchronize()
    t = time.perf_counter()
    summary = generate_couplings(policy, store, out, cfg)
    if policy.device.type == "cuda":
        torch.cuda.synchronize()
    seconds = time.perf_counter() - t
    root = zarr.open_group(str(out), mode="r")
    noise, action = root["noise"][:], root["action"][:]
    shutil.rmtree(out, ignore_errors=True)
    return ({"couplings": summary["n"], "seconds": seconds, "calls": summary["nfe"],
             "evals_per_coupling": summary["evals_per_coupling"]}, noise, action)


@torch.no_grad()
def run_reference(policy: Policy, data: PolicyData, windows: np.ndarray, noise: np.ndarray,
                  k: int, ref_batch: int, t0: float, rtol: float, atol: float
                  ) -> tuple[dict, np.ndarray]:
    """SeFA gen_data: per dataloader batch, per sample, one scipy RK45 on the flattened batch.

    noise: (len(windows) * K, T, Da), row w * K + j = window w, sample j (ours' layout).
    Returns the timing and the generated chunks in the same layout.
    """
    model = policy.model
    shape_tail = noise.shape[1:]
    out = np.empty_like(noise)
    calls = evals = 0
    t = time.perf_counter()
    for b in range(0, len(windows), ref_batch):
        block = windows[b:b + ref_batch]
        nb = len(block)
        obs, _ = data.tensors(data.train, block, torch.device("cpu"))
        for j in range(k):
            cond = model.encode(obs)  # the reference encodes inside every sampling call
            rows = (b + np.arange(nb)) * k + j
            y0 = noise[rows].astype(np.float64).ravel()

            def fun(tt, y, cond=cond, nb=nb):
                x = torch.from_numpy(y.reshape(nb, *shape_tail)).float()
                v = model.velocity(x, torch.full((nb,), tt, dtype=torch.float32), cond)
                return v.double().numpy().ravel()

            sol = solve_ivp(fun, (t0, 1.0), y0, method="RK45", rtol=rtol, atol=atol)
            if not sol.success:
                raise RuntimeError(f"solve_ivp failed: {sol.message}")
            out[rows] = sol.y[:, -1].reshape(nb, *shape_tail).astype(np.float32)
            calls += sol.nfev
            evals += sol.nfev * nb
    seconds = time.perf_counter() - t
    m = len(windows) * k
    return {"couplings": m, "seconds": seconds, "calls": calls, "evals_per_coupling": evals / m}, out


@torch.no_grad()
def tight_solve(policy: Policy, data: PolicyData, windows: np.ndarray, noise: np.ndarray, k: int,
                tol: float) -> tuple[np.ndarray, float]:
    """The couplings of `windows` (noise rows w*k+j) by dop853-ps at rtol = atol = tol on a
    float64 copy of the network (float64 time embedding: smooth in t). (x1, evals/coupling)."""
    model64 = copy.deepcopy(policy.model).double()
    obs, _ = data.tensors(data.train, windows, torch.device("cpu"))
    cond = policy.model.encode(obs).double().repeat_interleave(k, dim=0)
    res = solve(model64.velocity, torch.from_numpy(noise).double(), "dop853-ps",
                t0=policy.cfg.flow.t_eps, rtol=tol, atol=tol, cond=cond)
    return res.x.numpy(), res.sample_evals / len(noise)


@torch.no_grad()
def oscillation_in_t(policy: Policy, data: PolicyData, windows: np.ndarray, noise: np.ndarray,
                     k: int, points: int = 4001) -> dict:
    """How rough is the velocity along t? v(x0, t) at fixed x0 for a few chunks on a fine t grid
    (float64 network): the share of its variation (RMS about its mean) that a degree-8
    polynomial in t does not capture, and the time embedding's fastest angular frequency."""
    model64 = copy.deepcopy(policy.model).double()
    obs, _ = data.tensors(data.train, windows[:4], torch.device("cpu"))
    cond = policy.model.encode(obs).double()
    t = np.linspace(policy.cfg.flow.t_eps, 1.0, points)
    shares = []
    for w in range(len(cond)):
        x = torch.from_numpy(noise[w * k]).double()[None].expand(points, -1, -1)
        v = model64.velocity(x, torch.from_numpy(t), cond[w:w + 1].expand(points, -1))
        v = v.reshape(points, -1).numpy()
        smooth = np.polynomial.polynomial.polyval(t, np.polynomial.polynomial.polyfit(t, v, 8)).T
        shares.append(np.sqrt(((v - smooth) ** 2).mean()) / np.sqrt(((v - v.mean(0)) ** 2).mean()))
    embedding = next(mod for mod in policy.model.head.modules() if isinstance(mod, SinusoidalPosEmb))
    top = float(embedding.freqs.max()) * policy.cfg.flow.time_scale
    return {"chunks": len(shares), "oscillation_share": float(np.mean(shares)),
            "fastest_embedding_rad_per_t": top,
            "periods_on_interval": top * (1 - policy.cfg.flow.t_eps) / (2 * np.pi)}


@torch.no_grad()
def network_row_cost(policy: Policy, sizes: list[int], repeat: int = 7) -> list[dict]:
    """The bare network's time per row at each batch size (best of `repeat` loops of about
    2,560 rows), and its arithmetic rate when the head is linear layers only (an MLP head uses
    each nn.Linear weight once per row: 2 FLOPs per weight)."""
    head = policy.model.head
    per_row = 2 * sum(m.weight.numel() for m in head.modules() if isinstance(m, torch.nn.Linear))
    convs = any(isinstance(m, torch.nn.modules.conv._ConvNd) for m in head.modules())
    d = policy.model.head.global_cond_dim
    gen = torch.Generator().manual_seed(0)
    out = []
    for b in sizes:
        x = torch.randn(b, policy.cfg.policy.horizon, policy.cfg.shape_meta.action.shape[-1], generator=gen)
        t, cond = torch.rand(b, generator=gen), torch.randn(b, d, generator=gen)
        calls = max(1, 2560 // b)
        for _ in range(3):
            policy.model.velocity(x, t, cond)
        best = float("inf")
        for _ in range(repeat):
            start = time.perf_counter()
            for _ in range(calls):
                policy.model.velocity(x, t, cond)
            best = min(best, (time.perf_counter() - start) / (calls * b))
        out.append({"batch": b, "us_per_row": best * 1e6,
                    "gflops": None if convs else per_row / best / 1e9})
    return out


@torch.no_grad()
def batch_independence(policy: Policy, data: PolicyData, windows: np.ndarray, noise: np.ndarray,
                       k: int, batched: list[tuple[Setting, np.ndarray]]) -> dict:
    """Each chunk of `windows` solved ALONE vs its coupling from the full batch, per setting;
    and the network itself: one row evaluated alone vs inside the batch."""
    obs, _ = data.tensors(data.train, windows, torch.device("cpu"))
    cond = policy.model.encode(obs).repeat_interleave(k, dim=0)
    x0 = torch.from_numpy(noise)
    t_eps = policy.cfg.flow.t_eps
    out = {"chunks": len(noise), "settings": []}
    for s, in_batch in batched:
        alone = np.concatenate([solve(policy.model.velocity, x0[i:i + 1], s.solver, t0=t_eps, steps=s.steps,
                                      rtol=s.tol or 1e-5, atol=s.tol or 1e-5, cond=cond[i:i + 1]).x.numpy()
                                for i in range(len(noise))])
        diff = np.abs(alone - in_batch).reshape(len(noise), -1).max(1)
        out["settings"].append({"setting": s.label, "max_abs_diff": float(diff.max()),
                                "bit_identical": int((diff == 0).sum())})
    t = torch.full((len(noise),), 0.5)
    v = policy.model.velocity(x0, t, cond)
    v1 = torch.cat([policy.model.velocity(x0[i:i + 1], t[:1], cond[i:i + 1]) for i in range(len(noise))])
    out["network_row_max_abs_diff"] = float((v - v1).abs().max())
    return out


def errors(action: np.ndarray, tight: np.ndarray, rows: np.ndarray) -> dict:
    d = np.abs(action[rows].astype(np.float64) - tight)
    return {"mean_err": float(d.mean()), "max_err": float(d.max())}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--workspace", type=Path, help="keep (and reuse) the store and trained policy here")
    ap.add_argument("--checkpoint", type=Path, help="a trained sefa policy (run or checkpoint dir)")
    ap.add_argument("--store", type=Path, help="the Zarr store it was trained on")
    ap.add_argument("--train-steps", type=int, default=400, help="steps of the default quick policy")
    ap.add_argument("--windows", type=int, default=128, help="N training windows (evenly spread)")
    ap.add_argument("--samples", type=int, default=10, help="K noises per window")
    ap.add_argument("--ref-batch", type=int, default=64, help="the reference's dataloader batch")
    ap.add_argument("--rtol", type=float, default=1e-5, help="the reference's rtol")
    ap.add_argument("--atol", type=float, default=1e-5, help="the reference's atol")
    ap.add_argument("--tight-tol", type=float, default=1e-10, help="rtol = atol of the accuracy yardstick")
    ap.add_argument("--tight-windows", type=int, default=32,
                    help="windows whose couplings are checked against the tight solve (evenly spread)")
    ap.add_argument("--families", default=",".join(CANDIDATES),
                    help=f"solver families to calibrate and time (default: {','.join(CANDIDATES)})")
    ap.add_argument("--repeat", type=int, default=3, help="timed runs per method (interleaved); the fastest is kept")
    ap.add_argument("--threads", type=int, help="torch CPU threads (default: torch's choice)")
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--save", type=Path, help="also write the --json result to this file")
    args = ap.parse_args()
    if (args.checkpoint is None) != (args.store is None):
        ap.error("--checkpoint and --store go together")
    families = [f for f in args.families.split(",") if f]
    unknown = sorted(set(families) - set(CANDIDATES))
    if unknown:
        ap.error(f"unknown families {unknown}; valid: {', '.join(CANDIDATES)}")
    if args.threads:
        torch.set_num_threads(args.threads)
    log = (lambda *a: None) if args.json else (lambda msg: print(msg, file=sys.stderr, flush=True))
    started = time.perf_counter()

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        load_before = os.getloadavg()[0]
        setup = time.perf_counter()
        if args.checkpoint is not None:
            ckpt, store = args.checkpoint, args.store
        else:
            work = args.workspace or tmp / "work"
            work.mkdir(parents=True, exist_ok=True)
            ckpt, store = build(work, args.train_steps)
        setup_s = time.perf_counter() - setup

        policy = Policy.load(ckpt, device="cpu")
        data = PolicyData(policy.cfg, EpisodeStore.open(store), policy.normalizer)
        n_train = len(data.train)
        windows = window_subset(n_train, args.windows)
        n, k = len(windows), args.samples
        t_eps = policy.cfg.flow.t_eps
        params = sum(p.numel() for p in policy.model.parameters())
        run_ours(policy, store, tmp / "warm.zarr", 2, 2, Setting("rk45", tol=args.rtol))  # warm-up

        # The noise every method starts from (ours draws it; the reference and the tight solve
        # are handed the same), and the couplings checked for accuracy.
        at_ref = Setting("rk45", tol=args.rtol)
        first, noise, at_ref_action = run_ours(policy, store, tmp / "c.zarr", n, k, at_ref)
        sub = np.unique(np.linspace(0, n - 1, min(args.tight_windows, n)).round().astype(np.int64))
        rows = (sub[:, None] * k + np.arange(k)).ravel()
        log(f"tight solve of {len(rows)} couplings (dop853-ps, float64, tol {args.tight_tol:g}) ...")
        t = time.perf_counter()
        tight, tight_evals = tight_solve(policy, data, windows[sub], noise[rows], k, args.tight_tol)
        tight_s = time.perf_counter() - t
        few = rows[:min(8, len(sub)) * k]
        looser, _ = tight_solve(policy, data, windows[sub[:min(8, len(sub))]], noise[few], k,
                                args.tight_tol * 100)
        tight_check = float(np.abs(looser - tight[:len(few)]).max())
        log(f"  {tight_s:.0f} s, {tight_evals:.0f} evaluations per coupling; "
            f"vs tol {args.tight_tol * 100:g}: max |diff| {tight_check:.1e}")

        log("reference (scipy RK45 per batch and sample) ...")
        ref_first, ref_action = run_reference(policy, data, windows, noise, k, args.ref_batch, t_eps,
                                              args.rtol, args.atol)
        ref_err = errors(ref_action, tight, rows)
        log(f"  {ref_first['seconds']:.1f} s, {ref_first['evals_per_coupling']:.0f} evals/coupling, "
            f"mean err {ref_err['mean_err']:.2e}, max {ref_err['max_err']:.2e}")

        def equal_accuracy(e: dict) -> bool:
            return e["mean_err"] <= ref_err["mean_err"] and e["max_err"] <= ref_err["max_err"]

        # Calibration: per family, loose -> tight until one is at equal accuracy.
        calibration: list[dict] = []
        chosen: dict[str, Setting] = {}
        seen = {at_ref: (first, errors(at_ref_action, tight, rows))}
        actions = {at_ref: at_ref_action}
        for family in families:
            for s in candidates(family, args.rtol):
                if s in seen:
                    r, e = seen[s]
                else:
                    r, nz, act = run_ours(policy, store, tmp / "c.zarr", n, k, s)
                    assert np.array_equal(nz, noise)
                    e = errors(act, tight, rows)
                    seen[s], actions[s] = (r, e), act
                ok = equal_accuracy(e)
                calibration.append({"family": family, "setting": s.label, **r, **e, "equal_accuracy": ok})
                log(f"  calibrate {s.label:22s} {r['evals_per_coupling']:7.1f} evals/coupling  "
                    f"mean {e['mean_err']:.2e}  max {e['max_err']:.2e}  {'<= reference' if ok else ''}")
                if ok:
                    chosen[family] = s
                    break

        # Timing: interleaved, fastest of --repeat.
        timed: dict[str, tuple[str, Setting | None]] = {"reference": ("reference", None),
                                                      "rk45@ref": ("rk45 at the reference's tolerance", at_ref)}
        key_of = {at_ref: "rk45@ref"}  # a calibrated setting equal to it is timed once
        for family, s in chosen.items():
            if s not in key_of:
                key_of[s] = f"{family}@cal"
                timed[key_of[s]] = (f"{s.label} (calibrated)", s)
        best: dict[str, dict] = {}
        all_seconds: dict[str, list[float]] = {key: [] for key in timed}
        for rep in range(args.repeat):
            for key, (_, s) in timed.items():
                log(f"  timing {key} ({rep + 1}/{args.repeat})")
                if s is None:
                    r, _ = run_reference(policy, data, windows, noise, k, args.ref_batch, t_eps,
                                         args.rtol, args.atol)
                else:
                    r, nz, _ = run_ours(policy, store, tmp / "c.zarr", n, k, s)
                    assert np.array_equal(nz, noise)
                all_seconds[key].append(r["seconds"])
                if key not in best or r["seconds"] < best[key]["seconds"]:
                    best[key] = r
        ref_s = best["reference"]["seconds"]
        table = []
        for key, (label, s) in timed.items():
            e = ref_err if s is None else seen[s][1]
            r = best[key]
            table.append({"key": key, "method": label, "device": "cpu", **r, **e,
                          "couplings_per_s": r["couplings"] / r["seconds"],
                          "equal_accuracy": s is None or equal_accuracy(e),
                          "speedup": ref_s / r["seconds"], "all_seconds": all_seconds[key]})

        if torch.cuda.is_available():
            gpu = Policy.load(ckpt, device="cuda")
            run_ours(gpu, store, tmp / "warm.zarr", 2, 2, at_ref)
            for key, (label, s) in list(timed.items())[1:]:
                runs = [run_ours(gpu, store, tmp / "c.zarr", n, k, s) for _ in range(args.repeat)]
                r = min((x[0] for x in runs), key=lambda x: x["seconds"])
                e = errors(runs[0][2], tight, rows)
                table.append({"key": key + "/cuda", "method": label, "device": "cuda", **r, **e,
                              "couplings_per_s": r["couplings"] / r["seconds"],
                              "equal_accuracy": equal_accuracy(e), "speedup": ref_s / r["seconds"],
                              "all_seconds": [x[0]["seconds"] for x in runs]})

        seconds = {row["key"]: row["seconds"] for row in table if row["device"] == "cpu"}
        evals = {row["key"]: row["evals_per_coupling"] for row in table if row["device"] == "cpu"}

        def lever(name: str, before: str, after: str) -> dict | None:
            before, after = (key_of.get(chosen.get(x.split("@")[0]), x) if x.endswith("@cal") else x
                             for x in (before, after))
            if before not in seconds or after not in seconds:
                return None
            return {"lever": name, "from": before, "to": after, "time_factor": seconds[before] / seconds[after],
                    "evals_factor": evals[before] / evals[after]}

        levers = [x for x in (
            lever("batching: one torch solve of all N*K chunks, same solver and tolerance", "reference", "rk45@ref"),
            lever("tolerance calibrated to equal accuracy (shared-step rk45)", "rk45@ref", "rk45@cal"),
            lever("per-sample step control (rk45 -> rk45-ps, both calibrated)", "rk45@cal", "rk45-ps@cal"),
            lever("method: Dormand-Prince 8(5,3) (rk45-ps -> dop853-ps, both calibrated)", "rk45-ps@cal", "dop853-ps@cal"),
            lever("fixed-step rk4 instead of adaptive rk45 (both calibrated)", "rk45@cal", "rk4@cal"),
            lever("fixed-step midpoint instead of adaptive rk45 (both calibrated)", "rk45@cal", "midpoint@cal"),
        ) if x is not None]
        at_equal = [row for row in table if row["device"] == "cpu" and row["key"] != "reference"
                    and row["equal_accuracy"]]
        best_equal = max(at_equal, key=lambda row: row["speedup"]) if at_equal else None

        # Diagnostics: a chunk solved alone vs inside the batch; roughness of the field in t.
        independence = batch_independence(policy, data, windows[sub[:2]], noise[rows[:2 * k]], k,
                                          [(s, actions[s][rows[:2 * k]]) for s in chosen.values()
                                           if s.solver in ("rk45-ps", "rk45", "rk4")])
        oscillation = oscillation_in_t(policy, data, windows, noise, k)
        row_cost = network_row_cost(policy, [min(args.ref_batch, n), n * k])
        load_after = os.getloadavg()[0]

    out = {"machine": {"platform": platform.platform(), "processor": platform.machine(),
                       "cpu_count": os.cpu_count(), "torch_threads": torch.get_num_threads(),
                       "torch": torch.__version__, "scipy": scipy.__version__,
                       "cuda": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
                       "loadavg_1min_start_end": [load_before, load_after]},
           "checkpoint": str(args.checkpoint) if args.checkpoint else f"quick MLP base policy, "
                                                                   f"{args.train_steps} steps",
           "params": params, "setup_s": setup_s, "train_windows": n_train, "windows": n,
           "samples_per_window": k, "couplings": n * k, "ref_batch": args.ref_batch,
           "rtol": args.rtol, "atol": args.atol, "t0": t_eps, "repeat": args.repeat,
           "horizon": int(noise.shape[1]), "action_dim": int(noise.shape[2]),
           "tight": {"method": "dop853-ps float64", "tol": args.tight_tol, "windows": int(len(sub)),
                     "couplings": int(len(rows)), "evals_per_coupling": tight_evals, "seconds": tight_s,
                     "max_abs_diff_vs_100x_looser": tight_check},
           "reference_error": ref_err, "calibration": calibration, "rows": table, "levers": levers,
           "best_at_equal_accuracy": None if best_equal is None else
           {"method": best_equal["method"], "speedup": best_equal["speedup"]},
           "batch_independence": independence, "oscillation_in_t": oscillation,
           "network_row_cost": row_cost,
           "wall_s": time.perf_counter() - started}
    if args.save:
        args.save.write_text(json.dumps(out, indent=2))
    if args.json:
        print(json.dumps(out, indent=2))
        return
    report(out)


def report(out: dict) -> None:
    m, tight = out["machine"], out["tight"]
    print(f"reflow coupling generation, Push-T low-dim; {m['processor']}, {m['cpu_count']} CPUs, "
          f"{m['torch_threads']} torch threads, torch {m['torch']}, scipy {m['scipy']}, "
          f"device cpu{' + cuda ' + m['cuda'] if m['cuda'] else ' (no CUDA)'}")
    print(f"host 1-min load average {m['loadavg_1min_start_end'][0]:.2f} at start, "
          f"{m['loadavg_1min_start_end'][1]:.2f} at end (> 0 before we start = other processes "
          f"sharing the {m['cpu_count']} CPUs); whole run {out['wall_s']:.0f} s")
    print(f"policy: {out['checkpoint']} ({out['params'] / 1e6:.2f} M params); setup {out['setup_s']:.0f} s")
    print(f"{out['windows']} of {out['train_windows']} training windows x K={out['samples_per_window']} = "
          f"{out['couplings']} couplings of ({out['horizon']}, {out['action_dim']}), t {out['t0']:g} -> 1; "
          f"reference: scipy RK45 rtol={out['rtol']:g} atol={out['atol']:g}, batch {out['ref_batch']}")
    print(f"accuracy yardstick: {tight['method']} tol {tight['tol']:g} on the {tight['couplings']} couplings "
          f"of {tight['windows']} windows ({tight['evals_per_coupling']:.0f} evals/coupling, "
          f"{tight['seconds']:.0f} s; vs tol {tight['tol'] * 100:g}: max |diff| "
          f"{tight['max_abs_diff_vs_100x_looser']:.1e}); errors below are |x - x_tight|, normalized units")
    print()
    print("calibration (run once each; a family stops at its first setting at equal accuracy):")
    print(f"  {'setting':22s} {'evals/coupl':>11s} {'calls':>6s} {'mean err':>9s} {'max err':>9s}")
    for c in out["calibration"]:
        print(f"  {c['setting']:22s} {c['evals_per_coupling']:11.1f} {c['calls']:6d} {c['mean_err']:9.2e} "
              f"{c['max_err']:9.2e}  {'<= reference' if c['equal_accuracy'] else ''}")
    print()
    print(f"timed, best of {out['repeat']} interleaved runs (all runs' seconds in --json):")
    print(f"  {'method':44s} {'dev':4s} {'coupl/s':>8s} {'calls':>6s} {'evals/coupl':>11s} "
          f"{'mean err':>9s} {'max err':>9s} {'equal acc':>9s} {'speedup':>8s}")
    for r in out["rows"]:
        print(f"  {r['method']:44s} {r['device']:4s} {r['couplings_per_s']:8.1f} {r['calls']:6d} "
              f"{r['evals_per_coupling']:11.1f} {r['mean_err']:9.2e} {r['max_err']:9.2e} "
              f"{'yes' if r['equal_accuracy'] else 'no':>9s} {r['speedup']:7.2f}x")
    print()
    print("levers (ratio of best times, and of sample-evaluations per coupling):")
    for lv in out["levers"]:
        print(f"  {lv['lever']:76s} {lv['time_factor']:5.2f}x time, {lv['evals_factor']:5.2f}x evals")
    b = out["best_at_equal_accuracy"]
    print(f"best at equal accuracy: {b['method']}, {b['speedup']:.2f}x the reference" if b else
          "no configuration reached the reference's accuracy")
    ind, osc = out["batch_independence"], out["oscillation_in_t"]
    print(f"a chunk solved alone vs inside a batch ({ind['chunks']} chunks): the network's output for "
          f"a row differs by up to {ind['network_row_max_abs_diff']:.1e} (batched matmul rounding); "
          f"couplings:")
    for x in ind["settings"]:
        print(f"  {x['setting']:22s} {x['bit_identical']}/{ind['chunks']} bit-identical, "
              f"max |diff| {x['max_abs_diff']:.1e}")
    print("the network alone, per row: " + "; ".join(
        f"batch {c['batch']}: {c['us_per_row']:.1f} us" + (f" ({c['gflops']:.0f} GFLOP/s)" if c["gflops"] else "")
        for c in out["network_row_cost"]))
    print(f"velocity along t at fixed x ({osc['chunks']} chunks): {osc['oscillation_share']:.0%} of its "
          f"variation is faster than a degree-8 polynomial in t; the time embedding's fastest feature "
          f"turns at {osc['fastest_embedding_rad_per_t']:.0f} rad per unit t = "
          f"{osc['periods_on_interval']:.0f} periods on [t0, 1]")


if __name__ == "__main__":
    main()

"""The golden run: every existing way of training a policy, on tiny settings, from one base.

Each policy's weights (model and EMA: SHA-256 of their tensors, and per tensor its norm and a
fixed random projection) and the chunks it samples for fixed observations and noise are recorded
in tests/data/golden_run.json, one record per environment. tests/test_golden_run.py checks that
the same code paths still give the same results:

- bit for bit where a record's environment is this one: the torch and numpy builds, the kernels
  PyTorch picks (`torch.backends.cpu.get_cpu_capability()`, which `ATEN_CPU_CAPABILITY` lowers),
  the CPU (its model and the instruction sets its BLAS dispatches on) and 1 thread;
- within `TOLERANCE` elsewhere: another CPU's kernels round differently (a chunk value of 607.4450
  against 607.4451), so exact bits there would fail on every machine but the recorder's, while a
  tolerance this tight still fails on any change of code path (a changed loss, init, draw order
  or sampler moves these numbers by their own size, not by 1e-5 of it).

`python tests/golden_run.py --write` adds or replaces this environment's record, keeping the
others; record only when a change of results is intended (say so in the commit), and then
drop the records of the environments that were not run again (`--only-this`).

    flow       the base rectified flow (t ~ U[t_eps, 1], MSE)
    ddpm       the diffusion baseline (epsilon prediction, DP's scheduler)
    reflowed   a reflowed flow on the flow's couplings (uniform t, encoder frozen)
    student1   the reference one-step student (t = 0, MSE, one Euler step)
    student2   a two-step student (t on the Euler grid of two steps)
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
EXPECTED = REPO / "tests" / "data" / "golden_run.json"
TINY = ["shape_meta.obs.keypoint.type=low_dim", "shape_meta.obs.state.dims=[0,2]",
        "policy.head=mlp", "policy.mlp_hidden_dims=[32,32]", "policy.time_embed_dim=16",
        "training.batch_size=32", "training.max_steps=6", "training.val_every=6",
        "training.checkpoint_every=6", "training.val_sample_windows=4", "training.val_batches=1",
        "training.lr=1e-3", "training.lr_warmup_steps=2"]


# Relative to each number's own size, plus an absolute floor for values near 0; measured drift
# between kernel sets on one machine and across machines is below 1e-6 relative (the chunks'
# 4th decimal), a change of code path moves them by O(1) relative.
TOLERANCE = {"rel": 1e-4, "abs": 1e-3}


def digest(path: Path) -> str:
    """SHA-256 of a safetensors file's tensors, by name (not of the file: its header order and
    metadata are the writer's business)."""
    from safetensors.torch import load_file

    h = hashlib.sha256()
    for name, t in sorted(load_file(str(path)).items()):
        h.update(name.encode())
        h.update(t.contiguous().numpy().tobytes())
    return h.hexdigest()


def fingerprint(path: Path) -> dict[str, list[float]]:
    """Per tensor, by name: [its L2 norm, its projection on a fixed Gaussian vector], in float64.
    What a tolerance can compare where the bits differ: the projection moves by the tensor's own
    norm when its values change, not only its scale."""
    from safetensors.torch import load_file

    out = {}
    for name, t in sorted(load_file(str(path)).items()):
        v = t.detach().to(torch.float64).flatten().numpy()
        probe = np.random.default_rng(v.size).standard_normal(v.size)
        out[name] = [float(np.linalg.norm(v)), float(v @ probe)]
    return out


def close(got, want, rel: float = TOLERANCE["rel"], abs_: float = TOLERANCE["abs"]) -> bool:
    """Every number in two nested lists/dicts of the same shape within rel * |want| + abs_."""
    if isinstance(want, dict):
        return isinstance(got, dict) and got.keys() == want.keys() and all(
            close(got[k], want[k], rel, abs_) for k in want)
    if isinstance(want, list):
        return isinstance(got, list) and len(got) == len(want) and all(
            close(g, w, rel, abs_) for g, w in zip(got, want))
    if isinstance(want, str):
        return got == want
    return abs(got - want) <= rel * abs(want) + abs_


def run(ws: Path, data: Path, extra: tuple[str, ...] = ()) -> dict:
    """`extra`: settings added to every training (the test of the tolerance changes one)."""
    from sefa_pipelines.stages import reflowed_flow_config, student_config
    from sefa_data.ingest import IngestOptions, ingest
    from sefa_model.config import load_train_config
    from sefa_model.data.couplings import PairSource
    from sefa_model.policy.artifact import Policy
    from sefa_model.sefa.reflow import CouplingConfig, generate_couplings
    from sefa_model.train.loop import train

    store = ws / "dataset.zarr"
    ingest([data / "pusht_cchi_v7_replay.zarr"], store,
           IngestOptions(fps=10, keys=["keypoint", "state", "action"]))
    tiny = TINY + list(extra)
    base = load_train_config(None, tiny)
    train(base, ws / "flow", store)
    train(load_train_config(None, tiny + ["objective=ddpm", "diffusion.inference_steps=4"]),
          ws / "ddpm", store)
    flow = ws / "flow" / "checkpoints" / "latest"
    generate_couplings(Policy.load(flow, device="cpu"), store, ws / "couplings.zarr",
                       CouplingConfig(samples_per_window=2, solver="euler", steps=3, max_windows=16))
    pairs = lambda kind: PairSource.couplings(ws / "couplings.zarr", kind)  # noqa: E731
    train(reflowed_flow_config(base, []), ws / "reflowed", store, init_from=flow,
          couplings=pairs("reflow"), features_cache=ws / "features")
    train(student_config(base, []), ws / "student1", store, init_from=flow,
          couplings=pairs("reflow_one_step"), features_cache=ws / "features")
    train(student_config(base, [], steps=2), ws / "student2", store, init_from=flow,
          couplings=pairs("reflow_one_step"), features_cache=ws / "features")
    out = {}
    gen = np.random.default_rng(0)
    obs = {"keypoint": gen.uniform(0, 500, (2, 9, 2)).astype(np.float32),
           "state": gen.uniform(0, 500, (2, 5)).astype(np.float32)}
    for name in ("flow", "ddpm", "reflowed", "student1", "student2"):
        ckpt = ws / name / "checkpoints" / "latest"
        policy = Policy.load(ckpt, device="cpu")
        solver = {"flow": ("euler", 3), "reflowed": ("euler", 2), "ddpm": ("ddim", 4)}.get(name, (None, None))
        noise = torch.from_numpy(np.random.default_rng(1).standard_normal(
            (1, 16, 2)).astype(np.float32))
        chunk = policy.predict_action({k: v[None] for k, v in obs.items()}, solver=solver[0],
                                      steps=solver[1], noise=noise).action_pred
        out[name] = {"model": digest(ckpt / "model.safetensors"),
                     "ema": digest(ckpt / "ema.safetensors"),
                     "kind": json.loads((ckpt / "config.json").read_text())["kind"],
                     "chunk": np.asarray(chunk, dtype=np.float64).round(4).tolist(),
                     "weights": {"model": fingerprint(ckpt / "model.safetensors"),
                                 "ema": fingerprint(ckpt / "ema.safetensors")}}
    return out


def cpu_model() -> str:
    """The CPU's model name (Linux's /proc/cpuinfo, else platform's) and the instruction sets
    oneDNN/MKL dispatch on, which the ATen capability alone does not pin down."""
    import platform

    name, flags = platform.processor() or platform.machine(), set()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            key, _, value = line.partition(":")
            if key.strip() == "model name":
                name = value.strip()
            elif key.strip() == "flags":
                flags = set(value.split())
    except OSError:
        pass
    isa = [f for f in ("avx2", "fma", "avx512f", "avx512_bf16", "avx512_vnni", "amx_tile")
           if f in flags]
    return " ".join([name, *isa])


def environment() -> dict:
    """What decides the bits of a CPU run at 1 thread (the golden run sets it)."""
    return {"torch": torch.__version__, "numpy": np.__version__,
            "cpu_capability": torch.backends.cpu.get_cpu_capability(), "cpu": cpu_model(),
            "threads": 1}


def records() -> list[dict]:
    return json.loads(EXPECTED.read_text())["records"] if EXPECTED.exists() else []


def compare(got: dict, want: dict, exact: bool) -> list[str]:
    """The policies whose results differ from a record: all of their fields bit for bit when
    `exact`, else the chunks and weight fingerprints within TOLERANCE (and the kinds)."""
    bad = []
    for name, w in want.items():
        g = got.get(name)
        if g is None:
            bad.append(f"{name}: not run")
        elif exact and g != w:
            bad.append(f"{name}: not bit for bit ("
                       + ", ".join(k for k in w if g.get(k) != w[k]) + " differ)")
        elif not exact and not (g["kind"] == w["kind"] and close(g["chunk"], w["chunk"])
                                and close(g["weights"], w["weights"])):
            bad.append(f"{name}: beyond the tolerance {TOLERANCE}")
    return bad


if __name__ == "__main__":
    import tempfile

    ap = argparse.ArgumentParser()
    ap.add_argument("--write", action="store_true", help="add or replace this environment's record")
    ap.add_argument("--only-this", action="store_true",
                    help="with --write: drop the other environments' records (results changed)")
    args = ap.parse_args()
    sys.path.insert(0, str(REPO))
    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        result = {"environment": environment(), "policies": run(Path(tmp), REPO.parent / "shared" / "data")}
    for rec in records():
        exact = rec["environment"] == result["environment"]
        print(f"against {rec['environment']}: {'exact' if exact else 'tolerance'}:",
              compare(result["policies"], rec["policies"], exact) or "same")
    if args.write:
        kept = [] if args.only_this else [r for r in records()
                                          if r["environment"] != result["environment"]]
        EXPECTED.write_text(json.dumps({"records": kept + [result]}, indent=1) + "\n")
        print(f"wrote {EXPECTED}: {len(kept) + 1} record(s)")

"""The golden run: every existing way of training a policy, on tiny settings, from one base.

Each policy's weights (model and EMA, SHA-256 of their tensors) and the chunks it samples for
fixed observations and noise are recorded in tests/data/golden_run.json. They were written
before policies became methods (sefa_model/methods/); tests/test_golden_run.py checks that the
same code paths still give the same bits. Run `python tests/golden_run.py --write` to record
them again (only when a change of results is intended, and say so in the commit).

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


def digest(path: Path) -> str:
    """SHA-256 of a safetensors file's tensors, by name (not of the file: its header order and
    metadata are the writer's business)."""
    from safetensors.torch import load_file

    h = hashlib.sha256()
    for name, t in sorted(load_file(str(path)).items()):
        h.update(name.encode())
        h.update(t.contiguous().numpy().tobytes())
    return h.hexdigest()


def run(ws: Path, data: Path) -> dict:
    from sefa_pipelines.stages import reflowed_flow_config, student_config
    from sefa_data.ingest import IngestOptions, ingest
    from sefa_model.config import load_train_config
    from sefa_model.couplings import PairSource
    from sefa_model.policy import Policy
    from sefa_model.reflow import CouplingConfig, generate_couplings
    from sefa_model.training import train

    store = ws / "dataset.zarr"
    ingest([data / "pusht_cchi_v7_replay.zarr"], store,
           IngestOptions(fps=10, keys=["keypoint", "state", "action"]))
    base = load_train_config(None, TINY)
    train(base, ws / "flow", store)
    train(load_train_config(None, TINY + ["objective=ddpm", "diffusion.inference_steps=4"]),
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
                     "chunk": np.asarray(chunk, dtype=np.float64).round(4).tolist()}
    return out


def environment() -> dict:
    return {"torch": torch.__version__, "numpy": np.__version__}


if __name__ == "__main__":
    import tempfile

    ap = argparse.ArgumentParser()
    ap.add_argument("--write", action="store_true")
    args = ap.parse_args()
    sys.path.insert(0, str(REPO))
    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        result = {"environment": environment(), "policies": run(Path(tmp), REPO.parent / "shared" / "data")}
    if args.write:
        EXPECTED.write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps(result, indent=1)[:3000])

"""How closely the one-step students of benchmarks/students_study.py reproduce their RK45 teacher,
offline, and how cheap a teacher solve can be (docs/results/pusht.md, "Where the reference student
loses" and "A cheaper teacher solve"):

    python benchmarks/students_fit.py -w W [--rows reference_plain reference_aligned ...]
    python benchmarks/students_fit.py -w W --tolerances

W is the students study's workspace (its base flow `train`, its couplings `reflow/iter_1`, its
rows in W/rows37). Errors are mean squared errors per element in normalized action units.

Fit: each student against the teacher on N (observation, noise) pairs of three kinds: couplings
it trained on (the stored RK45 chunks), training windows reflow did not use with fresh noise, and
validation windows with fresh noise (the teacher solved with RK45 at 1e-5). `base_euler1` is the
teacher's own single Euler step. A student that fits its couplings much better than the unseen
windows generalizes from too few observations.

Tolerances: the first 128 windows' couplings (K as stored) solved again, same noise, at looser
RK45 tolerances and with fixed-step solvers, against the stored RK45 1e-5 chunks: error and NFE.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

TOLERANCES = [("rk45 1e-5", dict(solver="rk45", rtol=1e-5, atol=1e-5)),
              ("rk45 1e-4", dict(solver="rk45", rtol=1e-4, atol=1e-4)),
              ("rk45 1e-3", dict(solver="rk45", rtol=1e-3, atol=1e-3)),
              ("rk45 1e-2", dict(solver="rk45", rtol=1e-2, atol=1e-2)),
              ("rk4-8", dict(solver="rk4", steps=8)), ("rk4-16", dict(solver="rk4", steps=16)),
              ("euler-32", dict(solver="euler", steps=32))]


def mse(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.mean((a - b) ** 2))


class Bench:
    """The teacher, its data and its stored couplings, loaded once."""

    def __init__(self, ws: Path):
        import zarr

        from sefa_data.store.zarr_store import EpisodeStore
        from sefa_model.policy.artifact import Policy
        from sefa_model.data.windows import PolicyData

        self.ws = ws
        self.teacher = Policy.load(ws / "train" / "checkpoints" / "latest", device="cpu")
        self.data = PolicyData(self.teacher.cfg, EpisodeStore.open(ws / "dataset.zarr"),
                               self.teacher.normalizer)
        g = zarr.open_group(str(ws / "reflow" / "iter_1" / "couplings.zarr"), mode="r")
        self.window, self.noise, self.action = g["window"][:], g["noise"][:], g["action"][:]

    def solve(self, policy, split, windows: np.ndarray, x0: np.ndarray, **solver):
        """The sampler's result (chunks .x, .nfe) on these windows from this noise."""
        from sefa_model.policy.sampling import resolve_solver

        obs, _ = self.data.tensors(split, windows, policy.device)
        if not solver:  # the policy's own sampler (a student's one step)
            name, steps = resolve_solver(policy.cfg, None, None)
            solver = dict(solver=name, steps=steps)
        with torch.inference_mode():
            return policy.model.sample(policy.model.encode(obs), torch.as_tensor(x0), **solver)

    def sample(self, policy, split, windows: np.ndarray, x0: np.ndarray, **solver) -> np.ndarray:
        return self.solve(policy, split, windows, x0, **solver).x.numpy()

    def fit(self, rows: list[str], n: int, seed: int = 0) -> dict:
        from sefa_model.policy.artifact import Policy
        rng = np.random.default_rng(seed)
        d, shape = self.data, self.action.shape[1:]
        used = set(self.window.tolist())
        unseen = rng.choice(np.array([w for w in range(len(d.train)) if w not in used]), n, replace=False)
        valid = rng.choice(len(d.valid), n, replace=False)
        x_u, x_v = (rng.standard_normal((n, *shape)).astype(np.float32) for _ in range(2))
        rk45 = dict(solver="rk45", rtol=1e-5, atol=1e-5)
        t_u = self.sample(self.teacher, d.train, unseen, x_u, **rk45)
        t_v = self.sample(self.teacher, d.valid, valid, x_v, **rk45)
        pick = rng.choice(len(self.window), n, replace=False)
        out = {}
        for row in rows:
            if row == "base_euler1":
                policy, solver = self.teacher, dict(solver="euler", steps=1)
            else:
                policy, solver = Policy.load(self.ws / "rows37" / row / "checkpoints" / "latest", device="cpu"), {}
            out[row] = {
                "trained couplings": mse(self.sample(policy, d.train, self.window[pick], self.noise[pick], **solver),
                                         self.action[pick]),
                "unseen training windows": mse(self.sample(policy, d.train, unseen, x_u, **solver), t_u),
                "validation windows": mse(self.sample(policy, d.valid, valid, x_v, **solver), t_v)}
            print(row, {k: round(v, 6) for k, v in out[row].items()}, flush=True)
        return out

    def tolerances(self, windows: int = 128) -> dict:
        k = int(np.sum(self.window == self.window[0]))
        n = windows * k
        out = {}
        for name, solver in TOLERANCES:
            r = self.solve(self.teacher, self.data.train, self.window[:n], self.noise[:n], **solver)
            out[name] = {"nfe_per_solve": int(r.nfe), "mse_to_rk45_1e-5": mse(r.x.numpy(), self.action[:n])}
            print(name, out[name], flush=True)
        return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("-w", "--workspace", type=Path, required=True)
    ap.add_argument("--rows", nargs="+", default=["reference_plain", "reference_aligned", "rfpp_plain",
                                                  "shortcut", "base_euler1"])
    ap.add_argument("--n", type=int, default=400, help="pairs of each kind")
    ap.add_argument("--tolerances", action="store_true", help="the teacher's solve at looser settings")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    bench = Bench(args.workspace.resolve())
    result = bench.tolerances() if args.tolerances else bench.fit(args.rows, args.n)
    if args.json:
        args.json.write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()

"""Reflow couplings: for every training window, K noises pushed through the learned flow.

Each block of windows is solved as ONE batched ODE on the model's device: the observation is
encoded once per window, repeated K times, and the solver integrates all B*K chunks together:
"rk45" with one shared step size, as the reference's flattened scipy solve, or "rk45-ps" /
"dop853-ps" with a step size per chunk (see sefa_model.flow.solvers).

On CUDA (unless `capture=False`) the velocity field replays a CUDA graph at every evaluation of
the whole-batch solvers (rk45, the fixed-step ones), one graph per block size, shared by every
block of that size (sefa_model/flow/cuda_graphs.py). It is how a solve runs, not what it computes,
so it is no setting of the couplings (their attributes record it as `cuda_graphs`).

The noise of window w in round r is drawn on the CPU from a generator seeded by (seed, r, w)
alone, and the blocks are fixed by the window list, not by the number of processes: under
torchrun rank i solves blocks i, i + N, ..., rank 0 gathers them, and the couplings are the
same as one process's. Each reflow round draws fresh noise.

With `blocks_dir` (the stage's build folder), every finished block is written there as it is
solved (`block_<start>.npz`, numpy arrays only, renamed into place complete), under a
`blocks.json` that names the settings and the policy's weights: a run interrupted by Ctrl-C
keeps them, and the next run with the same settings loads them instead of solving them again
(rk45's shared step size makes a block's result depend on the block's windows, so a kept
block is reused only for the same block, never re-cut). Each block file carries its windows
and a digest of its content, and is reused only once its windows, its noise (drawn again from
the seed) and its digest check out; a damaged one is solved again, with one line saying so
(`BlockStore`). The folder goes once the couplings are written. The couplings are written as a Zarr group:

    noise   (M, T, Da) float32   x0, the starting noise
    action  (M, T, Da) float32   the generated chunk x1, in normalized action space
    window  (M,) int64           the training window (row of the train SequenceSampler)
    attrs: the provenance (sefa_model/data/couplings.py), samples_per_window, solver, rtol, atol, t0, nfe (calls, total), sample_evals (rows
           evaluated, total), solves, source checkpoint, and `expert_drift`: how far the
           generated chunks lie from the expert chunk of their own window (the alignment
           metric: mean, quantiles, and the fraction within each of DRIFT_EPS)
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import time
from contextlib import nullcontext
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from sefa_data.store.journal import fault_point
from sefa_data.store.zarr_store import EpisodeStore
from sefa_model.data.couplings import chunk_distance, write_couplings
from sefa_model.flow.cuda_graphs import FieldGraphs
from sefa_model.data.features import cached_window_features
from sefa_model.policy.artifact import Policy
from sefa_model.policy.sampling import watching_solves
from sefa_model.progress import report
from sefa_data.errors import SefaInputError
from sefa_model.distributed import DistContext, context
from sefa_model.data.windows import PolicyData
from sefa_model.flow.solvers import ADAPTIVE
from sefa_model.train.batches import step_seed


DRIFT_EPS = (0.02, 0.05, 0.1, 0.2)


def expert_drift(generated: np.ndarray, expert: np.ndarray) -> dict:
    """Summary of the distances between generated chunks and their windows' expert chunks
    (both (M, T, Da), normalized): what selective alignment would replace at each eps."""
    d = chunk_distance(generated, expert).astype(np.float64)
    q = np.quantile(d, [0.1, 0.5, 0.9]) if len(d) else [float("nan")] * 3
    return {"mean": float(d.mean()) if len(d) else float("nan"),
            "q10": float(q[0]), "median": float(q[1]), "q90": float(q[2]),
            "within": {f"{e:g}": float((d < e).mean()) if len(d) else float("nan") for e in DRIFT_EPS}}


@dataclass
class CouplingConfig:
    samples_per_window: int = 10  # K, the reference's sample_per_cond
    solver: str = "rk45"  # any of sefa_model.flow.solvers.METHODS; rk45 is the reference's
    rtol: float = 1e-5
    atol: float = 1e-5
    steps: int | None = None  # fixed-step solvers only
    batch_windows: int = 256  # windows per solve; each solve integrates batch_windows * K chunks
    max_windows: int | None = None  # a deterministic subset of the training windows (quick runs)
    seed: int = 0
    iteration: int = 1  # the reflow round: every round draws fresh noise


def window_noise(seed: int, iteration: int, windows: np.ndarray, k: int, shape: tuple[int, int]
                 ) -> torch.Tensor:
    """(len(windows) * k, *shape) standard normal noise, K rows per window, each window's rows
    drawn on the CPU from its own generator: independent of blocks, ranks and devices."""
    out = torch.empty(len(windows) * k, *shape)
    gen = torch.Generator()
    for i, w in enumerate(windows):
        gen.manual_seed(step_seed(seed, int(w), 7000 + iteration))
        out[i * k:(i + 1) * k] = torch.randn(k, *shape, generator=gen)
    return out


def window_subset(n: int, max_windows: int | None) -> np.ndarray:
    """Every window, or `max_windows` evenly spread ones (deterministic, covers all episodes)."""
    if max_windows is None or max_windows >= n:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, max_windows).round().astype(np.int64))


BLOCKS_INFO = "blocks.json"


def weights_digest(model: torch.nn.Module) -> str:
    """sha256 of a model's parameters and buffers, by name: the policy whose blocks they are."""
    h = hashlib.sha256()
    for name, t in sorted(model.state_dict().items()):
        h.update(name.encode())
        h.update(t.detach().float().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()


def block_digest(window: np.ndarray, noise: np.ndarray, action: np.ndarray, nfe: int,
                 evals: int) -> str:
    """sha256 of a block's content, written with it and checked before it is reused."""
    h = hashlib.sha256()
    for a in (window.astype(np.int64), noise.astype(np.float32), action.astype(np.float32),
              np.array([nfe, evals], np.int64)):
        h.update(str(a.shape).encode())
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


class BlockStore:
    """Finished blocks of one coupling job in a folder: kept across an interrupt, reused by the
    next run of the same job (`identity`: the settings, windows and weights), else cleared.

    A block file carries what it was made from: its windows, its noise (which the job's seed and
    round determine per window: `window_noise`) and the digest of its whole content. Before a
    block is reused its file must read, hold exactly this block's windows and noise, and match
    its digest; anything else (a truncated or emptied file, a flipped bit, another block's file
    copied over it) is a damaged block, solved again with one line saying why."""

    def __init__(self, directory: Path, identity: dict, is_main: bool = True,
                 barrier: Callable[[], None] = lambda: None,
                 log: Callable[[str], None] = lambda _: None):
        self.dir = Path(directory)
        info = self.dir / BLOCKS_INFO
        if is_main:
            try:
                same = json.loads(info.read_text()) == identity
            except (OSError, ValueError):
                same = False
            if not same:  # other settings or weights: their blocks are not this job's
                if self.count():
                    log(f"{info}: missing, unreadable or made with other settings or weights: "
                        f"its {self.count()} kept block(s) of couplings are not reused")
                shutil.rmtree(self.dir, ignore_errors=True)
                self.dir.mkdir(parents=True)
                tmp = info.with_name(info.name + ".tmp")
                tmp.write_text(json.dumps(identity, indent=2))
                os.replace(tmp, info)
        barrier()

    def path(self, start: int) -> Path:
        return self.dir / f"block_{start:09d}.npz"

    def load(self, start: int, window: np.ndarray, noise: np.ndarray) -> tuple[tuple | None, str]:
        """((noise, action, nfe, sample_evals), "") for a kept block of these windows and this
        noise; (None, "") when none was kept; (None, why) for a damaged one."""
        path = self.path(start)
        if not path.exists():
            return None, ""
        try:
            with np.load(path, allow_pickle=False) as z:
                got = {k: z[k] for k in ("window", "noise", "action", "nfe", "sample_evals",
                                         "digest")}
        except KeyError as e:
            return None, f"no {e} array (a block written before blocks recorded it)"
        except Exception as e:  # noqa: BLE001  whatever a damaged zip raises: BadZipFile, EOFError, zlib.error, ...
            return None, f"not a whole .npz file ({type(e).__name__}: {' '.join(str(e).split())[:120]})"
        kept_window = got["window"]
        if kept_window.shape != window.shape or not np.array_equal(kept_window, window):
            held = (f"windows {kept_window[0]}-{kept_window[-1]}" if kept_window.ndim == 1
                    and len(kept_window) else f"window array {kept_window.shape}")
            return None, (f"it holds {held}, not this block's windows {window[0]}-{window[-1]} "
                          "(another block's file?)")
        if got["noise"].shape != noise.shape or not np.array_equal(got["noise"], noise):
            return None, "its noise is not this block's (the seed and round draw it per window)"
        nfe, evals = int(got["nfe"]), int(got["sample_evals"])
        if str(got["digest"]) != block_digest(window, got["noise"], got["action"], nfe, evals):
            return None, "its content does not match the digest written with it (changed since)"
        if got["action"].shape != noise.shape or not np.isfinite(got["action"]).all():
            return None, f"its chunks are {got['action'].shape} or not finite"
        return (got["noise"], got["action"], nfe, evals), ""

    def reuse(self, starts: list[int], windows: np.ndarray, size: int,
              noise_of: Callable[[np.ndarray], np.ndarray], log: Callable[[str], None]
              ) -> list[tuple]:
        """(start, noise, action, nfe, sample_evals) of each kept block among `starts` that
        checks out; a damaged one is said in one line, and left to be solved again."""
        out = []
        for b in starts:
            block = windows[b:b + size]
            found, damaged = self.load(b, block, noise_of(block))
            if found is not None:
                out.append((b, *found))
            elif damaged:
                log(f"{self.path(b)}: a damaged block of couplings, not reused ({damaged}): "
                    "solving it again")
        return out

    def save(self, start: int, window: np.ndarray, noise: np.ndarray, action: np.ndarray,
             nfe: int, evals: int) -> None:
        final = self.path(start)
        tmp = final.with_name(final.stem + ".tmp.npz")
        np.savez(tmp, window=window.astype(np.int64), noise=noise, action=action,
                 nfe=np.int64(nfe), sample_evals=np.int64(evals),
                 digest=np.array(block_digest(window, noise, action, nfe, evals)))
        os.replace(tmp, final)  # a block file is whole or absent

    def count(self) -> int:
        return len(list(self.dir.glob("block_*[0-9].npz")))


@torch.no_grad()
def generate_couplings(policy: Policy, store_path: Path, out: Path, cfg: CouplingConfig,
                       progress: Callable[[int, int], None] = lambda done, total: None,
                       ctx: DistContext | None = None, source: str | None = None,
                       features_cache: Path | None = None, blocks_dir: Path | None = None,
                       log: Callable[[str], None] = lambda _: None,
                       capture: bool = True) -> dict:
    """Write the couplings of `policy` on the store's training windows to `out` (atomically).
    Under torchrun every rank calls this with its own policy copy; rank 0 writes. `source`
    names the checkpoint in the attributes when `policy.path` is a temporary one. With
    `features_cache`, every window's condition is read from (or computed once into) that cache
    instead of encoding each block (sefa_model/data/features.py). `capture`: see the module's doc."""
    ctx = ctx or context()
    if not policy.model.method.solves_ode:
        raise SefaInputError(f"reflow needs a rectified-flow policy; this checkpoint is the "
                             f"{policy.model.method.name} baseline", file=policy.path)
    data = PolicyData(policy.cfg, EpisodeStore.open(store_path), policy.normalizer)
    windows = window_subset(len(data.train), cfg.max_windows)
    k = cfg.samples_per_window
    shape = (policy.cfg.policy.horizon, policy.cfg.shape_meta.action.shape[-1])
    blocks = list(range(0, len(windows), cfg.batch_windows))
    mine = ctx.shard(blocks)
    started = time.perf_counter()
    features = None
    if features_cache is not None:
        features = cached_window_features(policy.model, data, windows, policy.device,
                                          features_cache, is_main=ctx.is_main, barrier=ctx.barrier)
    kept = None
    if blocks_dir is not None:
        kept = BlockStore(blocks_dir, {
            "config": asdict(cfg), "windows": len(windows), "shape": list(shape),
            "weights": weights_digest(policy.model), "normalizer": policy.normalizer.digest()},
            is_main=ctx.is_main, barrier=ctx.barrier, log=log)
    graphs = FieldGraphs() if capture and policy.device.type == "cuda" else None
    solved = []  # (block start, noise, action, nfe)
    reused = []
    if kept is not None:  # kept blocks first: the clock then measures solved blocks only
        solved = kept.reuse(mine, windows, cfg.batch_windows, lambda block: window_noise(
            cfg.seed, cfg.iteration, block, k, shape).numpy(), log)
        reused = [s[0] for s in solved]
    done = min(len(windows), sum(len(windows[b:b + cfg.batch_windows]) for b in reused) * ctx.world)
    if reused and ctx.is_main:
        log(f"reusing {len(reused)} of {len(blocks)} blocks of couplings kept by an interrupted "
            f"run ({done} windows); solving the other {len(blocks) - len(reused)}")
    if ctx.is_main:  # the bar from the first second, its clock including the first block
        report("couplings", done, len(windows), couplings=done * k)
    reused_set = set(reused)
    for b in (x for x in mine if x not in reused_set):
        block = windows[b:b + cfg.batch_windows]
        watch = _within_block(done, len(block), len(windows), k) if ctx.is_main else None
        solved.append(_solve_block(policy, data, features, windows, b, cfg, shape, graphs, watch))
        if kept is not None:
            start, noise, action, nfe, evals = solved[-1]
            kept.save(start, block, noise, action, nfe, evals)
            fault_point("reflow.block")  # tests: a Ctrl-C right after a block is kept
        # rank 0 reports the whole job's progress, assuming the other ranks keep pace
        done = min(len(windows), done + len(block) * ctx.world)
        progress(done, len(windows))
        if ctx.is_main:
            report("couplings", done, len(windows), couplings=done * k,
                   NFE_per_solve=sum(s[3] for s in solved) / len(solved))
    parts = ctx.gather(solved)
    summary = None
    if ctx.is_main:
        solved = sorted((p for part in parts for p in part), key=lambda p: p[0])
        expert = data.expert_chunks(windows)
        drift = expert_drift(np.concatenate([s[2] for s in solved]), np.repeat(expert, k, axis=0))
        summary = _write(out, windows, k, solved, started, {
            "expert_drift": drift,
            "samples_per_window": k, "solver": cfg.solver, "rtol": cfg.rtol, "atol": cfg.atol,
            "steps": cfg.steps, "t0": policy.cfg.flow.time_span[0], "seed": cfg.seed,
            "iteration": cfg.iteration, "processes": ctx.world, "device": str(policy.device),
            "cuda_graphs": graphs is not None,
            "source_checkpoint": source or policy.path, "space": "normalized action",
            **data.provenance()})
        if kept is not None:
            summary["reused_blocks"] = len(reused)
    summary = ctx.broadcast(summary)
    if blocks_dir is not None and ctx.is_main:  # the couplings are written: the blocks go
        shutil.rmtree(blocks_dir, ignore_errors=True)
    return summary


def _within_block(done: int, size: int, windows: int, k: int) -> Callable[[int, int, int], None]:
    """The progress of a block being solved (a block of 256 windows may take minutes on a
    CPU): the windows done before it, and the block's share by how far its solve is (the
    flow's time), short of the whole block until it is written; `couplings` counts the
    written ones."""
    def on_call(calls: int, at: int, total: int) -> None:
        inside = min(size - 1, size * at // max(total, 1))
        report("couplings", min(windows, done + inside), windows, couplings=done * k,
               NFE_in_block=calls)
    return on_call


def _solve_block(policy: Policy, data: PolicyData, features, windows: np.ndarray, b: int,
                 cfg: CouplingConfig, shape: tuple[int, int], graphs: FieldGraphs | None = None,
                 watch: Callable[[int, int, int], None] | None = None) -> tuple:
    """(block start, noise, generated chunks, NFE, rows evaluated) of the block of windows
    starting at b: K noises per window, integrated through the policy's ODE; `watch` is told
    how far the solve is at each network evaluation (`watching_solves`)."""
    block, k = windows[b:b + cfg.batch_windows], cfg.samples_per_window
    if features is not None:
        cond = features[b:b + cfg.batch_windows].to(policy.device)
    else:
        obs, _ = data.tensors(data.train, block, policy.device)
        cond = policy.model.encode(obs)
    cond = cond.repeat_interleave(k, dim=0)  # (B*K, D)
    x0 = window_noise(cfg.seed, cfg.iteration, block, k, shape)
    with watching_solves(policy.model, watch) if watch is not None else nullcontext():
        result = policy.model.sample(cond, x0.to(policy.device, non_blocking=True),
                                     solver=cfg.solver,
                                     steps=None if cfg.solver in ADAPTIVE else cfg.steps,
                                     rtol=cfg.rtol, atol=cfg.atol, graphs=graphs)
    return b, x0.numpy(), result.x.float().cpu().numpy(), result.nfe, result.sample_evals


def _write(out: Path, windows: np.ndarray, k: int, solved: list, started: float,
           attrs: dict) -> dict:
    noise = np.concatenate([s[1] for s in solved])
    action = np.concatenate([s[2] for s in solved])
    nfe = sum(s[3] for s in solved)
    sample_evals = sum(s[4] for s in solved)
    m = len(noise)
    seconds = time.perf_counter() - started
    summary = {"n": m, "windows": int(len(windows)), **attrs, "nfe": nfe,
               "solves": len(solved), "nfe_per_solve": nfe / max(1, len(solved)),
               "sample_evals": sample_evals, "evals_per_coupling": sample_evals / max(1, m),
               "seconds": seconds, "couplings_per_s": m / seconds}
    write_couplings(out, noise, action, np.repeat(windows, k), summary)
    return summary

"""Why the one-step student loses to its RK45 teacher on Push-T low-dim: probes on a students
study's workspace (benchmarks/students_study.py; W has `sefa train`, `sefa reflow`, `sefa align`
and the all-window features cache that `sefa distill` leaves).

    python benchmarks/students_probes.py train -w W --out DIR --tag control
    python benchmarks/students_probes.py train -w W --out DIR --tag onpolicy --onpolicy-from CKPT
    python benchmarks/students_probes.py train -w W --out DIR --tag deeper --extra-blocks 3
    python benchmarks/students_probes.py support -w W --student CKPT_OR_PT --out FILE.json \
        [--onpolicy DIR/onpolicy_*.pt]
    python benchmarks/students_probes.py latency -w W --student DIR/deeper.pt --extra-blocks 3

`train` fits the reference student (MSE at t = 0, lr 1e-3 with 100 warm-up steps and a cosine
decay, AdamW, gradient clip 1, EMA: the stage's settings) in a plain loop on the aligned
couplings, and rolls it out on the Push-T test seeds (from 100000; --eval). The loop is this
script's own so that couplings without a training window can join the batch:
  --onpolicy-from CKPT   on-policy couplings: CKPT is rolled out on --scenes training scenes (seeds
                         from 300000, never a test seed), every observation it met is labelled
                         by the teacher (RK45, rtol = atol = 1e-3) from --k fresh noises, and
                         --mix of each batch is drawn from them (DAgger's idea, for a distiller)
  --extra-blocks N       N more residual blocks before the output layer, each the identity at
                         initialisation (its last layer zero), so the student starts as the
                         teacher with more capacity
`support` compares the student's chunks with the teacher's on observations the student never
trained on (expert windows outside the couplings, and observations of on-policy rollouts):
the error d(S(x0), T(x0)), how much of it falls where the teacher's chunk moves fastest with its
noise, and whether the student's chunk leaves the set of chunks the teacher makes (its distance
to the nearest of K other teacher chunks, against the same for a teacher chunk). Distances are
sefa's chunk distance (sefa_model.data.couplings.chunk_distance), in normalized action space.
`latency` times a student's batch-1 predict_action beside the reference student's (one process,
alternated, the fastest p50 of 3 passes).
"""

from __future__ import annotations

import argparse
import copy
import json
import time
from pathlib import Path

import numpy as np
import torch

FIRST_COLLECT_SEED = 300000  # training scenes for on-policy couplings; test seeds start at 100000
RK = {"solver": "rk45", "rtol": 1e-3, "atol": 1e-3}  # the couplings' tolerance (students_fit --tolerances)


def log(msg: str) -> None:
    print(time.strftime("%H:%M:%S"), msg, flush=True)


def deepen(model, n: int):
    """n more FiLM blocks of the last width before the output layer, each the identity at
    initialisation (fc2 zero, identity residual)."""
    from sefa_model.nets.networks import _FiLMMlpBlock

    head = model.head
    width, cond_dim = head.out.in_features, head.blocks[-1].film.in_features
    for _ in range(n):
        block = _FiLMMlpBlock(width, width, cond_dim)
        torch.nn.init.zeros_(block.fc2.weight)
        torch.nn.init.zeros_(block.fc2.bias)
        head.blocks.append(block)
    return model


def load_student(ws: Path, path: str, extra_blocks: int = 0):
    """A sefa checkpoint, or a .pt state of this script for the reference student's network."""
    from sefa_model.policy.artifact import Policy

    if not path.endswith(".pt"):
        return Policy.load(path, device="cpu")
    policy = Policy.load(ws / "rows37" / "reference_aligned" / "checkpoints" / "latest", device="cpu")
    policy.model = deepen(policy.model, extra_blocks)
    policy.model.load_state_dict(torch.load(path, weights_only=True))
    policy.model.eval()
    return policy


def window_features(ws: Path) -> torch.Tensor:
    """(N, D): the frozen condition of every training window, from the features cache entry
    that holds all N windows (N: the couplings' `window_spec.n_train_windows`)."""
    import zarr
    from safetensors.numpy import load_file

    spec = dict(zarr.open_group(str(ws / "align" / "aligned.zarr"), mode="r").attrs)["window_spec"]
    every = np.arange(spec["n_train_windows"])
    for meta in sorted((ws / "features").glob("*/meta.json")):
        if json.loads(meta.read_text())["windows"] != len(every):
            continue
        entry = load_file(str(meta.parent / "features.safetensors"))
        if np.array_equal(entry["windows"], every):
            return torch.from_numpy(entry["features"])
    raise SystemExit(f"{ws}/features: no cache entry of all {len(every)} training windows "
                     "(sefa distill writes it)")


def chunk_shape(policy) -> tuple[int, int]:
    return policy.cfg.policy.horizon, policy.cfg.shape_meta.action.shape[-1]


@torch.inference_mode()
def chunks(policy, cond: torch.Tensor, x0: torch.Tensor, **solve) -> torch.Tensor:
    """The policy's chunks (normalized) from noises x0 under conditions cond, in batches."""
    out = torch.empty_like(x0)
    for i in range(0, len(x0), 4096):
        out[i:i + 4096] = policy.model.sample(cond[i:i + 4096], x0[i:i + 4096], **solve).x
    return out


def onpolicy_couplings(ws: Path, teacher, source: str, scenes: int, k: int, out: Path) -> dict:
    """The observations `source` meets on training scenes, each labelled by the teacher from k
    noises; cached in out/."""
    from sefa_sim.pusht import PushTEnv, rollout
    from sefa_sim.rollouts import pusht_policy_fn

    cache = out / f"onpolicy_{Path(source).parent.parent.name}_{scenes}x{k}.pt"
    if cache.exists():
        return torch.load(cache, weights_only=True)
    policy, env, keypoint, state = load_student(ws, source), PushTEnv(), [], []
    for seed in range(FIRST_COLLECT_SEED, FIRST_COLLECT_SEED + scenes):
        act = pusht_policy_fn(policy, None, None, seed)

        def recorded(history, act=act):
            keypoint.append(np.asarray(history["keypoint"], np.float32))
            state.append(np.asarray(history["state"], np.float32))
            return act({"keypoint": history["keypoint"], "state": history["state"]})
        rollout(recorded, seed, max_steps=300, n_obs_steps=2, n_action_steps=8, env=env)
    log(f"{len(keypoint)} observations from {scenes} scenes; labelling each from {k} noises")
    with torch.inference_mode():
        cond = teacher.model.encode(teacher.prepare_obs({"keypoint": np.stack(keypoint),
                                                         "state": np.stack(state)}))
    cond = cond.repeat_interleave(k, 0)
    x0 = torch.randn((len(cond),) + chunk_shape(teacher), generator=torch.Generator().manual_seed(7))
    pairs = {"cond": cond, "x0": x0, "x1": chunks(teacher, cond, x0, **RK)}
    torch.save(pairs, cache)
    return pairs


def grouped_rows(n_windows: int, k: int, group: int, windows: int, gen: torch.Generator
                 ) -> torch.Tensor:
    """(windows * group,) coupling rows: `windows` windows drawn at random, `group` of each one's
    k rows (rows w*k ... w*k + k - 1) without replacement, window by window."""
    w = torch.randint(n_windows, (windows,), generator=gen)
    pick = torch.rand(windows, k, generator=gen).argsort(dim=1)[:, :group]
    return (w[:, None] * k + pick).reshape(-1)


def energy_score(s: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """The energy score of the student's chunks s against the teacher's t, per observation:
    s, t (W, G, n), G chunks of each of W observations. E|S - T| - 1/2 E|S - S'| over the
    pairs of one observation (S' another of its student chunks), distances as RMS over the n
    elements (the scale of the chunk distance). A proper scoring rule: its expectation is
    lowest when the student's chunks of an observation are distributed as the teacher's, so
    unlike the MSE it does not pay to pull a chunk towards the observation's mean."""
    g = s.shape[1]
    cross = rms_distances(s, t).mean(dim=(1, 2))
    own = rms_distances(s, s).sum(dim=(1, 2)) / (g * (g - 1))  # the mean over pairs i != j
    return (cross - 0.5 * own).mean()


def rms_distances(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """(W, G, n), (W, G, n) -> (W, G, G): the RMS difference of every pair within an observation.
    Not torch.cdist: its gradient at a zero distance (the diagonal of a against itself) is NaN;
    the 1e-12 keeps the square root's gradient finite there."""
    return ((a[:, :, None] - b[:, None]).pow(2).mean(-1) + 1e-12).sqrt()


def train_student(ws: Path, teacher, a, onpolicy: dict | None):
    """The reference student's loss and schedule in a plain loop; returns its EMA network."""
    import zarr

    from sefa_model.train.ema import EMA
    from sefa_model.train.batches import cosine_with_warmup

    aligned = zarr.open_group(str(ws / "align" / "aligned.zarr"), mode="r")
    cond = window_features(ws)[aligned["window"][:]]
    x0, x1 = torch.from_numpy(aligned["noise"][:]), torch.from_numpy(aligned["target"][:])
    model = deepen(copy.deepcopy(teacher.model), a.extra_blocks).train()
    model.obs_encoder.requires_grad_(False)
    params = [p for p in model.parameters() if p.requires_grad]
    opt = torch.optim.AdamW(params, lr=a.lr, betas=(0.95, 0.999), eps=1e-8, weight_decay=1e-6)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, cosine_with_warmup(100, a.steps))
    ema, gen, batch = EMA(model), torch.Generator().manual_seed(42 + a.seed), 256
    n_on = int(round(batch * a.mix)) if onpolicy else 0
    k = len(x0) // len(np.unique(aligned["window"][:]))  # rows per window, contiguous
    for step in range(1, a.steps + 1):
        if a.energy is not None:  # a.group rows of each of batch / a.group windows
            i = grouped_rows(len(cond) // k, k, a.group, batch // a.group, gen)
        else:
            i = torch.randint(len(cond), (batch - n_on,), generator=gen)
        c, b0, b1 = cond[i], x0[i], x1[i]
        if n_on:
            j = torch.randint(len(onpolicy["cond"]), (n_on,), generator=gen)
            c = torch.cat([c, onpolicy["cond"][j]])
            b0, b1 = torch.cat([b0, onpolicy["x0"][j]]), torch.cat([b1, onpolicy["x1"][j]])
        v = model.velocity(b0, torch.zeros(batch), c)
        loss = torch.nn.functional.mse_loss(v, b1 - b0)
        if a.energy:
            pred, n = b0 + v, v[0].numel()  # the one-step chunks
            loss = loss + a.energy * energy_score(pred.view(-1, a.group, n), b1.view(-1, a.group, n))
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(params, 1.0)
        opt.step()
        sched.step()
        ema.update(model, step)
        if step % 500 == 0:
            log(f"step {step}/{a.steps}: loss {loss.item():.5f}")
    return ema.model


def cmd_train(a) -> None:
    from sefa_model.policy.artifact import Policy
    from sefa_sim.pusht import FIRST_TEST_SEED, PushTEnv, rollout
    from sefa_sim.rollouts import pusht_policy_fn

    ws, out = Path(a.workspace), Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    teacher = Policy.load(ws / "train" / "checkpoints" / "latest", device="cpu")
    if a.energy is not None and (a.onpolicy_from or 256 % a.group):
        raise SystemExit("--energy: --group must divide the batch (256), without --onpolicy-from")
    onpolicy = (onpolicy_couplings(ws, teacher, a.onpolicy_from, a.scenes, a.k, out)
                if a.onpolicy_from else None)
    state = out / f"{a.tag}.pt"
    if not state.exists():
        started = time.perf_counter()
        torch.save(train_student(ws, teacher, a, onpolicy).state_dict(), state)
        log(f"{a.tag}: {a.steps} steps in {time.perf_counter() - started:.0f} s")
    policy, env, per_seed = load_student(ws, str(state), a.extra_blocks), PushTEnv(), []
    for seed in range(FIRST_TEST_SEED, FIRST_TEST_SEED + a.eval):
        r = rollout(pusht_policy_fn(policy, None, None, seed), seed, max_steps=300,
                    n_obs_steps=2, n_action_steps=8, env=env)
        per_seed.append({"seed": seed, "score": r["score"], "success": r["success"]})
    score = float(np.mean([p["score"] for p in per_seed]))
    (out / f"{a.tag}.json").write_text(json.dumps({"args": vars(a), "score": score, "per_seed": per_seed}))
    log(f"{a.tag}: score {score:.4f} over {a.eval} test seeds")


def nearest(x: torch.Tensor, ref: torch.Tensor) -> np.ndarray:
    """(n, k, T, Da), (n, k, T, Da) -> (n * k,): each chunk's chunk distance to the nearest of
    the k reference chunks of its own observation."""
    n, k, t, da = x.shape
    d = torch.cdist(x.permute(0, 2, 1, 3).reshape(n * t, k, da), ref.permute(0, 2, 1, 3).reshape(n * t, k, da))
    return d.reshape(n, t, k, k).mean(1).min(-1).values.flatten().numpy()


def quantiles(x: np.ndarray) -> dict:
    return {"mean": float(x.mean()), **{f"p{p}": float(np.quantile(x, p / 100)) for p in (50, 90, 99)}}


def compare(teacher, student, cond: torch.Tensor, k: int, delta: float, gen) -> dict:
    from sefa_model.data.couplings import chunk_distance

    n, shape = len(cond), chunk_shape(teacher)
    c = cond.repeat_interleave(k, 0)
    a, b, d = (torch.randn((n * k,) + shape, generator=gen) for _ in range(3))
    d = delta * d / d.flatten(1).norm(dim=1)[:, None, None]
    ta, tb, td = (chunks(teacher, c, x, **RK) for x in (a, b, a + d))
    sa = chunks(student, c, a)  # the student's own sampler (its checkpoint's: one step)
    err = chunk_distance(sa.numpy(), ta.numpy())
    steep = chunk_distance(td.numpy(), ta.numpy()) / delta
    top = steep >= np.quantile(steep, 0.9)
    off_s, off_t = (nearest(x.reshape((n, k) + shape), tb.reshape((n, k) + shape)) for x in (sa, ta))
    # the spread of an observation's chunks over its noises, and whether the student's error
    # points from the teacher's chunk toward the mean of that observation's teacher chunks
    per_obs = lambda x: x.reshape((n, k) + shape)  # noqa: E731
    spread = lambda x: float(per_obs(x).std(1).mean())  # noqa: E731
    to_mean = (per_obs(ta).mean(1, keepdim=True) - per_obs(ta)).reshape(n * k, -1)
    towards = torch.nn.functional.cosine_similarity((sa - ta).reshape(n * k, -1), to_mean).mean()
    return {"observations": n, "noises": k, "error": quantiles(err),
            "error_share_in_steepest_tenth": float(err[top].sum() / err.sum()),
            "corr_error_steepness": float(np.corrcoef(err, steep)[0, 1]),
            "off_set_student": quantiles(off_s), "off_set_teacher": quantiles(off_t),
            "student_beyond_teacher_p90": float((off_s > np.quantile(off_t, 0.9)).mean()),
            "spread_over_noises": {"teacher": spread(ta), "student": spread(sa)},
            "cos_error_towards_teacher_mean": float(towards)}


def cmd_support(a) -> None:
    import zarr

    from sefa_model.policy.artifact import Policy

    ws = Path(a.workspace)
    teacher = Policy.load(ws / "train" / "checkpoints" / "latest", device="cpu")
    student = load_student(ws, a.student, a.extra_blocks)
    gen = torch.Generator().manual_seed(5)
    features = window_features(ws)
    trained = set(zarr.open_group(str(ws / "align" / "aligned.zarr"), mode="r")["window"][:].tolist())
    unseen = torch.tensor([i for i in range(len(features)) if i not in trained])
    sets = {"expert windows outside the couplings": features[unseen[torch.randperm(len(unseen), generator=gen)[:a.n]]]}
    if a.onpolicy:
        cond = torch.load(a.onpolicy, weights_only=True)["cond"][::a.onpolicy_k]
        sets["observations of on-policy rollouts"] = cond[torch.randperm(len(cond), generator=gen)[:a.n]]
    report = {}
    for name, cond in sets.items():
        report[name] = compare(teacher, student, cond, a.k, a.delta, gen)
        log(f"{name}: {json.dumps(report[name])}")
    Path(a.out).write_text(json.dumps({"student": a.student, "delta": a.delta, "report": report}, indent=1))


def p50_ms(policy, calls: int = 300) -> float:
    """Batch-1 predict_action on a fixed Push-T observation, p50 over `calls` after a warm-up."""
    obs = {"keypoint": np.full((2, 9, 2), 256.0, np.float32), "state": np.full((2, 5), 256.0, np.float32)}
    for _ in range(20):
        policy.predict_action(obs)
    times = []
    for _ in range(calls):
        started = time.perf_counter()
        policy.predict_action(obs)
        times.append(time.perf_counter() - started)
    return float(np.percentile(times, 50) * 1e3)


def cmd_latency(a) -> None:
    """The student's p50 beside the reference student's, alternated in one process."""
    ws = Path(a.workspace)
    student = load_student(ws, a.student, a.extra_blocks)
    reference = load_student(ws, str(ws / "rows37" / "reference_aligned" / "checkpoints" / "latest"))
    rows = {"student": [], "reference": []}
    for _ in range(3):
        rows["student"].append(p50_ms(student))
        rows["reference"].append(p50_ms(reference))
    weights = {k: sum(p.numel() for p in m.model.parameters()) for k, m in (("student", student), ("reference", reference))}
    print(json.dumps({"p50_ms_fastest_of_3": {k: min(v) for k, v in rows.items()}, "weights": weights}))


def main() -> None:
    torch.set_num_threads(1)
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    t = sub.add_parser("train")
    t.add_argument("-w", "--workspace", required=True)
    t.add_argument("--out", required=True)
    t.add_argument("--tag", required=True)
    t.add_argument("--steps", type=int, default=2000)
    t.add_argument("--lr", type=float, default=1e-3)
    t.add_argument("--extra-blocks", type=int, default=0)
    t.add_argument("--energy", type=float, default=None,
                   help="add this weight times the energy score (per observation, over --group "
                        "of its couplings in each batch); 0: the grouped batches alone")
    t.add_argument("--group", type=int, default=8, help="couplings per window in a batch (--energy)")
    t.add_argument("--onpolicy-from", default=None)
    t.add_argument("--scenes", type=int, default=500)
    t.add_argument("--k", type=int, default=4)
    t.add_argument("--mix", type=float, default=0.5)
    t.add_argument("--eval", type=int, default=500)
    t.add_argument("--seed", type=int, default=0, help="the training's seed: batches (42 + seed) and "
                   "the extra blocks' initialisation")
    s = sub.add_parser("support")
    s.add_argument("-w", "--workspace", required=True)
    s.add_argument("--student", required=True)
    s.add_argument("--extra-blocks", type=int, default=0)
    s.add_argument("--out", required=True)
    s.add_argument("--onpolicy", default=None, help="an on-policy couplings file of `train`")
    s.add_argument("--onpolicy-k", type=int, default=4)
    s.add_argument("--n", type=int, default=300)
    s.add_argument("--k", type=int, default=32)
    s.add_argument("--delta", type=float, default=0.05)
    s.add_argument("--seed", type=int, default=0)
    lat = sub.add_parser("latency")
    lat.add_argument("-w", "--workspace", required=True)
    lat.add_argument("--student", required=True)
    lat.add_argument("--extra-blocks", type=int, default=0)
    lat.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    torch.manual_seed(a.seed)  # the extra blocks' first layers are drawn from the global generator
    {"train": cmd_train, "support": cmd_support, "latency": cmd_latency}[a.cmd](a)


if __name__ == "__main__":
    main()

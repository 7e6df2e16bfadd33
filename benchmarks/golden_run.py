"""A golden run: the whole SeFA pipeline on Push-T, small and fully seeded, digested to sha256s.

A refactor that claims "no change in behaviour" runs this before and after and compares the
digests: every weight tensor of every stage, the couplings and the aligned targets must be bit
for bit the same. It runs through the real `sefa` command (ingest, train, reflow with two
rounds, align, distill) on one thread, so the numbers do not depend on the thread count.

    python benchmarks/golden_run.py -w /tmp/golden --out docs/data/golden_run.json
    python benchmarks/golden_run.py -w /tmp/golden2 --compare docs/data/golden_run.json

Sizes: base flow 200 steps; reflow K = 2 on 64 windows, a reflowed flow of 100 steps (round 2);
align at eps 0.5 (so that some chunks are replaced); a 100-step student. About 2 minutes.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
PUSHT = ROOT.parent / "shared" / "data" / "pusht_cchi_v7_replay.zarr"

PIPELINE = """\
threads: 1
train_config: {train_config}
train:
  - training.max_steps=200
  - training.val_every=100
  - training.checkpoint_every=100
  - training.lr_decay_steps=null
reflow:
  iters: 2
  samples_per_window: 2
  max_windows: 64
  seed: 0
  train_overrides:
    - training.max_steps=100
    - training.batch_size=64
    - training.val_every=100
    - training.checkpoint_every=100
align:
  eps: 0.5
distill:
  align: true
  train_overrides:
    - training.max_steps=100
    - training.batch_size=64
    - training.val_every=100
    - training.checkpoint_every=100
"""


def _sefa(*args: str) -> None:
    cmd = [str(Path(sys.executable).parent / "sefa"), *args]
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)


def run(workspace: Path) -> None:
    if workspace.exists():
        shutil.rmtree(workspace)
    workspace.mkdir(parents=True)
    pipeline = workspace.parent / f"{workspace.name}-pipeline.yaml"
    pipeline.write_text(PIPELINE.format(
        train_config=ROOT / "pipelines" / "pusht_lowdim_train.yaml"))
    _sefa("ingest", str(PUSHT), "--fps", "10", "--key", "keypoint", "--key", "state",
          "--key", "action", "-w", str(workspace))
    _sefa("run", str(pipeline), "--device", "cpu", "--threads", "1", "-w", str(workspace))


def _digest_safetensors(path: Path) -> dict[str, str]:
    from safetensors.numpy import load_file

    return {k: hashlib.sha256(np.ascontiguousarray(v).tobytes()).hexdigest()[:16]
            for k, v in sorted(load_file(str(path)).items())}


def _digest_zarr(path: Path) -> dict[str, str]:
    import zarr

    out = {}
    root = zarr.open_group(str(path), mode="r")

    def visit(group, prefix: str) -> None:
        for name, arr in sorted(group.arrays()):
            out[prefix + name] = hashlib.sha256(np.ascontiguousarray(arr[...]).tobytes()).hexdigest()[:16]
        for name, sub in sorted(group.groups()):
            visit(sub, prefix + name + "/")
    visit(root, "")
    return out


def digests(workspace: Path) -> dict[str, dict[str, str]]:
    """sha256 (16 hex digits) of every weight tensor and every couplings/aligned array."""
    out = {}
    for ckpt in sorted(workspace.glob("**/checkpoints/latest")):
        ckpt = ckpt.resolve()
        stage = ckpt.relative_to(workspace.resolve()).as_posix()
        for f in sorted(ckpt.glob("*.safetensors")):
            if f.name.startswith("optim"):
                continue
            out[f"{stage}/{f.name}"] = _digest_safetensors(f)
    for z in sorted(list(workspace.glob("**/couplings.zarr")) + list(workspace.glob("**/aligned.zarr"))):
        z = z.resolve()
        out[z.relative_to(workspace.resolve()).as_posix()] = _digest_zarr(z)
    return _by_stage(out)


def _by_stage(out: dict) -> dict:
    """Run ids are content hashes of the config: key digests by stage, not by run folder."""
    keyed = {}
    for path, d in out.items():
        parts = path.split("/")
        parts = [p for p in parts if not p.startswith("runs") and not _is_run_id(p)]
        keyed["/".join(parts)] = d
    return dict(sorted(keyed.items()))


def _is_run_id(part: str) -> bool:
    return len(part) == 12 and all(c in "0123456789abcdef" for c in part)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("-w", "--workspace", type=Path, required=True)
    ap.add_argument("--out", type=Path, help="write the digests here")
    ap.add_argument("--compare", type=Path, help="compare with digests written earlier")
    ap.add_argument("--no-run", action="store_true", help="digest an existing workspace")
    args = ap.parse_args()
    if not PUSHT.exists():
        sys.exit(f"error: {PUSHT} is missing (the golden run needs ../shared/data)")
    if not args.no_run:
        run(args.workspace)
    got = digests(args.workspace)
    n = sum(len(v) for v in got.values())
    print(f"{len(got)} artifacts, {n} arrays digested")
    if args.out:
        args.out.write_text(json.dumps(got, indent=1) + "\n")
        print(f"wrote {args.out}")
    if args.compare:
        want = json.loads(args.compare.read_text())
        diff = [f"{a}/{k}" for a in sorted(set(want) | set(got))
                for k in sorted(set(want.get(a, {})) | set(got.get(a, {})))
                if want.get(a, {}).get(k) != got.get(a, {}).get(k)]
        if diff:
            print(f"DIFFERENT: {len(diff)} of {n} arrays")
            for d in diff[:40]:
                print("  " + d)
            sys.exit(1)
        print(f"identical: all {n} arrays bit for bit")


if __name__ == "__main__":
    main()

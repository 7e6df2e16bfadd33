"""Frozen features against running the CNN every step, for the SeFA stages of an image policy.

    python benchmarks/bench_features.py [--preset pipelines/pusht_image_train.yaml]
        [--set policy.image_encoder=resnet18 ...] [--windows 512] [--steps 8] [--batch 64]
        [--device cpu] [--data DIR] [--json]

On the real Push-T image store (DIR/pusht_cchi_v7_replay.zarr: Diffusion Policy's pusht.zip
unpacks to pusht/; ingested into a temporary workspace) it makes a
base image policy (2 training steps: the weights do not change the timing), one-step couplings
of `--windows` training windows, and then times, in this one process:

- encode once: the frozen base encoder's features of those windows, written to the features
  cache (what the first SeFA stage pays), and reading them back (what every later stage pays);
- a distillation step with the frozen features (`training.freeze_encoder=true`, the default of
  the coupling stages) against one that runs the CNN forward and backward every step
  (`training.freeze_encoder=false`, fine-tuning): median wall time between optimizer steps.

The speed-up is the ratio of the two step times; "break-even steps" is after how many steps the
one-time encoding has paid for itself.
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

from sefa_data.bench.throughput import DEFAULT_DATA_DIR

REPO = Path(__file__).resolve().parents[1]
PUSHT_FILE = "pusht_cchi_v7_replay.zarr"


def step_times(cfg, out: Path, store: Path, **kwargs) -> list[float]:
    from sefa_model.train.loop import Callbacks, train

    stamps: list[float] = []
    train(cfg, out, store, callbacks=Callbacks(on_step=lambda *a: stamps.append(time.perf_counter())),
          **kwargs)
    # the last step also validates and writes the checkpoint: not a training step's cost
    return [b - a for a, b in zip(stamps, stamps[1:])][:-1]


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", type=Path, default=REPO / "pipelines" / "pusht_image_train.yaml")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="config overrides on top of the preset (e.g. policy.image_encoder=resnet18)")
    ap.add_argument("--windows", type=int, default=512)
    ap.add_argument("--steps", type=int, default=8, help="timed distillation steps per variant")
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA_DIR, help="the folder holding pusht_cchi_v7_replay.zarr (Diffusion Policy's pusht.zip unpacks to pusht/)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    pusht = args.data / PUSHT_FILE
    if not pusht.exists():
        sys.exit(f"error: {pusht} not found (Diffusion Policy's Push-T zarr: give its folder with --data)")

    from sefa_pipelines.stages import student_config
    from sefa_data.ingest import IngestOptions, ingest
    from sefa_model.config import load_train_config
    from sefa_model.data.features import cached_window_features
    from sefa_model.policy.artifact import Policy
    from sefa_model.sefa.reflow import CouplingConfig, generate_couplings
    from sefa_model.data.couplings import PairSource
    from sefa_model.data.windows import PolicyData
    from sefa_model.train.loop import train

    tmp = Path(tempfile.mkdtemp(prefix="bench_features_", dir="/dev/shm" if Path("/dev/shm").is_dir() else None))
    store = tmp / "dataset.zarr"
    ingest([pusht], store, IngestOptions(fps=10, keys=["img", "state", "action"]))
    quick = [f"training.device={args.device}", f"training.batch_size={args.batch}",
             "training.val_every=1000000", "training.checkpoint_every=1000000", "training.ema=false"]
    base_cfg = load_train_config(args.preset, args.set + quick + ["training.max_steps=2"])
    train(base_cfg, tmp / "base", store)
    base = Policy.load(tmp / "base", device=args.device)
    couplings = tmp / "couplings.zarr"
    generate_couplings(base, store, couplings, CouplingConfig(
        samples_per_window=1, solver="euler", steps=1, max_windows=args.windows))

    from sefa_data.store.zarr_store import EpisodeStore
    import zarr

    windows = zarr.open_group(str(couplings), mode="r")["window"][:]
    data = PolicyData(base.cfg, EpisodeStore.open(store), base.normalizer)
    cache = tmp / "features"
    t = time.perf_counter()
    cached_window_features(base.model, data, sorted(set(windows.tolist())), base.device, cache)
    encode_s = time.perf_counter() - t
    t = time.perf_counter()
    cached_window_features(base.model, data, sorted(set(windows.tolist())), base.device, cache)
    read_s = time.perf_counter() - t

    rows = {}
    for name, freeze in (("frozen_features", True), ("cnn_every_step", False)):
        cfg = student_config(load_train_config(args.preset, args.set + quick),
                             [f"training.max_steps={args.steps + 2}", f"training.freeze_encoder={str(freeze).lower()}"])
        gaps = step_times(cfg, tmp / name, store, init_from=tmp / "base" / "checkpoints" / "latest",
                          features_cache=cache, couplings=PairSource.couplings(couplings, "sefa_one_step"))
        rows[name] = statistics.median(gaps)
    speedup = rows["cnn_every_step"] / rows["frozen_features"]
    result = {
        "preset": str(args.preset.relative_to(REPO) if args.preset.is_relative_to(REPO) else args.preset),
        "overrides": args.set, "device": args.device, "batch": args.batch,
        "windows": int(len(set(windows.tolist()))), "timed_steps": args.steps,
        "encode_once_s": encode_s, "cache_read_s": read_s,
        "step_ms_frozen_features": 1e3 * rows["frozen_features"],
        "step_ms_cnn_every_step": 1e3 * rows["cnn_every_step"],
        "speedup": speedup,
        "break_even_steps": encode_s / max(1e-9, rows["cnn_every_step"] - rows["frozen_features"]),
    }
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        print(f"{result['preset']} {' '.join(args.set)} on {args.device}, batch {args.batch}, "
              f"{result['windows']} windows")
        print(f"  encode once      {encode_s:8.2f} s   (read back from the cache: {read_s:.3f} s)")
        print(f"  step, features   {result['step_ms_frozen_features']:8.1f} ms")
        print(f"  step, CNN        {result['step_ms_cnn_every_step']:8.1f} ms")
        print(f"  speed-up         {speedup:8.1f} x   (break-even after "
              f"{result['break_even_steps']:.0f} steps)")
    import shutil

    shutil.rmtree(tmp, ignore_errors=True)
    return result


if __name__ == "__main__":
    main()

"""Load a dataset folder with LeRobot's own LeRobotDataset and report what LeRobot sees.

Runs under LeRobot's Python, not sefa's (LeRobot 0.6.1 needs Python >= 3.12):

    python3.12 -m venv lerobot-venv && lerobot-venv/bin/pip install "lerobot[dataset]==0.6.1"
    HF_HUB_OFFLINE=1 lerobot-venv/bin/python scripts/lerobot_check.py DATASET_DIR [--ref REF.npz] [--frames N] [--json]

REF.npz is what LeRobot should return (`python scripts/lerobot_ref.py STORE REF.npz`, with sefa).
Exit 0: LeRobot loaded every frame and (with --ref) the arrays match; 1: it did not (the reason
is the last line).

Checks: LeRobot opens it (meta/info.json, episodes, tasks, stats), every frame loads through
__getitem__ (videos decoded by LeRobot at each frame's timestamp, within its tolerance_s), shapes
and dtypes match info.json, episode_index/frame_index/timestamp are consistent with fps. With
--ref REF.npz (arrays named after features, plus episode_ends), low-dim features must equal the
reference exactly and image/video features must be within --max-pixel-diff (mean |diff| in 0..255).
"""
import argparse, json, sys
from pathlib import Path

import numpy as np


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("root", type=Path)
    ap.add_argument("--ref", type=Path)
    ap.add_argument("--max-pixel-diff", type=float, default=3.0)
    ap.add_argument("--frames", type=int, default=0,
                    help="load only this many frames, evenly spread (0: every frame)")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    import lerobot
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    info = json.loads((a.root / "meta" / "info.json").read_text())
    repo_id = info.get("repo_id") or f"local/{a.root.name}"
    ds = LeRobotDataset(repo_id, root=a.root)
    feats = {k: v for k, v in ds.features.items()
             if k not in ("timestamp", "frame_index", "episode_index", "index", "task_index")}
    report = {"lerobot": lerobot.__version__, "root": str(a.root), "codebase_version": info.get("codebase_version"),
              "fps": ds.fps, "frames": len(ds), "episodes": ds.num_episodes,
              "features": {k: [v["dtype"], list(v["shape"])] for k, v in feats.items()}, "problems": []}
    cols = {k: [] for k in feats}
    # episode boundaries and frame indices from LeRobot's own table (no video decoding)
    ep_col = np.asarray(ds.hf_dataset["episode_index"]).reshape(-1)
    fi_col = np.asarray(ds.hf_dataset["frame_index"]).reshape(-1)
    ends = [int(i) for i in np.flatnonzero(np.diff(ep_col)) + 1] + [len(ep_col)]
    starts = np.repeat(np.r_[0, ends[:-1]], np.diff(np.r_[0, ends]))
    bad = np.flatnonzero(fi_col != np.arange(len(fi_col)) - starts)
    if len(bad):
        report["problems"].append(f"frame {int(bad[0])}: frame_index {int(fi_col[bad[0]])} breaks its episode's count")
    idx = range(len(ds)) if a.frames <= 0 or a.frames >= len(ds) else \
        sorted(set(np.linspace(0, len(ds) - 1, a.frames).round().astype(int).tolist()))
    report["frames_loaded"] = len(idx)
    for i in idx:
        item = ds[i]
        fi = int(item["frame_index"])
        ts = float(item["timestamp"])
        if abs(ts - fi / ds.fps) > 1e-3:
            report["problems"].append(f"frame {i}: timestamp {ts:.4f}, expected {fi / ds.fps:.4f}")
        for k, v in feats.items():
            x = item[k].numpy() if hasattr(item[k], "numpy") else np.asarray(item[k])
            if v["dtype"] in ("video", "image"):   # LeRobot returns float CHW in [0, 1]
                x = np.round(np.moveaxis(x, 0, -1) * 255.0).astype(np.uint8)
            cols[k].append(x)
        if len(report["problems"]) > 20:
            break
    report["episode_ends"] = ends[:5] + (["..."] if len(ends) > 5 else [])
    if a.ref:
        ref = np.load(a.ref)
        if "episode_ends" in ref and list(ref["episode_ends"]) != ends:
            report["problems"].append(f"episode_ends differ: LeRobot {ends[:5]}..., reference {list(ref['episode_ends'][:5])}...")
        for k in feats:
            if k not in ref:
                continue
            got, want = np.stack(cols[k]), ref[k]
            if len(idx) != len(ds):
                want = want[list(idx)]
            if got.shape != want.shape:
                report["problems"].append(f"{k}: shape {got.shape}, reference {want.shape}")
            elif feats[k]["dtype"] in ("video", "image"):
                d = float(np.abs(got.astype(np.int16) - want.astype(np.int16)).mean())
                report[f"mean_abs_pixel_diff/{k}"] = round(d, 3)
                if d > a.max_pixel_diff:
                    report["problems"].append(f"{k}: mean |pixel diff| {d:.2f} > {a.max_pixel_diff}")
            elif not np.array_equal(got.astype(want.dtype), want):
                report["problems"].append(f"{k}: values differ from the reference (max |diff| "
                                          f"{float(np.abs(got.astype(np.float64) - want).max()):.3g})")
    ok = not report["problems"]
    if a.json:
        print(json.dumps(report, indent=1))
    else:
        for k, v in report.items():
            if k != "problems":
                print(f"{k}: {v}")
        for p in report["problems"]:
            print("problem:", p)
    print(f"LeRobot {lerobot.__version__}: {'OK' if ok else 'FAILED'}: {len(ds)} frames, {ds.num_episodes} episodes"
          + ("" if ok else f"; {report['problems'][0]}"))
    return 0 if ok else 1


if __name__ == "__main__":
    try:
        sys.exit(main())
    except Exception as e:  # the reason LeRobot refused the folder, as one line
        print(f"LeRobot refused the dataset: {type(e).__name__}: {e}")
        sys.exit(1)

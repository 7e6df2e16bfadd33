"""LeRobot in and out (issue 21): ingest speed against decoding alone, and conversion speed
against LeRobot's own writer.

    python benchmarks/bench_lerobot.py [--data ../shared/data] [--frames 2000] [--repeat 3]
                                       [--lerobot-python PY] [--json]

(a) LeRobot video ingest: PyAV decoding alone (every frame of lerobot_pusht_v30's AV1 video
    to an RGB array, as the reader decodes it) against `sefa ingest` of the whole dataset into
    a fresh store (in /dev/shm when there is one): frames/s and the ratio ingest / decoding
    (goal: at least 0.6).
(b) Conversion of a camera bag: the first Push-T episodes (at least --frames frames) written as
    a ROS 2 MCAP bag with JPEG images (`sefa_data.bench.pusht_bags`), converted by `sefa convert
    --to lerobot` (bag read, JPEG decoded, resampled, written as LeRobot v3.0 with AV1 video),
    against LeRobot 0.6.1's own writer (`add_frame`/`save_episode`/`finalize`) given the same
    frames already decoded in memory (benchmarks/lerobot_writer_baseline.py, run with
    LeRobot's Python: --lerobot-python, default the lerobot_check.sh venv). Frames/s and the
    ratio sefa / LeRobot (goal: above 1). Skipped with a reason when LeRobot's Python is absent.

Medians over --repeat runs; both sides run in this one invocation, on the same machine.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
VIDEO_DATASET = "lerobot_pusht_v30"
DEFAULT_LEROBOT_PY = Path(os.environ.get("LEROBOT_CHECK_VENV",
                                         Path.home() / ".cache/sefa-lerobot-check")) / "bin/python"


def scratch() -> Path:
    shm = Path("/dev/shm")
    return Path(tempfile.mkdtemp(dir=shm if shm.is_dir() else None, prefix="bench_lerobot-"))


def decode_alone(dataset: Path) -> tuple[int, float]:
    import av

    frames, start = 0, time.perf_counter()
    for video in sorted((dataset / "videos").rglob("*.mp4")):
        with av.open(str(video)) as c:
            stream = c.streams.video[0]
            stream.thread_type = "AUTO"
            for frame in c.decode(stream):
                frame.to_ndarray(format="rgb24")
                frames += 1
    return frames, time.perf_counter() - start


def ingest_run(dataset: Path) -> tuple[int, float]:
    from sefa_data.ingest import IngestOptions, ingest

    work = scratch()
    try:
        start = time.perf_counter()
        report = ingest([dataset], work / "store.zarr", IngestOptions())
        return report.inputs[0].frames, time.perf_counter() - start
    finally:
        shutil.rmtree(work, ignore_errors=True)


def camera_bag(data: Path, frames: int, work: Path):
    from sefa_data.bench import pusht_bags

    pf = pusht_bags.pusht_frames(data, frames)
    bag = pusht_bags.write_recording(work / "pusht_compressed_mcap", pf, "mcap", "compressed")
    tmap = work / "map.yaml"
    tmap.write_text(pusht_bags.topic_map_text("compressed", (96, 96)))
    np.savez(work / "frames.npz", img=pf.img, state=pf.state, action=pf.action,
             episode_ends=pf.episode_ends)
    return pf, bag, tmap


def convert_run(bag: Path, tmap: Path) -> tuple[int, float]:
    from sefa_data.ingest import IngestOptions
    from sefa_data.convert import convert_to_lerobot

    work = scratch()
    try:
        start = time.perf_counter()
        summary = convert_to_lerobot([bag], work / "lr", IngestOptions(topic_map=str(tmap)),
                                     ["Push the T-shaped block onto the target."])
        return summary["frames"], time.perf_counter() - start
    finally:
        shutil.rmtree(work, ignore_errors=True)


def lerobot_run(python: Path, frames_npz: Path) -> tuple[int, float]:
    work = scratch()
    try:
        out = subprocess.run([str(python), str(REPO / "benchmarks/lerobot_writer_baseline.py"),
                              str(frames_npz), str(work / "lr")], capture_output=True, text=True,
                             env={**os.environ, "HF_HUB_OFFLINE": "1", "SVT_LOG": "1"})
        if out.returncode:
            raise RuntimeError(f"LeRobot's writer failed: {out.stderr.strip().splitlines()[-1:]}")
        result = json.loads(out.stdout.strip().splitlines()[-1])
        return result["frames"], result["seconds"]
    finally:
        shutil.rmtree(work, ignore_errors=True)


def median_rate(run, repeat: int) -> dict:
    runs = [run() for _ in range(repeat)]
    rate = statistics.median(n / s for n, s in runs)
    return {"frames": runs[0][0], "frames_per_s": round(rate, 1),
            "seconds": [round(s, 2) for _, s in runs]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    ap.add_argument("--frames", type=int, default=2000)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--lerobot-python", type=Path, default=DEFAULT_LEROBOT_PY)
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    os.environ.setdefault("SVT_LOG", "1")
    dataset = a.data / VIDEO_DATASET
    result = {"ingest": {"decode_alone": median_rate(lambda: decode_alone(dataset), a.repeat),
                         "sefa_ingest": median_rate(lambda: ingest_run(dataset), a.repeat)}}
    r = result["ingest"]
    r["ratio"] = round(r["sefa_ingest"]["frames_per_s"] / r["decode_alone"]["frames_per_s"], 3)
    print(f"(a) LeRobot video ingest: decoding alone {r['decode_alone']['frames_per_s']} frames/s, "
          f"sefa ingest {r['sefa_ingest']['frames_per_s']} frames/s, ratio {r['ratio']} "
          "(goal >= 0.6)", flush=True)
    work = scratch()
    try:
        pf, bag, tmap = camera_bag(a.data, a.frames, work)
        c = result["convert"] = {"sefa_convert": median_rate(lambda: convert_run(bag, tmap), a.repeat)}
        if a.lerobot_python.is_file():
            c["lerobot_writer"] = median_rate(lambda: lerobot_run(a.lerobot_python,
                                                                   work / "frames.npz"), a.repeat)
            c["ratio"] = round(c["sefa_convert"]["frames_per_s"]
                               / c["lerobot_writer"]["frames_per_s"], 3)
            print(f"(b) camera bag -> LeRobot ({len(pf)} frames): sefa convert "
                  f"{c['sefa_convert']['frames_per_s']} frames/s, LeRobot 0.6.1 writer "
                  f"{c['lerobot_writer']['frames_per_s']} frames/s, ratio {c['ratio']} "
                  "(goal > 1)", flush=True)
        else:
            c["lerobot_writer"] = f"skipped: no LeRobot Python at {a.lerobot_python}"
            print(f"(b) sefa convert {c['sefa_convert']['frames_per_s']} frames/s; "
                  f"{c['lerobot_writer']}")
    finally:
        shutil.rmtree(work, ignore_errors=True)
    if a.json:
        print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()

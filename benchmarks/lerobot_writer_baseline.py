"""LeRobot 0.6.1's own writer on given frames: the baseline of benchmarks/bench_lerobot.py.

Runs under LeRobot's Python (>= 3.12, the venv of ../shared/tools/lerobot_check.sh), not sefa's:

    LEROBOT_PYTHON FRAMES.npz OUT_DIR

FRAMES.npz holds img (N, H, W, 3) uint8, state, action and episode_ends. The frames go through
`LeRobotDataset.create`, `add_frame` (with the task) per frame, `save_episode` per episode and
`finalize`, with LeRobot's defaults (AV1 video, libsvtav1, crf 30, g 2). Prints one JSON line:
frames, seconds (writing only: imports and loading the npz are not timed).
"""
import json
import sys
import time

import numpy as np


def main(frames_path: str, out: str) -> None:
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    f = np.load(frames_path)
    img, state, action, ends = f["img"], f["state"], f["action"], f["episode_ends"]
    features = {
        "observation.image": {"dtype": "video", "shape": list(img.shape[1:]),
                              "names": ["height", "width", "channel"]},
        "observation.state": {"dtype": "float32", "shape": [state.shape[1]], "names": None},
        "action": {"dtype": "float32", "shape": [action.shape[1]], "names": None}}
    start = time.perf_counter()
    ds = LeRobotDataset.create("local/baseline", fps=10, features=features, root=out,
                               use_videos=True)
    begin = 0
    for end in ends.tolist():
        for i in range(begin, end):
            ds.add_frame({"observation.image": img[i], "observation.state": state[i],
                          "action": action[i], "task": "Push the T-shaped block onto the target."})
        ds.save_episode()
        begin = end
    ds.finalize()
    print(json.dumps({"frames": int(ends[-1]), "seconds": time.perf_counter() - start}))


if __name__ == "__main__":
    main(*sys.argv[1:3])

"""Does this interpreter's onnxruntime load a `sefa export` ONNX file, and does it agree with
another runtime? Needs numpy and onnxruntime only (run it in an environment with the runtime a
robot has, e.g. `pip install onnxruntime==1.17.3`).

    python scripts/onnx_runtime_check.py deploy/onnx out.npy [--compare ref.npy]

Runs the artifact on fixed random inputs of its metadata's shapes (batch 3, seed 0), saves the
chunk to out.npy and, with --compare, prints the max |difference| from a chunk another runtime
saved the same way.
"""

import argparse
import json
from pathlib import Path

import numpy as np
import onnxruntime as ort

ap = argparse.ArgumentParser()
ap.add_argument("export", type=Path)
ap.add_argument("out", type=Path)
ap.add_argument("--compare", type=Path)
args = ap.parse_args()
meta = json.loads((args.export / "metadata.json").read_text())
rng = np.random.default_rng(0)
feed = {name: rng.standard_normal((3, *meta["obs"][key]["shape"])).astype(np.float32)
        for name, key in zip(meta["onnx_input_names"], meta["inputs"][:-1])}
feed["noise"] = rng.standard_normal((3, *meta["noise"]["shape"])).astype(np.float32)
session = ort.InferenceSession(str(args.export / "policy.onnx"), providers=["CPUExecutionProvider"])
chunk = session.run(["action_pred"], feed)[0]
np.save(args.out, chunk)
print(f"onnxruntime {ort.__version__}: loaded opset {meta.get('onnx_opset')}, IR "
      f"{meta.get('onnx_ir_version')}; chunk {chunk.shape}, finite {bool(np.isfinite(chunk).all())}")
if args.compare:
    print(f"max |difference| from {args.compare}: {np.abs(chunk - np.load(args.compare)).max():.3g}")

"""`sefa ARGS` run in this process through sefa_cli.main.main (no child's 3.5 s of imports): its
exit code, stdout and stderr, as a child process would give them. And a small real workspace
made with it: the KUKA LWR MCAP recording (../shared/data) with a tiny flow trained on it."""

from __future__ import annotations

import contextlib
import io
import sys
from dataclasses import dataclass
from pathlib import Path


@dataclass
class Result:
    returncode: int
    stdout: str
    stderr: str


def sefa(*args, ok: bool = True) -> Result:
    from sefa_cli.main import main

    out, err = io.StringIO(), io.StringIO()
    argv = sys.argv
    sys.argv = ["sefa", *map(str, args)]
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                main()
                code = 0
            except SystemExit as e:
                code = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
    finally:
        sys.argv = argv
    r = Result(code, out.getvalue(), err.getvalue())
    if ok:
        assert r.returncode == 0, r.stderr[-3000:]
    return r


JOINTS = ", ".join(f"lwr_arm_{i}_joint" for i in range(7))
# a 32x32 MLP flow, 20 steps, Euler-4 validation: seconds on a CPU
TINY_KUKA = ["policy.head=mlp", "policy.mlp_hidden_dims=[32,32]", "policy.time_embed_dim=16",
             "training.max_steps=20", "training.batch_size=32", "training.lr=1e-3",
             "training.lr_warmup_steps=2", "training.val_every=20", "training.checkpoint_every=20",
             "training.val_batches=1", "training.val_sample_windows=12", "flow.solver=euler",
             "flow.steps=4"]


def kuka_workspace(shared_data: Path, ws: Path) -> Path:
    """The KUKA MCAP ingested at 100 Hz (joint positions as observation and action; one episode,
    so a window-level validation split) and TINY_KUKA trained on it, in `ws`."""
    (ws / "map.yaml").write_text(f"""fps: 100
features:
  observation.joint_pos: {{topic: /joint_states, field: "position[{JOINTS}]"}}
  action: {{topic: /joint_states, field: "position[{JOINTS}]"}}
""")
    sefa("ingest", shared_data / "kuka_lwr_honeypot_ros2_mcap", "--map", ws / "map.yaml",
         "-w", ws)
    sefa("train", *TINY_KUKA, "--threads", "1", "-w", ws)
    return ws

"""Where a training's numbers go: `logs.jsonl` (the record the tools read), TensorBoard event
files, Weights & Biases when asked for, and a plot of the curves beside the log.

    RUN/logs.jsonl        one JSON record per log or validation step
    RUN/tensorboard/      event files: `tensorboard --logdir RUN` (or the workspace's runs/)
    RUN/curves.png        training loss and validation action MSE against the mean-action
                          baseline, redrawn at every checkpoint

TensorBoard is written through torch.utils.tensorboard (the `tensorboard` package, a core
dependency); W&B only with `training.wandb: PROJECT` and the `wandb` package installed. Only
rank 0 of a torchrun job makes a RunLog.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

from sefa_data.errors import ConfigError
from sefa_data import atomic

SERIES = ("train_loss", "lr", "val_loss", "val_action_mse", "val_mean_action_mse", "val_nfe")


class RunLog:
    def __init__(self, run_dir: Path, start_step: int, *, wandb_project: str | None = None,
                 config: dict | None = None):
        from torch.utils.tensorboard import SummaryWriter

        self.run_dir = Path(run_dir)
        self.path = self.run_dir / "logs.jsonl"
        truncate_log(self.path, start_step)
        # purge_step: a resumed run's events past its checkpoint are dropped, as in logs.jsonl;
        # TensorBoard drops steps >= purge_step, and the checkpoint's own step is kept
        self.tb = SummaryWriter(str(self.run_dir / "tensorboard"),
                                purge_step=start_step + 1 if start_step else None)
        self.wandb = None
        if wandb_project:
            try:
                import wandb
            except ImportError:
                raise ConfigError("training.wandb needs the wandb package (pip install wandb)",
                                  key="training.wandb") from None
            self.wandb = wandb.init(project=wandb_project, config=config, dir=str(self.run_dir),
                                    resume="allow")

    def record(self, record: dict) -> None:
        with open(self.path, "a") as fh:
            fh.write(json.dumps(record) + "\n")
        step = int(record["step"])
        for key in SERIES:
            if key in record and record[key] is not None and math.isfinite(float(record[key])):
                self.tb.add_scalar(key.replace("val_", "val/").replace("train_", "train/"),
                                   float(record[key]), step)
        if self.wandb is not None:
            self.wandb.log({k: record[k] for k in SERIES if k in record}, step=step)

    def checkpoint(self) -> None:
        """At a checkpoint: events on disk, the plot redrawn."""
        self.tb.flush()
        plot_curves(self.path, self.run_dir / "curves.png")

    def close(self) -> None:
        self.checkpoint()
        self.tb.close()
        if self.wandb is not None:
            self.wandb.finish()

    def abort(self) -> None:
        """A failed or interrupted run: the writers stop now, no plot; W&B marks it failed.
        TensorBoard's writer thread left running would flush into the unfinished run folder the
        caller then removes, and print a traceback under the one-line error."""
        self.tb.close()
        if self.wandb is not None:
            self.wandb.finish(exit_code=1)

    def __enter__(self) -> RunLog:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


def truncate_log(path: Path, step: int) -> None:
    """On resume, drop records past the checkpoint so the log reads as one run."""
    if not path.exists():
        return
    keep = [line for line in path.read_text().splitlines()
            if line.strip() and json.loads(line)["step"] <= step]
    path.write_text("".join(line + "\n" for line in keep))


def run_name(run_dir: Path) -> str:
    """A run's name as it will be once complete: a build folder `.<id>.partial` is run <id>."""
    name = run_dir.name
    if name.startswith(".") and name.endswith(".partial"):
        name = name[1:-len(".partial")]
    return name


def plot_curves(log: Path, out: Path) -> bool:
    """Training loss and validation action MSE (with the mean-action MSE it must beat) against
    the step, from logs.jsonl; written atomically. False when there is nothing to draw yet."""
    if not log.exists():
        return False
    records = [json.loads(line) for line in log.read_text().splitlines() if line.strip()]
    train = [(r["step"], r["train_loss"]) for r in records
             if "train_loss" in r and math.isfinite(r["train_loss"])]
    val = [(r["step"], r["val_action_mse"], r["val_mean_action_mse"]) for r in records
           if "val_action_mse" in r]
    if not train and not val:
        return False
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
    if train:
        axes[0].plot(*zip(*train), lw=1)
        axes[0].set_yscale("log")
    axes[0].set(title="training loss", xlabel="step")
    if val:
        steps, mse, mean = zip(*val)
        axes[1].plot(steps, mse, "o-", label="sampled chunks")
        axes[1].plot(steps, mean, "--", color="gray", label="mean action (baseline)")
        axes[1].legend()
    axes[1].set(title="validation action MSE", xlabel="step")
    fig.suptitle(run_name(log.parent))
    fig.tight_layout()
    with atomic.writing(out) as tmp:
        fig.savefig(tmp, dpi=90, format="png")
    plt.close(fig)
    return True

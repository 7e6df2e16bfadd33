"""LeRobot's config of a sefa policy (`"type": "sefa"` in config.json).

`sefa export --format lerobot` writes it (sefa_deploy/lerobot_export.py); LeRobot parses it with
draccus, so each field can be changed on LeRobot's command line: `--policy.execution=ensemble`,
`--policy.replan_every=2`, `--policy.ensemble_k=0.1`, `--policy.device=cuda`. The network, the
normalizer and the input map (`sefa`) are the export's and are not meant to be edited.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from lerobot.configs import PreTrainedConfig
from lerobot.configs.types import FeatureType

from sefa_deploy.execution import DEFAULT_ENSEMBLE_K, check_execution
from sefa_deploy.lerobot_format import ACTION, POLICY_TYPE

TRAIN_WITH_SEFA = ("sefa policies are trained with sefa (`sefa run`, `sefa train`), not inside "
                   "LeRobot; export one for LeRobot with `sefa export CHECKPOINT --format lerobot "
                   "--out DIR` and run it with --policy.path=DIR")


@PreTrainedConfig.register_subclass(POLICY_TYPE)
@dataclass
class SefaConfig(PreTrainedConfig):
    n_obs_steps: int = 2
    horizon: int = 16  # the chunk's length, from the first observed frame
    n_action_steps: int = 8  # the chunk's steps to execute, from the current frame on
    solver: str | None = None  # the sampler: the checkpoint's own (euler-1 for a student)
    steps: int | None = None
    # how select_action turns chunks into one action per step (sefa_deploy/execution.py):
    # receding (execute replan_every actions, then predict again) or ensemble (ACT's temporal
    # ensembling: predict every replan_every steps, execute the exp(-k i)-weighted mean)
    execution: str = "receding"
    replan_every: int | None = None  # default: n_action_steps (receding), 1 (ensemble)
    ensemble_k: float = DEFAULT_ENSEMBLE_K
    # the sampler's noise: None draws from torch's global generator (which lerobot-eval seeds
    # with --seed); a number seeds the policy's own generator at every reset, so that one
    # observation sequence gives the same actions every run
    noise_seed: int | None = None
    # the export's: the training config, the normalizer's modes, the input map, provenance
    sefa: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        super().__post_init__()
        try:
            check_execution(self.execution, self.replan_every, self.ensemble_k,
                            self.n_action_steps)
        except ValueError as e:  # "--replan-every: ..." in LeRobot's option names
            name, _, what = str(e).partition(": ")
            raise ValueError(f"--policy.{name.lstrip('-').replace('-', '_')}: {what}") from None

    @property
    def observation_delta_indices(self) -> list[int]:
        return list(range(1 - self.n_obs_steps, 1))

    @property
    def action_delta_indices(self) -> list[int]:
        return list(range(1 - self.n_obs_steps, 1 - self.n_obs_steps + self.horizon))

    @property
    def reward_delta_indices(self) -> None:
        return None

    def get_optimizer_preset(self):
        raise NotImplementedError(TRAIN_WITH_SEFA)

    def get_scheduler_preset(self):
        raise NotImplementedError(TRAIN_WITH_SEFA)

    def validate_features(self) -> None:
        """The features LeRobot passes (from the env or the robot) against the export's: one
        line naming the feature when the action's size or an input is missing."""
        if not self.sefa:
            raise ValueError(f"this config has no `sefa` section: {TRAIN_WITH_SEFA}")
        want = self.sefa["train_config"]["shape_meta"]["action"]["shape"][-1]
        action = (self.output_features or {}).get(ACTION)
        if action is None or action.type is not FeatureType.ACTION:
            raise ValueError(f"this sefa policy outputs '{ACTION}' ({want} values), which the "
                             f"output features lack: {sorted(self.output_features or {})}")
        if tuple(action.shape) != (want,):
            raise ValueError(f"'{ACTION}' has shape {tuple(action.shape)} here; this sefa policy "
                             f"outputs {want} values per step")
        missing = [m["feature"] for m in self.sefa["inputs"]
                   if m["feature"] not in (self.input_features or {})]
        if missing:
            raise ValueError(f"this sefa policy reads '{missing[0]}', which the input features "
                             f"lack: {sorted(self.input_features or {})} (LeRobot's "
                             "--rename_map maps names)")

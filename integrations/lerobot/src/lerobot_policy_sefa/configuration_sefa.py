"""LeRobot's config of a sefa policy (`"type": "sefa"` in config.json).

`sefa export --format lerobot` writes it (sefa_deploy/lerobot_export.py); LeRobot parses it with
draccus, so each field can be changed on LeRobot's command line: `--policy.execution.mode=ensemble`,
`--policy.execution.replan_every=2`, `--policy.noise_seed=0`, `--policy.device=cuda`. The
network, the normalizer and the input map (`sefa`) are the export's and are not meant to be
edited.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from lerobot.configs import PreTrainedConfig
from lerobot.configs.types import FeatureType

from sefa_data.errors import SefaInputError
from sefa_deploy.lerobot_format import ACTION, POLICY_TYPE
from sefa_model.policy.execution import FIELD, ExecutionSettings

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
    # how select_action turns chunks into one action per step: sefa's executor
    # (sefa_model/policy/execution.py) with these settings: mode receding (Diffusion Policy),
    # ensemble (ACT), coherent (Bidirectional Decoding's backward coherence among `samples`);
    # not bid, which needs a second policy
    execution: ExecutionSettings = field(default_factory=ExecutionSettings)
    # the sampler's noise: None draws from torch's global generator (which lerobot-eval seeds
    # with --seed); a number seeds the policy's own generator at every reset, so that one
    # observation sequence gives the same actions every run
    noise_seed: int | None = None
    # the export's: the training config, the normalizer's modes, the input map, provenance
    sefa: dict[str, Any] = field(default_factory=dict)

    def execution_settings(self) -> ExecutionSettings:
        """The executor's settings resolved for this policy; one line naming LeRobot's option
        (--policy.execution.replan_every, ...) when a value cannot work. Checked when the policy
        is made, not in __post_init__: draccus would replace the line with its own "Couldn't
        instantiate class SefaConfig"."""
        if self.execution.mode == "bid":
            raise ValueError("--policy.execution.mode: bid contrasts the policy with a weaker "
                             "one, which a sefa LeRobot folder does not carry (use receding, "
                             "ensemble or coherent)")
        # the steps executed from the current frame on must lie in the predicted chunk, which
        # starts n_obs_steps - 1 frames back (else select_action fails mid-episode)
        needed = self.n_obs_steps - 1 + self.n_action_steps
        if self.n_action_steps < 1:
            raise ValueError(f"--policy.n_action_steps: {self.n_action_steps} steps: a chunk "
                             "executes at least 1")
        if needed > self.horizon:
            raise ValueError(f"--policy.n_action_steps: {self.n_action_steps} steps from the "
                             f"current frame on need a chunk of {needed}, and the policy predicts "
                             f"horizon = {self.horizon} from n_obs_steps = {self.n_obs_steps} "
                             f"frames back (at most {self.horizon - self.n_obs_steps + 1})")
        try:
            return self.execution.resolved(self.n_action_steps)
        except SefaInputError as e:
            raise ValueError(f"--policy.execution.{FIELD.get(e.key, e.key)}: {e.what}") from None

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

"""LeRobot's pre- and postprocessor of a sefa policy: LeRobot's standard rename, batch and device
steps, no normalizer steps (the normalization is inside the policy; sefa_deploy/lerobot_format.py
says why). A loaded policy reads its own policy_preprocessor.json and
policy_postprocessor.json; this factory is what LeRobot calls for a config without them."""

from __future__ import annotations

from typing import Any

import torch

from lerobot.processor import (AddBatchDimensionProcessorStep, DeviceProcessorStep,
                               PolicyAction, PolicyProcessorPipeline,
                               RenameObservationsProcessorStep)
from lerobot.processor.factory import make_policy_processor_pipelines

from .configuration_sefa import SefaConfig


def make_sefa_pre_post_processors(
    config: SefaConfig,
    dataset_stats: dict[str, dict[str, torch.Tensor]] | None = None,
) -> tuple[PolicyProcessorPipeline[dict[str, Any], dict[str, Any]],
           PolicyProcessorPipeline[PolicyAction, PolicyAction]]:
    """`dataset_stats` is not used: the policy carries the normalizer it was trained with."""
    return make_policy_processor_pipelines(
        input_steps=[RenameObservationsProcessorStep(rename_map={}),
                     AddBatchDimensionProcessorStep(), DeviceProcessorStep(device=config.device)],
        output_steps=[DeviceProcessorStep(device="cpu")],
    )

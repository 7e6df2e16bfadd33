"""A policy: the model that owns its network, encoder and sampler (`model`), the observation and
action transforms (`processor`), the checkpoint on disk (`checkpoint`), the sampler a method
fixes (`sampling`) and `Policy`, a checkpoint loaded for inference (`artifact`).

    from sefa_model.policy import Policy
"""

from sefa_model.policy.artifact import Policy

__all__ = ["Policy"]

"""A policy: the model that owns its network, encoder and sampler (`model`), the observation and
action transforms (`processor`), the checkpoint on disk (`checkpoint`), the sampler a method
fixes (`sampling`), `Policy`, a checkpoint loaded for inference (`artifact`), and how its
chunks become one action per control step (`execution`).

    from sefa_model.policy import Policy
"""

__all__ = ["Policy"]


def __getattr__(name: str):
    # loaded on first use: `execution`'s settings are read by sefa.yaml's config, which must
    # not pay for importing torch
    if name == "Policy":
        from sefa_model.policy.artifact import Policy

        return Policy
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

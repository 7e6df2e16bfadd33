"""sefa_data: recordings in, a validated Diffusion-Policy-layout Zarr episode store out."""

from sefa_data.errors import ConfigError, SefaInputError

__all__ = ["ConfigError", "SefaInputError"]

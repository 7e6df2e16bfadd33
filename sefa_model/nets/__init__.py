"""The networks: Diffusion Policy's conditional U-Net and an MLP head (`networks`), and the
observation encoders (`encoders`). Nothing here imports sefa."""

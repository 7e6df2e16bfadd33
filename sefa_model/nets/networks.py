"""Velocity networks v(x_t, t, c) for rectified-flow action chunks.

Both heads share one call signature, the one Diffusion Policy uses for its noise predictor:

    head(sample: (B, T, Da), timestep: (B,) float, global_cond: (B, C)) -> (B, T, Da)

``sample`` is the interpolated action chunk x_t, ``timestep`` the flow time as the *caller*
scales it (SeFA feeds ``t * 999``; see ``SinusoidalPosEmb``) and ``global_cond`` the flattened
observation features of the To conditioning frames (DP's ``obs_as_global_cond``).

- ``ConditionalUnet1D``: DP's temporal U-Net. Conv1d + GroupNorm + Mish blocks, residual blocks
  with FiLM from [time embedding ; global cond], stride-2 down / transposed-conv up.
- ``MlpHead``: a small residual MLP over the flattened chunk, for fast low-dim experiments.
- ``build_head(kind, **kwargs)``: pick one by name from a config.
"""

from __future__ import annotations

import math

import torch
from torch import nn

__all__ = [
    "SinusoidalPosEmb",
    "Conv1dBlock",
    "ConditionalResidualBlock1D",
    "Downsample1d",
    "Upsample1d",
    "ConditionalUnet1D",
    "MlpHead",
    "HEADS",
    "build_head",
]


# --------------------------------------------------------------------------------------------
# Time embedding


class SinusoidalPosEmb(nn.Module):
    """Transformer-style sinusoidal embedding of a scalar per sample: (B,) -> (B, dim).

    The frequencies span 1 .. 1/10000, which resolves integer-like steps in [0, ~1000]. A flow
    time t in [0, 1] is therefore passed *already scaled* (``t * 999`` in SeFA and in DP-based
    RF code; Adroit uses ``t * 100``): with raw t in [0, 1] the low-frequency half of the
    embedding would be nearly constant and the network could barely tell times apart.
    """

    def __init__(self, dim: int):
        super().__init__()
        if dim < 4 or dim % 2:
            raise ValueError(f"SinusoidalPosEmb dim must be even and >= 4, got {dim}")
        self.dim = dim
        half = dim // 2
        # Geometric ladder of frequencies; a buffer so it follows .to(device) but is not trained.
        freqs = torch.exp(-math.log(10000.0) * torch.arange(half, dtype=torch.float32) / (half - 1))
        self.register_buffer("freqs", freqs, persistent=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x: (B,) float (scaled time) -> (B, dim) = [sin(x f) ; cos(x f)]."""
        # At least float32 (integer steps, half-precision models), float64 in a float64 model:
        # t * 999 rounded to float32 makes the field a staircase in t (steps ~6e-8 near t=1), which
        # a tight-tolerance reference solve of the flow ODE would otherwise keep resolving.
        args = x.to(torch.promote_types(self.freqs.dtype, torch.float32))[:, None] * self.freqs[None, :]
        return torch.cat([args.sin(), args.cos()], dim=-1)


def _time_mlp(dim: int, hidden: int) -> nn.Sequential:
    """Sinusoidal features -> learned embedding (B,) -> (B, dim), as in DP's diffusion_step_encoder."""
    return nn.Sequential(SinusoidalPosEmb(dim), nn.Linear(dim, hidden), nn.Mish(), nn.Linear(hidden, dim))


def _step_mlp(dim: int, hidden: int) -> nn.Sequential:
    """The step-size embedding of students that take one (shortcut, mean flow): as the time
    embedding, its last layer zero so that a new one adds nothing: the student starts as the
    base flow it is initialised from, at every step size."""
    mlp = _time_mlp(dim, hidden)
    nn.init.zeros_(mlp[-1].weight)
    nn.init.zeros_(mlp[-1].bias)
    return mlp


def _embed_time(time_encoder: nn.Module, step_encoder: nn.Module | None, timestep, step,
                batch: int, device: torch.device) -> torch.Tensor:
    """(B, time_embed_dim): the time's embedding, plus the step size's where the head has one
    (step None: 0, the instantaneous velocity)."""
    emb = time_encoder(_as_batch_timestep(timestep, batch, device))
    if step_encoder is not None:
        emb = emb + step_encoder(_as_batch_timestep(0.0 if step is None else step, batch, device))
    return emb


def _as_batch_timestep(timestep: torch.Tensor | float, batch: int, device: torch.device) -> torch.Tensor:
    """Accept (B,), a 0-d tensor or a Python number and return a (B,) float tensor (float32,
    or float64 when given float64: see SinusoidalPosEmb).

    Samplers often hold one t for the whole batch; broadcasting here keeps their code short.
    """
    t = torch.as_tensor(timestep, device=device)
    if t.ndim == 0:
        t = t.expand(batch)
    if t.ndim != 1 or t.shape[0] != batch:
        raise ValueError(f"timestep must be a scalar or shape ({batch},), got {tuple(t.shape)}")
    return t.to(torch.promote_types(t.dtype, torch.float32))


def _check_cond(global_cond: torch.Tensor | None, batch: int, dim: int) -> torch.Tensor | None:
    if dim == 0:
        if global_cond is not None and global_cond.numel() != 0:
            raise ValueError("this head was built with global_cond_dim=0 but got a global_cond")
        return None
    if global_cond is None:
        raise ValueError(f"global_cond of shape ({batch}, {dim}) is required")
    if global_cond.shape != (batch, dim):
        raise ValueError(f"global_cond must be ({batch}, {dim}), got {tuple(global_cond.shape)}")
    return global_cond


# --------------------------------------------------------------------------------------------
# U-Net building blocks (all on (B, C, T) tensors: channels = action/feature dims, T = horizon)


class Conv1dBlock(nn.Module):
    """Conv1d -> GroupNorm -> Mish: (B, C_in, T) -> (B, C_out, T). Odd kernel keeps T."""

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int, n_groups: int = 8):
        super().__init__()
        self.block = nn.Sequential(
            nn.Conv1d(in_channels, out_channels, kernel_size, padding=kernel_size // 2),
            # GroupNorm, not BatchNorm: statistics per sample, so EMA weights and batch-1
            # inference behave exactly like training.
            nn.GroupNorm(n_groups, out_channels),
            nn.Mish(),
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.block(x)


class ConditionalResidualBlock1D(nn.Module):
    """Two Conv1dBlocks with FiLM on the first one's output, plus a residual path.

    (B, C_in, T), cond (B, cond_dim) -> (B, C_out, T). With ``cond_predict_scale`` the condition
    predicts a per-channel scale and bias (FiLM); otherwise only a bias is added.
    """

    def __init__(self, in_channels: int, out_channels: int, cond_dim: int, kernel_size: int = 5,
                 n_groups: int = 8, cond_predict_scale: bool = True):
        super().__init__()
        self.out_channels = out_channels
        self.cond_predict_scale = cond_predict_scale
        self.conv1 = Conv1dBlock(in_channels, out_channels, kernel_size, n_groups)
        self.conv2 = Conv1dBlock(out_channels, out_channels, kernel_size, n_groups)
        film_dim = 2 * out_channels if cond_predict_scale else out_channels
        self.cond_encoder = nn.Sequential(nn.Mish(), nn.Linear(cond_dim, film_dim))
        # 1x1 conv only when the channel count changes; identity otherwise.
        self.residual = (nn.Conv1d(in_channels, out_channels, 1) if in_channels != out_channels
                         else nn.Identity())

    def forward(self, x: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        h = self.conv1(x)  # (B, C_out, T)
        film = self.cond_encoder(cond)[:, :, None]  # (B, film_dim, 1), broadcast over T
        if self.cond_predict_scale:
            scale, bias = film.chunk(2, dim=1)
            h = scale * h + bias
        else:
            h = h + film
        h = self.conv2(h)
        return h + self.residual(x)


class Downsample1d(nn.Module):
    """Stride-2 conv: (B, C, T) -> (B, C, T/2)."""

    def __init__(self, channels: int):
        super().__init__()
        self.conv = nn.Conv1d(channels, channels, 3, stride=2, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.conv(x)


class Upsample1d(nn.Module):
    """Transposed conv: (B, C, T) -> (B, C, 2T)."""

    def __init__(self, channels: int):
        super().__init__()
        self.conv = nn.ConvTranspose1d(channels, channels, 4, stride=2, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.conv(x)


# --------------------------------------------------------------------------------------------
# Heads


class ConditionalUnet1D(nn.Module):
    """Diffusion Policy's 1-D temporal U-Net over action chunks, used as a velocity field.

    Layout for ``down_dims = (d0, d1, d2)`` and horizon T (channels x length):

        in  Da x T
        down 0: Res(Da->d0), Res(d0->d0)   skip0 d0 x T     Down -> T/2
        down 1: Res(d0->d1), Res(d1->d1)   skip1 d1 x T/2   Down -> T/4
        down 2: Res(d1->d2), Res(d2->d2)   skip2 d2 x T/4   (no Down: deepest level)
        mid:    Res(d2->d2) x 2                              d2 x T/4
        up 0:   [x ; skip2] Res(2*d2->d1), Res(d1->d1)       Up -> T/2
        up 1:   [x ; skip1] Res(2*d1->d0), Res(d0->d0)       Up -> T
        out:    Conv1dBlock(d0->d0), Conv1d 1x1 (d0->Da)

    As in DP, each up level concatenates the skip taken at the *same* resolution before the
    upsample, so the full-resolution skip0 is never concatenated (the last Up restores T).
    We keep that layout on purpose: parameter counts and capacity then match DP's published
    configs. T must be divisible by 2 ** (len(down_dims) - 1) so every Down/Up pair round-trips.

    Every residual block is FiLM-conditioned on [time embedding (time_embed_dim) ; global_cond].
    """

    def __init__(self, input_dim: int, global_cond_dim: int, time_embed_dim: int = 256,
                 down_dims: tuple[int, ...] = (256, 512, 1024), kernel_size: int = 5,
                 n_groups: int = 8, cond_predict_scale: bool = True, step_input: bool = False):
        super().__init__()
        down_dims = tuple(int(d) for d in down_dims)
        if input_dim < 1:
            raise ValueError(f"input_dim must be >= 1, got {input_dim}")
        if global_cond_dim < 0:
            raise ValueError(f"global_cond_dim must be >= 0, got {global_cond_dim}")
        if not down_dims:
            raise ValueError("down_dims must name at least one level")
        if kernel_size < 1 or kernel_size % 2 == 0:
            raise ValueError(f"kernel_size must be odd so convs keep the horizon, got {kernel_size}")
        bad = [d for d in down_dims if d % n_groups]
        if bad:
            raise ValueError(f"every down_dims entry must be divisible by n_groups={n_groups}, got {bad}")

        self.input_dim = input_dim
        self.global_cond_dim = global_cond_dim
        self.down_dims = down_dims
        # Each level but the deepest halves T.
        self.horizon_multiple = 2 ** (len(down_dims) - 1)

        self.time_encoder = _time_mlp(time_embed_dim, 4 * time_embed_dim)
        self.step_encoder = _step_mlp(time_embed_dim, 4 * time_embed_dim) if step_input else None
        cond_dim = time_embed_dim + global_cond_dim

        def res(cin: int, cout: int) -> ConditionalResidualBlock1D:
            return ConditionalResidualBlock1D(cin, cout, cond_dim, kernel_size, n_groups,
                                              cond_predict_scale)

        dims = (input_dim,) + down_dims
        n_levels = len(down_dims)
        self.down_levels = nn.ModuleList()
        for i in range(n_levels):
            is_deepest = i == n_levels - 1
            self.down_levels.append(nn.ModuleList([
                res(dims[i], dims[i + 1]),
                res(dims[i + 1], dims[i + 1]),
                nn.Identity() if is_deepest else Downsample1d(dims[i + 1]),
            ]))

        mid = down_dims[-1]
        self.mid_blocks = nn.ModuleList([res(mid, mid), res(mid, mid)])

        # Up levels walk back from the deepest level; level i concatenates skip i+1 (same
        # resolution as x) and outputs down_dims[i] channels, then upsamples.
        self.up_levels = nn.ModuleList()
        for i in reversed(range(n_levels - 1)):
            self.up_levels.append(nn.ModuleList([
                res(2 * down_dims[i + 1], down_dims[i]),
                res(down_dims[i], down_dims[i]),
                Upsample1d(down_dims[i]),
            ]))

        self.final = nn.Sequential(
            Conv1dBlock(down_dims[0], down_dims[0], kernel_size, n_groups),
            nn.Conv1d(down_dims[0], input_dim, 1),
        )

    def check_horizon(self, horizon: int) -> None:
        """Raise ValueError unless a chunk of this length survives the down/up path unchanged."""
        m = self.horizon_multiple
        if horizon < m or horizon % m:
            raise ValueError(
                f"horizon T={horizon} is incompatible with {len(self.down_dims)} U-Net levels: "
                f"T must be a positive multiple of {m} (e.g. {m}, {2 * m}, {4 * m})")

    def forward(self, sample: torch.Tensor, timestep: torch.Tensor | float,
                global_cond: torch.Tensor | None = None, step: torch.Tensor | None = None
                ) -> torch.Tensor:
        """sample (B, T, Da), timestep (B,) scaled float, global_cond (B, C), step (B,) scaled
        step size (heads built with step_input) -> velocity (B, T, Da)."""
        if sample.ndim != 3 or sample.shape[-1] != self.input_dim:
            raise ValueError(f"sample must be (B, T, {self.input_dim}), got {tuple(sample.shape)}")
        batch, horizon, _ = sample.shape
        self.check_horizon(horizon)
        global_cond = _check_cond(global_cond, batch, self.global_cond_dim)

        cond = _embed_time(self.time_encoder, self.step_encoder, timestep, step, batch,
                           sample.device)  # (B, time_embed_dim)
        if global_cond is not None:
            cond = torch.cat([cond, global_cond.to(cond.dtype)], dim=-1)  # (B, cond_dim)

        x = sample.transpose(1, 2)  # (B, Da, T): convs run over time
        skips: list[torch.Tensor] = []
        for res1, res2, down in self.down_levels:
            x = res2(res1(x, cond), cond)
            skips.append(x)
            x = down(x)
        for block in self.mid_blocks:
            x = block(x, cond)
        for res1, res2, up in self.up_levels:
            x = torch.cat([x, skips.pop()], dim=1)
            x = res2(res1(x, cond), cond)
            x = up(x)
        x = self.final(x)  # (B, Da, T)
        return x.transpose(1, 2)


class _FiLMMlpBlock(nn.Module):
    """Linear -> LayerNorm -> FiLM(cond) -> Mish -> Linear, plus a residual path.

    (B, in_dim), cond (B, cond_dim) -> (B, out_dim). FiLM re-injects time and observation at
    every depth; concatenating them only at the input lets deep layers wash them out.
    """

    def __init__(self, in_dim: int, out_dim: int, cond_dim: int):
        super().__init__()
        self.fc1 = nn.Linear(in_dim, out_dim)
        self.norm = nn.LayerNorm(out_dim)
        self.film = nn.Linear(cond_dim, 2 * out_dim)
        self.act = nn.Mish()
        self.fc2 = nn.Linear(out_dim, out_dim)
        self.residual = nn.Linear(in_dim, out_dim) if in_dim != out_dim else nn.Identity()

    def forward(self, x: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        scale, bias = self.film(cond).chunk(2, dim=-1)
        # (1 + scale): at init the FiLM is near identity, so the LayerNorm output is not
        # multiplied by a random near-zero gain before the residual MLP has learned anything.
        h = self.act(self.norm(self.fc1(x)) * (1 + scale) + bias)
        return self.fc2(h) + self.residual(x)


class MlpHead(nn.Module):
    """A fast velocity head for low-dim tasks: residual MLP over the flattened action chunk.

    (B, T, Da) -> flatten (B, T*Da) ; concat [time embedding ; global_cond] -> FiLM residual
    blocks of widths ``hidden_dims`` -> Linear -> (B, T, Da). The horizon is fixed at
    construction because the first layer sees all T*Da numbers at once.
    """

    def __init__(self, input_dim: int, horizon: int, global_cond_dim: int, time_embed_dim: int = 128,
                 hidden_dims: tuple[int, ...] = (512, 512, 512), step_input: bool = False):
        super().__init__()
        hidden_dims = tuple(int(h) for h in hidden_dims)
        if input_dim < 1 or horizon < 1:
            raise ValueError(f"input_dim and horizon must be >= 1, got {input_dim}, {horizon}")
        if global_cond_dim < 0:
            raise ValueError(f"global_cond_dim must be >= 0, got {global_cond_dim}")
        if not hidden_dims:
            raise ValueError("hidden_dims must name at least one layer")
        self.input_dim = input_dim
        self.horizon = horizon
        self.global_cond_dim = global_cond_dim

        self.time_encoder = _time_mlp(time_embed_dim, 2 * time_embed_dim)
        self.step_encoder = _step_mlp(time_embed_dim, 2 * time_embed_dim) if step_input else None
        cond_dim = time_embed_dim + global_cond_dim
        flat = horizon * input_dim
        widths = (flat + cond_dim,) + hidden_dims
        self.blocks = nn.ModuleList(
            _FiLMMlpBlock(widths[i], widths[i + 1], cond_dim) for i in range(len(hidden_dims)))
        self.out = nn.Linear(hidden_dims[-1], flat)

    def forward(self, sample: torch.Tensor, timestep: torch.Tensor | float,
                global_cond: torch.Tensor | None = None, step: torch.Tensor | None = None
                ) -> torch.Tensor:
        """sample (B, T, Da), timestep (B,) scaled float, global_cond (B, C), step (B,) scaled
        step size (heads built with step_input) -> velocity (B, T, Da)."""
        expected = (self.horizon, self.input_dim)
        if sample.ndim != 3 or tuple(sample.shape[1:]) != expected:
            raise ValueError(f"sample must be (B, {self.horizon}, {self.input_dim}) for this MlpHead, "
                             f"got {tuple(sample.shape)}")
        batch = sample.shape[0]
        global_cond = _check_cond(global_cond, batch, self.global_cond_dim)

        cond = _embed_time(self.time_encoder, self.step_encoder, timestep, step, batch, sample.device)
        if global_cond is not None:
            cond = torch.cat([cond, global_cond.to(cond.dtype)], dim=-1)  # (B, cond_dim)
        h = torch.cat([sample.flatten(1), cond], dim=-1)  # (B, T*Da + cond_dim)
        for block in self.blocks:
            h = block(h, cond)
        return self.out(h).view(batch, self.horizon, self.input_dim)


HEADS: dict[str, type[nn.Module]] = {"unet": ConditionalUnet1D, "mlp": MlpHead}


def build_head(kind: str, **kwargs) -> nn.Module:
    """Build a velocity head by name: ``build_head("unet", input_dim=2, global_cond_dim=40)``.

    ``kwargs`` go to the class constructor unchanged (``MlpHead`` also needs ``horizon``).
    """
    try:
        cls = HEADS[kind]
    except KeyError:
        raise ValueError(f"unknown head kind {kind!r}; valid kinds: {sorted(HEADS)}") from None
    return cls(**kwargs)

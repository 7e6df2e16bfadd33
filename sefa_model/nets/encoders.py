"""Observation encoders: a dict of (B, To, ...) tensors -> one global-condition vector (B, D).

Conventions (Diffusion Policy's ``obs_as_global_cond``):

- low-dim keys arrive as (B, To, *shape) float, already normalized by the caller;
- rgb keys arrive as (B, To, C, H, W) float in [0, 1];
- the condition is built per frame as [image features of every rgb key ; every low-dim key]
  and the To frames are flattened in time order: (B, To * frame_dim). SeFA stores it reshaped
  back to (B, To, frame_dim), so the per-frame layout is part of the contract.

Modules:

- ``LowDimEncoder``: no parameters, just the concatenation.
- ``ImageEncoder`` ("small"): one per camera. A small ResNet (BasicBlocks, GroupNorm), the
  default: a quarter of ResNet-18's parameters, though not of its compute at 84x84.
- ``ResNet18Encoder`` ("resnet18"): torchvision's ResNet-18 in plain torch with GroupNorm for
  BatchNorm, Diffusion Policy's and robomimic's image trunk.
- both end in one of two pooling heads, as the two tools do: spatial-softmax keypoints
  (robomimic's ``VisualCore``, used by DP's CNN image policy) or global average pooling (DP's
  ``MultiImageObsEncoder``), each optionally followed by a Linear projection.
- ``ObsEncoder``: builds them from ``shape_meta`` and adds random/center crop for images.

Both encoders take images in [0, 1] and feed the trunk ``2x - 1``, as DP's Push-T pipeline does
(its image normalizer maps [0, 1] to [-1, 1]). ImageNet weights loaded into the ResNet-18 would
want ImageNet's mean/std instead (DP's ``imagenet_norm``); nothing here loads them yet.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Literal

import torch
import torch.nn.functional as F
from torch import nn

__all__ = [
    "LowDimEncoder",
    "BasicBlock",
    "SpatialSoftmax",
    "spatial_soft_argmax",
    "ImageEncoder",
    "TorchvisionBasicBlock",
    "ResNet18Trunk",
    "ResNet18Encoder",
    "IMAGE_ENCODERS",
    "IMAGE_POOLS",
    "build_image_encoder",
    "crop_images",
    "random_crop",
    "center_crop",
    "ObsEncoder",
]


def _first_frames(x: torch.Tensor, n_obs_steps: int, key: str) -> torch.Tensor:
    """(B, >=To, ...) -> (B, To, ...). Windows may carry more frames than the policy conditions
    on (DP loads the whole horizon); only the first To are observation history."""
    if x.ndim < 2 or x.shape[1] < n_obs_steps:
        raise ValueError(f"obs {key!r}: expected (B, {n_obs_steps}, ...) with n_obs_steps="
                         f"{n_obs_steps} frames, got {tuple(x.shape)}")
    return x[:, :n_obs_steps]


# --------------------------------------------------------------------------------------------
# Low-dim


class LowDimEncoder(nn.Module):
    """Concatenate the low-dim keys frame by frame: {key: (B, To, D_k)} -> (B, To * sum D_k).

    ``dims[key]`` is the flattened size of one frame of that key, so (B, To, 3, 3) with
    dims=9 is fine. ``out_dim = n_obs_steps * sum(dims)``.
    """

    def __init__(self, keys: Sequence[str], dims: Mapping[str, int], n_obs_steps: int):
        super().__init__()
        keys = list(keys)
        if not keys:
            raise ValueError("LowDimEncoder needs at least one key")
        missing = [k for k in keys if k not in dims]
        if missing:
            raise ValueError(f"LowDimEncoder: no dim given for keys {missing}")
        if n_obs_steps < 1:
            raise ValueError(f"n_obs_steps must be >= 1, got {n_obs_steps}")
        self.keys = keys
        self.dims = {k: int(dims[k]) for k in keys}
        self.n_obs_steps = n_obs_steps
        self.frame_dim = sum(self.dims.values())
        self.out_dim = n_obs_steps * self.frame_dim

    def frames(self, obs: Mapping[str, torch.Tensor]) -> torch.Tensor:
        """{key: (B, To, ...)} -> (B, To, frame_dim), keys in construction order."""
        parts = []
        for key in self.keys:
            if key not in obs:
                raise ValueError(f"obs is missing low-dim key {key!r}")
            x = _first_frames(obs[key], self.n_obs_steps, key)
            x = x.reshape(x.shape[0], self.n_obs_steps, -1)
            if x.shape[-1] != self.dims[key]:
                raise ValueError(f"obs {key!r}: expected {self.dims[key]} values per frame, "
                                 f"got {x.shape[-1]}")
            parts.append(x)
        return torch.cat(parts, dim=-1)

    def forward(self, obs: Mapping[str, torch.Tensor]) -> torch.Tensor:
        return self.frames(obs).flatten(1)  # (B, To * frame_dim)


# --------------------------------------------------------------------------------------------
# Image trunk


class BasicBlock(nn.Module):
    """ResNet BasicBlock with GroupNorm: (B, C_in, H, W) -> (B, C_out, H/stride, W/stride).

    GroupNorm instead of BatchNorm because the evaluated policy is an EMA of the weights: BatchNorm
    running statistics do not average consistently with EMA weights and break at batch size 1.
    """

    def __init__(self, in_channels: int, out_channels: int, stride: int = 1, n_groups: int = 8):
        super().__init__()
        self.conv1 = nn.Conv2d(in_channels, out_channels, 3, stride, padding=1, bias=False)
        self.norm1 = nn.GroupNorm(n_groups, out_channels)
        self.conv2 = nn.Conv2d(out_channels, out_channels, 3, 1, padding=1, bias=False)
        self.norm2 = nn.GroupNorm(n_groups, out_channels)
        self.shortcut: nn.Module = nn.Identity()
        if stride != 1 or in_channels != out_channels:
            self.shortcut = nn.Sequential(
                nn.Conv2d(in_channels, out_channels, 1, stride, bias=False),
                nn.GroupNorm(n_groups, out_channels))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = F.relu(self.norm1(self.conv1(x)))
        h = self.norm2(self.conv2(h))
        return F.relu(h + self.shortcut(x))


def spatial_soft_argmax(maps: torch.Tensor) -> torch.Tensor:
    """Expected (x, y) of a softmax over each map: (B, K, H, W) -> (B, K, 2), values in [-1, 1].

    Pixel centers sit at ((i + 0.5) / W) * 2 - 1 (the ``align_corners=False`` convention of
    ``grid_sample``), so a 1x1 map yields (0, 0) and coordinates do not depend on resolution.
    x runs along W (left -1 -> right +1), y along H (top -1 -> bottom +1).
    """
    b, k, h, w = maps.shape
    probs = maps.flatten(2).softmax(dim=-1).view(b, k, h, w)
    xs = (torch.arange(w, device=maps.device, dtype=probs.dtype) + 0.5) / w * 2 - 1  # (W,)
    ys = (torch.arange(h, device=maps.device, dtype=probs.dtype) + 0.5) / h * 2 - 1  # (H,)
    x = (probs.sum(dim=2) * xs).sum(dim=-1)  # marginal over rows, then E[x]: (B, K)
    y = (probs.sum(dim=3) * ys).sum(dim=-1)  # marginal over cols, then E[y]: (B, K)
    return torch.stack([x, y], dim=-1)


class SpatialSoftmax(nn.Module):
    """1x1 conv to K keypoint maps, then their soft-argmax: (B, C, H, W) -> (B, 2K).

    Output is interleaved per keypoint: [x_0, y_0, x_1, y_1, ...]. Keypoints (where is the
    feature?) rather than pooled features (how much of it?) is what robomimic and DP found to
    work for manipulation, where positions matter more than appearance.

    Against robomimic's ``SpatialSoftmax`` as DP's image policy configures it (num_kp 32,
    temperature 1.0 held fixed, noise_std 0, output_variance off): the same 1x1 conv with bias,
    softmax over all H*W positions at temperature 1, and (x, y) per keypoint flattened to 2K. The
    coordinate grid differs: robomimic puts pixel i at ``linspace(-1, 1, W)[i]`` (the outer pixel
    centers on -1 and +1), we put it at (i + 0.5) / W * 2 - 1. Ours is robomimic's times (W - 1) / W
    on each axis, a fixed rescaling the Linear after it absorbs, except on an axis one pixel long
    (robomimic -1, ours 0). Not implemented, all off in DP: a learned temperature, keypoint noise
    in training, the keypoint covariance output.
    """

    def __init__(self, in_channels: int, num_keypoints: int = 32):
        super().__init__()
        self.num_keypoints = num_keypoints
        self.keypoint_maps = nn.Conv2d(in_channels, num_keypoints, 1)
        self.out_dim = 2 * num_keypoints

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return spatial_soft_argmax(self.keypoint_maps(x)).flatten(1)


# --------------------------------------------------------------------------------------------
# Image encoders: trunk -> pool -> optional Linear

IMAGE_ENCODERS = ("tiny", "small", "resnet18")
# "tiny": the small encoder at half its widths and one block per stage, for 2 CPU cores (about
# 1/8 of its compute; tests/sefa_model_tests/test_encoders.py counts the FLOPs)
TINY = {"widths": (16, 32, 64, 128), "blocks_per_stage": 1}
IMAGE_POOLS = ("spatial_softmax", "avg")


class _PooledEncoder(nn.Module):
    """What both image encoders share: (N, C, H, W) in [0, 1] -> trunk -> pool -> Linear.

    Pools: "spatial_softmax" gives 2K keypoint coordinates (K = ``num_keypoints``), "avg" the
    mean of each trunk channel over the map. ``feature_dim`` adds a Linear to that width
    (robomimic's ``feature_dimension``, 64 in DP's image policy); None keeps the pooled features
    (DP's ``MultiImageObsEncoder``: ResNet-18's 512 averaged channels). ``out_dim`` is the result.
    Subclasses build their trunk, then call ``_build_head`` and implement ``trunk_features``.
    """

    def _build_head(self, channels: int, pool: str, feature_dim: int | None,
                    num_keypoints: int) -> None:
        if pool not in IMAGE_POOLS:
            raise ValueError(f"unknown image pool {pool!r}; valid pools: {list(IMAGE_POOLS)}")
        if feature_dim is not None and feature_dim < 1:
            raise ValueError(f"feature_dim must be >= 1 or None, got {feature_dim}")
        if num_keypoints < 1:
            raise ValueError(f"num_keypoints must be >= 1, got {num_keypoints}")
        self.pool = pool
        self.feature_dim = feature_dim
        pooled = channels
        if pool == "spatial_softmax":
            self.keypoints = SpatialSoftmax(channels, num_keypoints)
            pooled = self.keypoints.out_dim
        # Identity has no parameters: a pool without projection adds no state-dict entries.
        self.proj = nn.Linear(pooled, feature_dim) if feature_dim is not None else nn.Identity()
        self.out_dim = feature_dim if feature_dim is not None else pooled

    def trunk_features(self, x: torch.Tensor) -> torch.Tensor:
        """(N, C, H, W) in [-1, 1] -> (N, C', h, w)."""
        raise NotImplementedError

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """images (N, C, H, W) in [0, 1] -> (N, out_dim)."""
        # Center to [-1, 1], as DP's image normalizer does, so the first conv sees zero-mean
        # input without dataset statistics.
        x = self.trunk_features(images * 2 - 1)  # (N, C', h, w)
        pooled = self.keypoints(x) if self.pool == "spatial_softmax" else x.mean(dim=(2, 3))
        return self.proj(pooled)  # (N, out_dim)


class ImageEncoder(_PooledEncoder):
    """The small encoder: (N, C, H, W) float in [0, 1] -> (N, out_dim).

    stem (3x3 conv, stride 2) -> one stage per width (``blocks_per_stage`` BasicBlocks, the first
    stage at stride 1 and the rest at stride 2) -> pool -> Linear. With the default 4 widths the
    trunk has stride 16: 84 -> 6x6, 96 -> 6x6, 32 -> 2x2 maps, and "avg" gives widths[-1] = 256
    features. 2.8 M parameters against ResNet-18's 11.2 M, but about its compute at 84x84 (0.53
    against 0.59 GFLOP per image): without ResNet-18's 7x7/2 conv and max-pool (stride 4 before
    its first block), the first stage runs at 42x42. Module names (stem, stages, keypoints,
    proj) are those of checkpoints written before the pool became a choice, so they load
    unchanged.
    """

    def __init__(self, in_channels: int = 3, feature_dim: int | None = 64,
                 widths: tuple[int, ...] = (32, 64, 128, 256), num_keypoints: int = 32,
                 n_groups: int = 8, blocks_per_stage: int = 2,
                 pool: Literal["spatial_softmax", "avg"] = "spatial_softmax"):
        super().__init__()
        widths = tuple(int(w) for w in widths)
        if not widths:
            raise ValueError("ImageEncoder widths must name at least one stage")
        bad = [w for w in widths if w % n_groups]
        if bad:
            raise ValueError(f"every ImageEncoder width must be divisible by n_groups={n_groups}, got {bad}")
        if blocks_per_stage < 1:
            raise ValueError("blocks_per_stage must be >= 1")
        self.in_channels = in_channels

        self.stem = nn.Sequential(
            nn.Conv2d(in_channels, widths[0], 3, stride=2, padding=1, bias=False),
            nn.GroupNorm(n_groups, widths[0]),
            nn.ReLU(),
        )
        stages = []
        prev = widths[0]
        for i, width in enumerate(widths):
            blocks = [BasicBlock(prev, width, stride=1 if i == 0 else 2, n_groups=n_groups)]
            blocks += [BasicBlock(width, width, 1, n_groups) for _ in range(blocks_per_stage - 1)]
            stages.append(nn.Sequential(*blocks))
            prev = width
        self.stages = nn.Sequential(*stages)
        self._build_head(widths[-1], pool, feature_dim, num_keypoints)

    def trunk_features(self, x: torch.Tensor) -> torch.Tensor:
        """(N, C, H, W) in [-1, 1] -> (N, widths[-1], H/16, W/16)."""
        return self.stages(self.stem(x))


def _group_norm(channels: int) -> nn.GroupNorm:
    """Where torchvision has BatchNorm2d(C): GroupNorm(C // 16, C), 16 channels per group, as DP's
    ``replace_bn_with_gn`` (``replace_submodules`` with ``num_groups=x.num_features // 16``) does."""
    return nn.GroupNorm(channels // 16, channels)


class TorchvisionBasicBlock(nn.Module):
    """torchvision's ResNet BasicBlock, attribute names included, with GroupNorm:
    (N, C_in, H, W) -> (N, C_out, ceil(H / stride), ceil(W / stride)).

    The computation of ``BasicBlock`` above; the names differ (bn1, downsample.0, ...) so that
    torchvision's weights load by name, while ``BasicBlock`` keeps its own for small-encoder
    checkpoints.
    """

    def __init__(self, in_channels: int, out_channels: int, stride: int = 1):
        super().__init__()
        self.conv1 = nn.Conv2d(in_channels, out_channels, 3, stride, padding=1, bias=False)
        self.bn1 = _group_norm(out_channels)
        self.conv2 = nn.Conv2d(out_channels, out_channels, 3, 1, padding=1, bias=False)
        self.bn2 = _group_norm(out_channels)
        self.downsample: nn.Module | None = None
        if stride != 1 or in_channels != out_channels:
            self.downsample = nn.Sequential(
                nn.Conv2d(in_channels, out_channels, 1, stride, bias=False),
                _group_norm(out_channels))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        identity = x if self.downsample is None else self.downsample(x)
        out = F.relu(self.bn1(self.conv1(x)))
        out = self.bn2(self.conv2(out))
        return F.relu(out + identity)


class ResNet18Trunk(nn.Module):
    """torchvision's ``resnet18`` up to ``layer4`` (no avgpool, no fc: robomimic's ``ResNet18Conv``)
    with every BatchNorm a GroupNorm: (N, C, H, W) -> (N, 512, ceil(H / 32), ceil(W / 32)).

    conv1 7x7/2 (64) -> bn1 -> ReLU -> maxpool 3x3/2 -> layer1..layer4, two BasicBlocks each, at
    widths 64, 128, 256, 512; layers 2-4 open at stride 2 with a 1x1/2 conv downsample. 84x84 and
    96x96 inputs both give 3x3 maps. The parameters are torchvision's, by name and shape
    (``conv1.weight``, ``layer2.0.downsample.0.weight``, ...; 11,176,512 of them): its weights
    without fc and BatchNorm's running statistics load with ``load_state_dict``.
    """

    widths = (64, 128, 256, 512)
    out_channels = 512

    def __init__(self, in_channels: int = 3):
        super().__init__()
        self.conv1 = nn.Conv2d(in_channels, 64, 7, stride=2, padding=3, bias=False)
        self.bn1 = _group_norm(64)
        self.maxpool = nn.MaxPool2d(3, stride=2, padding=1)
        prev = 64
        for i, width in enumerate(self.widths):
            stride = 1 if i == 0 else 2
            setattr(self, f"layer{i + 1}", nn.Sequential(TorchvisionBasicBlock(prev, width, stride),
                                                         TorchvisionBasicBlock(width, width)))
            prev = width
        # torchvision's initialization: DP and robomimic build resnet18 without weights, then swap
        # in GroupNorms, which start at weight 1, bias 0 like torchvision's BatchNorms.
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(N, C, H, W) -> (N, 512, ceil(H / 32), ceil(W / 32))."""
        x = self.maxpool(F.relu(self.bn1(self.conv1(x))))  # (N, 64, H/4, W/4)
        x = self.layer1(x)  # (N, 64, H/4, W/4)
        x = self.layer2(x)  # (N, 128, H/8, W/8)
        x = self.layer3(x)  # (N, 256, H/16, W/16)
        return self.layer4(x)  # (N, 512, H/32, W/32)


class ResNet18Encoder(_PooledEncoder):
    """One camera through DP's / robomimic's trunk: (N, C, H, W) in [0, 1] -> (N, out_dim).

    ``ResNet18Trunk`` (under ``trunk.``) -> pool -> optional Linear. The two tools' settings:

    - pool="spatial_softmax", feature_dim=64: robomimic's ``VisualCore`` (ResNet18Conv,
      SpatialSoftmax with 32 keypoints, Linear to 64), which DP's CNN image policy
      (``DiffusionUnetHybridImagePolicy``, its Push-T image result) uses with GroupNorm;
      11,197,088 parameters.
    - pool="avg", feature_dim=None: DP's ``MultiImageObsEncoder`` on ``get_resnet("resnet18")``
      (fc replaced by Identity, so torchvision's global average pool): 512 features.
    """

    def __init__(self, in_channels: int = 3, feature_dim: int | None = 64,
                 pool: Literal["spatial_softmax", "avg"] = "spatial_softmax",
                 num_keypoints: int = 32):
        super().__init__()
        self.in_channels = in_channels
        self.trunk = ResNet18Trunk(in_channels)
        self._build_head(self.trunk.out_channels, pool, feature_dim, num_keypoints)

    def trunk_features(self, x: torch.Tensor) -> torch.Tensor:
        """(N, C, H, W) in [-1, 1] -> (N, 512, ceil(H / 32), ceil(W / 32))."""
        return self.trunk(x)


def build_image_encoder(name: str, in_channels: int = 3, feature_dim: int | None = 64,
                        pool: str = "spatial_softmax") -> _PooledEncoder:
    """``policy.image_encoder`` -> its module: "tiny" or "small" (``ImageEncoder``) or "resnet18"."""
    if name == "tiny":
        return ImageEncoder(in_channels=in_channels, feature_dim=feature_dim, pool=pool, **TINY)
    if name == "small":
        return ImageEncoder(in_channels=in_channels, feature_dim=feature_dim, pool=pool)
    if name == "resnet18":
        return ResNet18Encoder(in_channels=in_channels, feature_dim=feature_dim, pool=pool)
    raise ValueError(f"unknown image encoder {name!r}; valid encoders: {list(IMAGE_ENCODERS)}")

# --------------------------------------------------------------------------------------------
# Cropping (plain torch, differentiable w.r.t. the pixels, per-image offsets)


def crop_images(images: torch.Tensor, tops: torch.Tensor, lefts: torch.Tensor,
                crop_shape: tuple[int, int]) -> torch.Tensor:
    """Cut a (ch, cw) window at per-image offsets: (N, C, H, W), tops/lefts (N,) -> (N, C, ch, cw)."""
    ch, cw = crop_shape
    n = images.shape[0]
    device = images.device
    rows = tops.to(device)[:, None] + torch.arange(ch, device=device)  # (N, ch)
    cols = lefts.to(device)[:, None] + torch.arange(cw, device=device)  # (N, cw)
    batch = torch.arange(n, device=device)[:, None, None]
    # Advanced indices on dims 0, 2, 3 broadcast to (N, ch, cw); the sliced channel dim goes last.
    out = images[batch, :, rows[:, :, None], cols[:, None, :]]  # (N, ch, cw, C)
    return out.permute(0, 3, 1, 2)


def _check_crop(images: torch.Tensor, crop_shape: tuple[int, int]) -> tuple[int, int]:
    h, w = images.shape[-2:]
    ch, cw = crop_shape
    if not (0 < ch <= h and 0 < cw <= w):
        raise ValueError(f"crop_shape {tuple(crop_shape)} does not fit images of size {(h, w)}")
    return h - ch, w - cw


def random_crop(images: torch.Tensor, crop_shape: tuple[int, int],
                generator: torch.Generator | None = None) -> torch.Tensor:
    """Crop each image at its own uniformly random offset: (N, C, H, W) -> (N, C, ch, cw)."""
    max_top, max_left = _check_crop(images, crop_shape)
    n = images.shape[0]
    gen_device = generator.device if generator is not None else images.device
    tops = torch.randint(0, max_top + 1, (n,), generator=generator, device=gen_device)
    lefts = torch.randint(0, max_left + 1, (n,), generator=generator, device=gen_device)
    return crop_images(images, tops, lefts, crop_shape)


def center_crop(images: torch.Tensor, crop_shape: tuple[int, int]) -> torch.Tensor:
    """Deterministic central window: (N, C, H, W) -> (N, C, ch, cw)."""
    max_top, max_left = _check_crop(images, crop_shape)
    top, left = max_top // 2, max_left // 2
    return images[:, :, top:top + crop_shape[0], left:left + crop_shape[1]]


# --------------------------------------------------------------------------------------------
# Full observation encoder


def _module_name(key: str) -> str:
    """A ModuleDict-safe name for an obs key ("observation.images.top" has dots)."""
    return "rgb_" + key.replace(".", "_")


class ObsEncoder(nn.Module):
    """All observation keys of ``shape_meta`` -> global condition (B, n_obs_steps * frame_dim).

    ``shape_meta = {"obs": {key: {"shape": [...], "type": "rgb" | "low_dim"}}}`` (type defaults to
    "low_dim", as in DP). rgb shapes are [C, H, W]. Each rgb key gets its own image encoder
    (cameras see different things, so weights are not shared): ``image_encoder`` "small"
    (``ImageEncoder``) or "resnet18" (``ResNet18Encoder``), pooled by ``image_pool``
    ("spatial_softmax" or "avg") and projected to ``image_feature_dim`` (None: no projection).

    Per frame: [image features (the encoder's ``out_dim`` per rgb key, shape_meta order) ;
    low-dim values (shape_meta order)]; frames are then flattened in time order.

    With ``crop_shape=(ch, cw)``, images are randomly cropped in training (``self.training``) with
    an independent offset per image and per frame, as DP's crop randomizer does, and center
    cropped in eval so rollouts are deterministic.
    """

    def __init__(self, shape_meta: Mapping, n_obs_steps: int, image_feature_dim: int | None = 64,
                 crop_shape: tuple[int, int] | None = None, image_encoder: str = "small",
                 image_pool: str = "spatial_softmax"):
        super().__init__()
        if n_obs_steps < 1:
            raise ValueError(f"n_obs_steps must be >= 1, got {n_obs_steps}")
        obs_meta = shape_meta.get("obs") if isinstance(shape_meta, Mapping) else None
        if not obs_meta:
            raise ValueError("shape_meta must have a non-empty 'obs' mapping")
        if crop_shape is not None:
            crop_shape = (int(crop_shape[0]), int(crop_shape[1]))
        self.n_obs_steps = n_obs_steps
        self.crop_shape = crop_shape

        self.rgb_keys: list[str] = []
        self.low_dim_keys: list[str] = []
        self.rgb_shapes: dict[str, tuple[int, int, int]] = {}
        low_dims: dict[str, int] = {}
        encoders: dict[str, nn.Module] = {}
        for key, meta in obs_meta.items():
            if "shape" not in meta:
                raise ValueError(f"shape_meta obs {key!r}: missing 'shape'")
            shape = tuple(int(s) for s in meta["shape"])
            kind = meta.get("type", "low_dim")
            if kind == "rgb":
                if len(shape) != 3:
                    raise ValueError(f"shape_meta obs {key!r}: rgb shape must be [C, H, W], got {list(shape)}")
                c, h, w = shape
                if crop_shape is not None and not (0 < crop_shape[0] <= h and 0 < crop_shape[1] <= w):
                    raise ValueError(f"shape_meta obs {key!r}: crop_shape {crop_shape} does not fit "
                                     f"images of size {(h, w)}")
                name = _module_name(key)
                if name in encoders:
                    raise ValueError(f"shape_meta obs {key!r}: clashes with another rgb key after "
                                     f"replacing '.' by '_' ({name!r})")
                encoders[name] = build_image_encoder(image_encoder, in_channels=c,
                                                     feature_dim=image_feature_dim, pool=image_pool)
                self.rgb_keys.append(key)
                self.rgb_shapes[key] = (c, h, w)
            elif kind == "low_dim":
                self.low_dim_keys.append(key)
                low_dims[key] = math.prod(shape)
            else:
                raise ValueError(f"shape_meta obs {key!r}: unknown type {kind!r}; "
                                 "valid types: ['low_dim', 'rgb']")

        self.image_encoders = nn.ModuleDict(encoders)
        self.low_dim = (LowDimEncoder(self.low_dim_keys, low_dims, n_obs_steps)
                        if self.low_dim_keys else None)
        self.frame_dim = (sum(enc.out_dim for enc in self.image_encoders.values())
                          + (self.low_dim.frame_dim if self.low_dim is not None else 0))
        self.out_dim = n_obs_steps * self.frame_dim

    def _encode_images(self, key: str, x: torch.Tensor) -> torch.Tensor:
        """(B, To, C, H, W) in [0, 1] -> (B, To, F), F the key's encoder ``out_dim``."""
        c, h, w = self.rgb_shapes[key]
        if x.ndim != 5 or tuple(x.shape[2:]) != (c, h, w):
            raise ValueError(f"obs {key!r}: expected (B, To, {c}, {h}, {w}), got {tuple(x.shape)}")
        if not x.is_floating_point():
            raise ValueError(f"obs {key!r}: images must be float in [0, 1], got {x.dtype} "
                             "(divide uint8 images by 255)")
        b, t = x.shape[:2]
        images = x.reshape(b * t, c, h, w)  # frames become batch entries: one crop each
        if self.crop_shape is not None:
            images = (random_crop(images, self.crop_shape) if self.training
                      else center_crop(images, self.crop_shape))
        features = self.image_encoders[_module_name(key)](images)  # (B*To, F)
        return features.view(b, t, -1)

    def frames(self, obs: Mapping[str, torch.Tensor]) -> torch.Tensor:
        """{key: (B, >=To, ...)} -> per-frame features (B, To, frame_dim)."""
        parts = []
        for key in self.rgb_keys:
            if key not in obs:
                raise ValueError(f"obs is missing rgb key {key!r}")
            parts.append(self._encode_images(key, _first_frames(obs[key], self.n_obs_steps, key)))
        if self.low_dim is not None:
            parts.append(self.low_dim.frames(obs))
        # One dtype for the whole condition: float64 state must not promote image features.
        return torch.cat([p.to(parts[0].dtype) for p in parts], dim=-1)

    def forward(self, obs: Mapping[str, torch.Tensor]) -> torch.Tensor:
        """{key: (B, >=To, ...)} -> global condition (B, To * frame_dim)."""
        return self.frames(obs).flatten(1)

"""Velocity heads and observation encoders: shapes, conditioning, gradients, crops, errors.

Small widths everywhere except the parameter-count test, so the file runs in a few CPU seconds.
"""

from __future__ import annotations

import pytest
import torch
from torch import nn

from sefa_model.nets.encoders import (
    ImageEncoder,
    LowDimEncoder,
    ObsEncoder,
    SpatialSoftmax,
    center_crop,
    random_crop,
    spatial_soft_argmax,
)
from sefa_model.nets.networks import ConditionalUnet1D, MlpHead, SinusoidalPosEmb, build_head

SMALL = (16, 32, 64)


@pytest.fixture(autouse=True)
def _seed():
    torch.manual_seed(0)


def n_params(module: nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())


def assert_all_params_get_grad(module: nn.Module, loss: torch.Tensor) -> None:
    module.zero_grad(set_to_none=True)
    loss.backward()
    dead = [name for name, p in module.named_parameters()
            if p.grad is None or not torch.isfinite(p.grad).all() or p.grad.abs().sum() == 0]
    assert not dead, f"parameters without gradient: {dead}"


def pusht_image_meta() -> dict:
    return {"obs": {"image": {"shape": [3, 40, 40], "type": "rgb"},
                    "agent_pos": {"shape": [2], "type": "low_dim"}}}


# --------------------------------------------------------------------------------------------
# Time embedding


def test_sinusoidal_pos_emb():
    emb = SinusoidalPosEmb(16)
    t = torch.tensor([0.0, 1.0, 500.0, 999.0])
    out = emb(t)
    assert out.shape == (4, 16)
    assert torch.allclose(out[0], torch.cat([torch.zeros(8), torch.ones(8)]))
    assert not torch.allclose(out[2], out[3])
    with pytest.raises(ValueError):
        SinusoidalPosEmb(7)


@pytest.mark.parametrize("kind", ["unet", "mlp"])
def test_float64_head_sees_time_in_float64_and_float32_head_is_unchanged(kind):
    """A float64 copy of a head (the reflow benchmark's tight-tolerance reference solve) must
    be smooth in t: with t rounded to float32, t * 999 moves in steps of ~6e-5 and the field is
    a staircase in t. The float32 head keeps rounding t to float32, integer steps included."""
    kwargs = dict(input_dim=2, global_cond_dim=6, time_embed_dim=32)
    net = (build_head("unet", down_dims=SMALL, **kwargs) if kind == "unet"
           else build_head("mlp", horizon=16, hidden_dims=(64, 64), **kwargs)).eval()
    x, cond = torch.randn(1, 16, 2), torch.randn(1, 6)
    t = torch.tensor([998.0], dtype=torch.float64)
    dt = 1e-5  # far below float32's spacing at 998 (6e-5)
    with torch.no_grad():
        assert torch.equal(net(x, (t + dt).float(), cond), net(x, t + dt, cond))
        assert torch.equal(net(x, t, cond), net(x, t + dt, cond))  # the same float32 time
        net64 = net.double()
        out64 = net64(x.double(), t + dt, cond.double())
        assert out64.dtype == torch.float64
        assert not torch.equal(out64, net64(x.double(), t, cond.double()))
    emb = SinusoidalPosEmb(8)
    assert emb(torch.tensor([3, 7])).dtype == torch.float32  # integer diffusion steps


# --------------------------------------------------------------------------------------------
# Heads: shapes and conditioning


@pytest.mark.parametrize("batch,horizon,action_dim,cond_dim,down_dims", [
    (1, 16, 2, 40, SMALL),
    (3, 8, 7, 10, SMALL),
    (2, 4, 10, 136, SMALL),
    (2, 12, 4, 6, (16, 32)),      # 2 levels: any even horizon
    (2, 5, 3, 6, (16,)),          # 1 level: no down/up at all
    (2, 16, 3, 0, SMALL),         # unconditional
])
def test_unet_shapes(batch, horizon, action_dim, cond_dim, down_dims):
    net = ConditionalUnet1D(action_dim, cond_dim, time_embed_dim=32, down_dims=down_dims)
    x = torch.randn(batch, horizon, action_dim)
    cond = torch.randn(batch, cond_dim) if cond_dim else None
    assert net(x, torch.rand(batch) * 999, cond).shape == (batch, horizon, action_dim)


@pytest.mark.parametrize("batch,horizon,action_dim,cond_dim", [
    (1, 16, 2, 40), (5, 8, 7, 10), (2, 16, 10, 136), (3, 16, 4, 0)])
def test_mlp_shapes(batch, horizon, action_dim, cond_dim):
    net = MlpHead(action_dim, horizon, cond_dim, time_embed_dim=32, hidden_dims=(64, 64, 48))
    x = torch.randn(batch, horizon, action_dim)
    cond = torch.randn(batch, cond_dim) if cond_dim else None
    assert net(x, torch.rand(batch) * 999, cond).shape == (batch, horizon, action_dim)


@pytest.mark.parametrize("kind", ["unet", "mlp"])
def test_output_depends_on_cond_and_time(kind):
    kwargs = dict(input_dim=2, global_cond_dim=40, time_embed_dim=32)
    net = (build_head("unet", down_dims=SMALL, **kwargs) if kind == "unet"
           else build_head("mlp", horizon=16, hidden_dims=(64, 64), **kwargs))
    net.eval()
    x, t, cond = torch.randn(4, 16, 2), torch.rand(4) * 999, torch.randn(4, 40)
    with torch.no_grad():
        base = net(x, t, cond)
        assert not torch.allclose(base, net(x, t, cond + torch.randn_like(cond)), atol=1e-5)
        assert not torch.allclose(base, net(x, (t + 250) % 999, cond), atol=1e-5)
        # A scalar time is broadcast over the batch.
        assert torch.allclose(net(x, 1.0, cond), net(x, torch.ones(4), cond))


def test_default_unet_matches_diffusion_policy_size():
    # Push-T low-dim: Da=2, cond = To(2) * 20 keypoint dims; DP's CNN config reports ~6.5e7.
    net = ConditionalUnet1D(input_dim=2, global_cond_dim=2 * 20)
    count = n_params(net)
    print(f"default ConditionalUnet1D (Push-T low-dim): {count:,} parameters")
    assert 60_000_000 < count < 70_000_000
    with torch.no_grad():
        assert net(torch.randn(1, 16, 2), torch.tensor([999.0]), torch.randn(1, 40)).shape == (1, 16, 2)
    mlp = MlpHead(input_dim=2, horizon=16, global_cond_dim=40)
    print(f"default MlpHead (Push-T low-dim): {n_params(mlp):,} parameters")
    assert n_params(mlp) < 5_000_000


def test_build_head():
    assert isinstance(build_head("unet", input_dim=2, global_cond_dim=4, down_dims=SMALL),
                      ConditionalUnet1D)
    assert isinstance(build_head("mlp", input_dim=2, horizon=8, global_cond_dim=4), MlpHead)
    with pytest.raises(ValueError, match=r"'mlp'.*'unet'"):
        build_head("transformer", input_dim=2, global_cond_dim=4)


# --------------------------------------------------------------------------------------------
# Gradients and normalization layers


def test_unet_every_parameter_gets_gradient():
    net = ConditionalUnet1D(3, 8, time_embed_dim=32, down_dims=SMALL)
    out = net(torch.randn(2, 16, 3), torch.rand(2) * 999, torch.randn(2, 8))
    assert_all_params_get_grad(net, out.square().mean())


def test_mlp_every_parameter_gets_gradient():
    net = MlpHead(3, 16, 8, time_embed_dim=32, hidden_dims=(64, 64, 32))
    out = net(torch.randn(2, 16, 3), torch.rand(2) * 999, torch.randn(2, 8))
    assert_all_params_get_grad(net, out.square().mean())


def test_image_and_obs_encoder_every_parameter_gets_gradient():
    enc = ImageEncoder(widths=(8, 16), num_keypoints=4, feature_dim=8)
    assert_all_params_get_grad(enc, enc(torch.rand(2, 3, 32, 32)).square().mean())

    obs_enc = ObsEncoder(pusht_image_meta(), n_obs_steps=2, image_feature_dim=8, crop_shape=(32, 32))
    obs = {"image": torch.rand(2, 2, 3, 40, 40), "agent_pos": torch.randn(2, 2, 2)}
    assert_all_params_get_grad(obs_enc, obs_enc(obs).square().mean())


def test_group_norm_only():
    modules = [
        ConditionalUnet1D(2, 40, down_dims=SMALL),
        MlpHead(2, 16, 40),
        ObsEncoder(pusht_image_meta(), n_obs_steps=2),
    ]
    for module in modules:
        batch_norms = [m for m in module.modules() if isinstance(m, nn.modules.batchnorm._BatchNorm)]
        assert not batch_norms, f"{type(module).__name__} contains BatchNorm: {batch_norms}"
    for module in modules[0], modules[2]:
        assert any(isinstance(m, nn.GroupNorm) for m in module.modules())


# --------------------------------------------------------------------------------------------
# Image encoder pieces


@pytest.mark.parametrize("size", [32, 84, 96])
def test_image_encoder_sizes(size):
    enc = ImageEncoder(widths=(8, 16, 16, 32), num_keypoints=8, feature_dim=16)
    assert enc(torch.rand(2, 3, size, size)).shape == (2, 16)


def test_spatial_soft_argmax_finds_the_peak():
    h, w = 7, 9
    maps = torch.zeros(2, 3, h, w)
    peaks = [[(0, 0), (3, 4), (6, 8)], [(2, 7), (5, 1), (6, 0)]]  # (row, col)
    for b, per_image in enumerate(peaks):
        for k, (r, c) in enumerate(per_image):
            maps[b, k, r, c] = 60.0  # sharp enough that the softmax is one-hot
    coords = spatial_soft_argmax(maps)
    assert coords.shape == (2, 3, 2)
    for b, per_image in enumerate(peaks):
        for k, (r, c) in enumerate(per_image):
            expected = torch.tensor([(c + 0.5) / w * 2 - 1, (r + 0.5) / h * 2 - 1])
            assert torch.allclose(coords[b, k], expected, atol=1e-4)
    # x grows to the right and y downwards.
    assert coords[0, 0, 0] < 0 and coords[0, 0, 1] < 0 and coords[0, 2, 0] > 0 and coords[0, 2, 1] > 0

    # The module version: identity 1x1 conv, interleaved [x0, y0, x1, y1, ...].
    layer = SpatialSoftmax(in_channels=3, num_keypoints=3)
    with torch.no_grad():
        layer.keypoint_maps.weight.copy_(torch.eye(3)[:, :, None, None])
        layer.keypoint_maps.bias.zero_()
    assert torch.allclose(layer(maps), coords.flatten(1), atol=1e-6)

    # Arbitrary features always give coordinates inside [-1, 1].
    random = spatial_soft_argmax(torch.randn(4, 5, 6, 6) * 10)
    assert random.abs().max() <= 1.0


def test_random_and_center_crop():
    # Pixel value = its flat position, so a crop's top-left value tells its offset.
    images = torch.arange(20 * 24, dtype=torch.float32).view(1, 1, 20, 24).repeat(64, 2, 1, 1)
    crop = (16, 16)
    a, b = random_crop(images, crop), random_crop(images, crop)
    assert a.shape == b.shape == (64, 2, 16, 16)
    assert not torch.equal(a, b)
    tops, lefts = (a[:, 0, 0, 0] // 24).long(), (a[:, 0, 0, 0] % 24).long()
    assert len(set(zip(tops.tolist(), lefts.tolist()))) > 1  # offsets differ within a batch
    for n in range(64):
        t, l = tops[n], lefts[n]
        assert torch.equal(a[n], images[n, :, t:t + 16, l:l + 16])
    assert tops.max() <= 4 and lefts.max() <= 8

    centered = center_crop(images, crop)
    assert torch.equal(centered, images[:, :, 2:18, 4:20])
    with pytest.raises(ValueError):
        random_crop(images, (21, 8))


@pytest.mark.parametrize("encoder,size,crop", [("small", 40, 32), ("resnet18", 72, 64)])
def test_obs_encoder_crop_is_random_in_train_and_center_in_eval(encoder, size, crop):
    # ResNet-18 needs 64-pixel crops for 2x2 maps: on a 1x1 map its keypoints cannot move
    meta = {"obs": {"image": {"shape": [3, size, size], "type": "rgb"},
                    "agent_pos": {"shape": [2], "type": "low_dim"}}}
    enc = ObsEncoder(meta, n_obs_steps=2, image_feature_dim=8, crop_shape=(crop, crop),
                     image_encoder=encoder)
    obs = {"image": torch.rand(3, 2, 3, size, size), "agent_pos": torch.randn(3, 2, 2)}
    enc.train()
    with torch.no_grad():
        assert not torch.allclose(enc(obs), enc(obs))
        enc.eval()
        first = enc(obs)
        assert torch.equal(first, enc(obs))  # eval: identical features for identical inputs
        cropped = center_crop(obs["image"].flatten(0, 1), (crop, crop))
        image_features = enc.image_encoders["rgb_image"](cropped).view(3, 2, 8)
        assert torch.allclose(first.view(3, 2, 10)[..., :8], image_features, atol=1e-6)


class RecordImages(nn.Module):
    """Stands in for an image encoder and keeps the (cropped) images it is given."""

    out_dim = 8

    def __init__(self):
        super().__init__()
        self.seen: list[torch.Tensor] = []

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        self.seen.append(images)
        return images.new_zeros(len(images), self.out_dim)


def test_obs_encoder_crops_every_image_and_frame_at_its_own_offset():
    enc = ObsEncoder(pusht_image_meta(), n_obs_steps=2, image_feature_dim=8, crop_shape=(32, 32))
    record = enc.image_encoders["rgb_image"] = RecordImages()
    # Every sample and frame shows the same image, pixel value = its flat position, so a crop's
    # top-left value tells where it was cut.
    pixels = torch.arange(40 * 40, dtype=torch.float32).view(40, 40)
    obs = {"image": pixels.expand(16, 2, 3, 40, 40).clone(), "agent_pos": torch.zeros(16, 2, 2)}
    enc.train()
    enc(obs)
    crops = record.seen[-1].view(16, 2, 3, 32, 32)
    tops, lefts = (crops[:, :, 0, 0, 0] // 40).long(), (crops[:, :, 0, 0, 0] % 40).long()  # (B, To)
    assert tops.max() <= 8 and lefts.max() <= 8  # inside the 40x40 image
    for b in range(16):
        for t in range(2):
            top, left = tops[b, t], lefts[b, t]
            assert torch.equal(crops[b, t], obs["image"][b, t, :, top:top + 32, left:left + 32])
    offsets = tops * 40 + lefts
    assert (offsets[:, 0] != offsets[:, 1]).any()  # the frames of one sample are cropped apart
    assert len(offsets[:, 0].unique()) > 1  # and so are the samples of one batch
    enc.eval()
    enc(obs)
    assert torch.equal(record.seen[-1], obs["image"].flatten(0, 1)[:, :, 4:36, 4:36])  # the center


# --------------------------------------------------------------------------------------------
# Observation layout


def test_low_dim_encoder_layout():
    enc = LowDimEncoder(["a", "b"], {"a": 2, "b": 3}, n_obs_steps=2)
    a, b = torch.randn(4, 2, 2), torch.randn(4, 2, 3)
    out = enc({"a": a, "b": b, "ignored": torch.randn(4, 2, 9)})
    assert enc.out_dim == 10 and out.shape == (4, 10)
    # DP's obs_as_global_cond: frame 0 (all keys), then frame 1.
    assert torch.equal(out, torch.cat([a, b], dim=-1).flatten(1))


def test_obs_encoder_layout_and_extra_frames():
    meta = {"obs": {"cam.front": {"shape": [3, 32, 32], "type": "rgb"},
                    "pos": {"shape": [3]},                         # type defaults to low_dim
                    "wrist": {"shape": [3, 32, 32], "type": "rgb"},
                    "grip": {"shape": [1], "type": "low_dim"}}}
    enc = ObsEncoder(meta, n_obs_steps=2, image_feature_dim=8).eval()
    assert enc.rgb_keys == ["cam.front", "wrist"] and enc.low_dim_keys == ["pos", "grip"]
    assert enc.frame_dim == 8 + 8 + 3 + 1 and enc.out_dim == 2 * 20
    obs = {"cam.front": torch.rand(2, 5, 3, 32, 32), "wrist": torch.rand(2, 5, 3, 32, 32),
           "pos": torch.randn(2, 5, 3), "grip": torch.randn(2, 5, 1, dtype=torch.float64)}
    with torch.no_grad():
        out = enc(obs)
    assert out.shape == (2, 40) and out.dtype == torch.float32
    frames = out.view(2, 2, 20)
    # Only the first To frames are used; per frame, images come first, then low-dim in order.
    assert torch.allclose(frames[..., 16:19], obs["pos"][:, :2])
    assert torch.allclose(frames[..., 19:], obs["grip"][:, :2].float())


def test_low_dim_only_obs_encoder_matches_low_dim_encoder():
    meta = {"obs": {"keypoint": {"shape": [9, 2], "type": "low_dim"},
                    "agent_pos": {"shape": [2], "type": "low_dim"}}}
    enc = ObsEncoder(meta, n_obs_steps=2)
    assert enc.out_dim == 2 * 20 and n_params(enc) == 0
    obs = {"keypoint": torch.randn(3, 2, 9, 2), "agent_pos": torch.randn(3, 2, 2)}
    expected = torch.cat([obs["keypoint"].flatten(2), obs["agent_pos"]], dim=-1).flatten(1)
    assert torch.equal(enc(obs), expected)


# --------------------------------------------------------------------------------------------
# Errors


def test_head_value_errors():
    net = ConditionalUnet1D(2, 4, time_embed_dim=32, down_dims=SMALL)
    with pytest.raises(ValueError, match="multiple of 4"):
        net(torch.randn(1, 6, 2), torch.zeros(1), torch.randn(1, 4))
    with pytest.raises(ValueError, match="multiple of 4"):
        net(torch.randn(1, 2, 2), torch.zeros(1), torch.randn(1, 4))
    with pytest.raises(ValueError, match="sample"):
        net(torch.randn(1, 8, 3), torch.zeros(1), torch.randn(1, 4))
    with pytest.raises(ValueError, match="global_cond"):
        net(torch.randn(1, 8, 2), torch.zeros(1), torch.randn(1, 5))
    with pytest.raises(ValueError, match="global_cond"):
        net(torch.randn(1, 8, 2), torch.zeros(1), None)
    with pytest.raises(ValueError, match="timestep"):
        net(torch.randn(2, 8, 2), torch.zeros(3), torch.randn(2, 4))
    with pytest.raises(ValueError, match="odd"):
        ConditionalUnet1D(2, 4, kernel_size=4)
    with pytest.raises(ValueError, match="n_groups"):
        ConditionalUnet1D(2, 4, down_dims=(12, 24))
    mlp = MlpHead(2, 16, 4, hidden_dims=(32,))
    with pytest.raises(ValueError, match="16"):
        mlp(torch.randn(1, 8, 2), torch.zeros(1), torch.randn(1, 4))


def test_encoder_value_errors():
    with pytest.raises(ValueError, match="'depth'.*'pointcloud'"):
        ObsEncoder({"obs": {"depth": {"shape": [1, 32, 32], "type": "pointcloud"}}}, n_obs_steps=2)
    with pytest.raises(ValueError, match="'image'"):
        ObsEncoder({"obs": {"image": {"shape": [32, 32], "type": "rgb"}}}, n_obs_steps=2)
    with pytest.raises(ValueError, match="crop_shape"):
        ObsEncoder(pusht_image_meta(), n_obs_steps=2, crop_shape=(48, 48))
    with pytest.raises(ValueError, match="'obs'"):
        ObsEncoder({"action": {"shape": [2]}}, n_obs_steps=2)
    with pytest.raises(ValueError, match="n_groups"):
        ImageEncoder(widths=(12, 24))
    with pytest.raises(ValueError):
        LowDimEncoder(["a"], {}, n_obs_steps=2)

    enc = ObsEncoder(pusht_image_meta(), n_obs_steps=2, image_feature_dim=8)
    good = {"image": torch.rand(1, 2, 3, 40, 40), "agent_pos": torch.randn(1, 2, 2)}
    with pytest.raises(ValueError, match="missing.*'agent_pos'"):
        enc({"image": good["image"]})
    with pytest.raises(ValueError, match="'image'.*uint8"):
        enc({**good, "image": (good["image"] * 255).to(torch.uint8)})
    with pytest.raises(ValueError, match="'image'"):
        enc({**good, "image": torch.rand(1, 2, 3, 32, 40)})
    with pytest.raises(ValueError, match="'agent_pos'.*2 frames|n_obs_steps=2"):
        enc({**good, "agent_pos": torch.randn(1, 1, 2)})
    with pytest.raises(ValueError, match="'agent_pos'.*values per frame"):
        enc({**good, "agent_pos": torch.randn(1, 2, 3)})

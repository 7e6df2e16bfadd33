"""Image encoders: the ResNet-18 trunk against torchvision's architecture, both pooling heads,
output widths in every combination, gradients, the PolicyConfig keys and old configs.

Crops are tested with the other ObsEncoder tests in test_networks.py. torchvision is not
installed here, so its architecture is written down below from its definition
(torchvision/models/resnet.py: resnet18 = ResNet(BasicBlock, [2, 2, 2, 2])).
"""

from __future__ import annotations

import pytest
import torch
from torch import nn

from sefa_data.config_io import from_dict
from sefa_data.errors import ConfigError
from sefa_model.config import PolicyConfig, TrainConfig, config_to_dict, load_train_config
from sefa_model.nets.encoders import (
    ImageEncoder,
    ObsEncoder,
    ResNet18Encoder,
    ResNet18Trunk,
    build_image_encoder,
    spatial_soft_argmax,
)

# torchvision.models.resnet18() has 11,689,512 parameters, of which fc (512 x 1000 + 1000) is
# 513,000. GroupNorm has BatchNorm's affine parameters (weight and bias per channel), so the
# count carries over.
TORCHVISION_RESNET18_WITHOUT_FC = 11_176_512
# The small encoder's count before the encoder became a choice (commit e23484b): checkpoints
# written then must keep loading.
SMALL_ENCODER_PARAMS = 2_807_424


@pytest.fixture(autouse=True)
def _seed():
    torch.manual_seed(0)


def n_params(module: nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())


def torchvision_resnet18_parameters() -> dict[str, tuple[int, ...]]:
    """torchvision's resnet18 state-dict names and shapes, fc and BatchNorm buffers left out."""
    shapes = {"conv1.weight": (64, 3, 7, 7), "bn1.weight": (64,), "bn1.bias": (64,)}
    prev = 64
    for layer, width in enumerate((64, 128, 256, 512), start=1):
        for block in range(2):
            p = f"layer{layer}.{block}."
            c_in = prev if block == 0 else width
            shapes[p + "conv1.weight"] = (width, c_in, 3, 3)
            shapes[p + "bn1.weight"] = shapes[p + "bn1.bias"] = (width,)
            shapes[p + "conv2.weight"] = (width, width, 3, 3)
            shapes[p + "bn2.weight"] = shapes[p + "bn2.bias"] = (width,)
            if block == 0 and layer > 1:  # stride 2: a 1x1 conv and a norm on the shortcut
                shapes[p + "downsample.0.weight"] = (width, prev, 1, 1)
                shapes[p + "downsample.1.weight"] = shapes[p + "downsample.1.bias"] = (width,)
        prev = width
    return shapes


# --------------------------------------------------------------------------------------------
# ResNet-18


def test_resnet18_trunk_has_torchvisions_parameters():
    trunk = ResNet18Trunk()
    expected = torchvision_resnet18_parameters()
    ours = {name: tuple(p.shape) for name, p in trunk.named_parameters()}
    assert list(ours) == list(expected)  # same names, in torchvision's order
    assert ours == expected
    assert n_params(trunk) == TORCHVISION_RESNET18_WITHOUT_FC
    assert not list(trunk.buffers())  # no running statistics: nothing depends on the batch
    # loads a torchvision-named state dict strictly (here: our own, renamed nowhere)
    trunk.load_state_dict({k: torch.zeros(s) for k, s in expected.items()}, strict=True)


def test_resnet18_trunk_strides_and_sizes():
    trunk = ResNet18Trunk().eval()
    with torch.no_grad():
        # 84 -> 42 (conv1) -> 21 (maxpool) -> 21, 11, 6, 3 (layers): ceil(H / 32)
        assert trunk(torch.rand(1, 3, 84, 84)).shape == (1, 512, 3, 3)
        assert trunk(torch.rand(1, 3, 96, 96)).shape == (1, 512, 3, 3)
        assert trunk(torch.rand(1, 3, 224, 224)).shape == (1, 512, 7, 7)  # ImageNet's 7x7
        assert trunk(torch.rand(1, 3, 84, 120)).shape == (1, 512, 3, 4)


def test_resnet18_norms_are_diffusion_policys_group_norms():
    enc = ResNet18Encoder()
    assert not [m for m in enc.modules() if isinstance(m, nn.modules.batchnorm._BatchNorm)]
    norms = [m for m in enc.modules() if isinstance(m, nn.GroupNorm)]
    # bn1, two per BasicBlock (8 blocks), one per downsample (layers 2-4)
    assert len(norms) == 1 + 16 + 3
    assert all(m.num_groups == m.num_channels // 16 for m in norms)
    assert {(m.num_channels, m.num_groups) for m in norms} == {(64, 4), (128, 8), (256, 16), (512, 32)}


def test_resnet18_trunk_is_initialized_as_torchvision():
    trunk = ResNet18Trunk()
    w = trunk.layer4[1].conv2.weight  # kaiming_normal_, mode fan_out: std sqrt(2 / (512 * 9))
    assert w.std().item() == pytest.approx((2 / (512 * 9)) ** 0.5, rel=0.05)
    assert torch.equal(trunk.bn1.weight, torch.ones(64)) and torch.equal(trunk.bn1.bias, torch.zeros(64))


# --------------------------------------------------------------------------------------------
# Pooling heads and widths

SMALL_TRUNK_WIDTH = 256
#                        encoder,   pool,              feature_dim, out_dim
COMBINATIONS = [("small", "spatial_softmax", 48, 48), ("small", "spatial_softmax", None, 64),
                ("small", "avg", 48, 48), ("small", "avg", None, SMALL_TRUNK_WIDTH),
                ("resnet18", "spatial_softmax", 48, 48), ("resnet18", "spatial_softmax", None, 64),
                ("resnet18", "avg", 48, 48), ("resnet18", "avg", None, 512)]


@pytest.mark.parametrize("size", [84, 96])
@pytest.mark.parametrize("name,pool,feature_dim,out_dim", COMBINATIONS)
def test_image_encoder_output_widths(name, pool, feature_dim, out_dim, size):
    enc = build_image_encoder(name, feature_dim=feature_dim, pool=pool)
    assert enc.out_dim == out_dim
    assert isinstance(enc, ResNet18Encoder if name == "resnet18" else ImageEncoder)
    with torch.no_grad():
        assert enc(torch.rand(2, 3, size, size)).shape == (2, out_dim)


@pytest.mark.parametrize("name,pool,feature_dim,out_dim", COMBINATIONS)
def test_obs_encoder_dims_in_every_combination(name, pool, feature_dim, out_dim):
    meta = {"obs": {"top": {"shape": [3, 96, 96], "type": "rgb"},
                    "wrist": {"shape": [3, 96, 96], "type": "rgb"},
                    "agent_pos": {"shape": [2]}}}
    enc = ObsEncoder(meta, n_obs_steps=2, image_feature_dim=feature_dim, crop_shape=(84, 84),
                     image_encoder=name, image_pool=pool).eval()
    assert enc.frame_dim == 2 * out_dim + 2 and enc.out_dim == 2 * enc.frame_dim
    obs = {"top": torch.rand(1, 2, 3, 96, 96), "wrist": torch.rand(1, 2, 3, 96, 96),
           "agent_pos": torch.randn(1, 2, 2)}
    with torch.no_grad():
        frames = enc.frames(obs)
    assert frames.shape == (1, 2, enc.frame_dim)
    assert torch.equal(frames[..., -2:], obs["agent_pos"])  # low-dim after both cameras


def test_the_two_tools_settings():
    # robomimic's VisualCore as DP's CNN image policy builds it: ResNet18Conv, 32 keypoints, 64
    robomimic = ResNet18Encoder(feature_dim=64, pool="spatial_softmax")
    assert n_params(robomimic) == TORCHVISION_RESNET18_WITHOUT_FC + (512 * 32 + 32) + (64 * 64 + 64)
    # DP's MultiImageObsEncoder: resnet18 with fc = Identity, i.e. the 512 averaged channels
    dp = ResNet18Encoder(feature_dim=None, pool="avg").eval()
    assert n_params(dp) == TORCHVISION_RESNET18_WITHOUT_FC
    images = torch.rand(3, 3, 84, 84)
    with torch.no_grad():
        assert torch.allclose(dp(images), dp.trunk(images * 2 - 1).mean(dim=(2, 3)))


def test_spatial_softmax_is_robomimics_up_to_a_fixed_grid_scale():
    """robomimic's grid is linspace(-1, 1, W); ours (i + 0.5) / W * 2 - 1, its (W - 1) / W times."""
    maps = torch.randn(2, 5, 3, 4) * 3
    b, k, h, w = maps.shape
    probs = maps.flatten(2).softmax(-1)
    pos_y, pos_x = torch.meshgrid(torch.linspace(-1, 1, h), torch.linspace(-1, 1, w), indexing="ij")
    robomimic = torch.stack([(probs * pos_x.flatten()).sum(-1), (probs * pos_y.flatten()).sum(-1)], -1)
    ours = spatial_soft_argmax(maps)
    assert ours.shape == robomimic.shape == (b, k, 2)  # (x, y) per keypoint, as robomimic's
    scale = torch.tensor([(w - 1) / w, (h - 1) / h])
    assert torch.allclose(ours, robomimic * scale, atol=1e-6)


@pytest.mark.parametrize("name,pool,feature_dim", [("resnet18", "spatial_softmax", 64),
                                                   ("resnet18", "avg", None), ("small", "avg", 16)])
def test_gradients_reach_every_parameter(name, pool, feature_dim):
    meta = {"obs": {"image": {"shape": [3, 72, 72], "type": "rgb"}, "agent_pos": {"shape": [2]}}}
    # 64x64 crops: 2x2 maps after ResNet-18, so the keypoint softmax has positions to move
    enc = ObsEncoder(meta, n_obs_steps=2, image_feature_dim=feature_dim, crop_shape=(64, 64),
                     image_encoder=name, image_pool=pool)
    obs = {"image": torch.rand(2, 2, 3, 72, 72), "agent_pos": torch.randn(2, 2, 2)}
    enc(obs).square().mean().backward()
    dead = [n for n, p in enc.named_parameters()
            if p.grad is None or not torch.isfinite(p.grad).all() or p.grad.abs().sum() == 0]
    assert not dead, f"parameters without gradient: {dead}"


def test_encoder_errors():
    with pytest.raises(ValueError, match="'resnet50'.*small.*resnet18"):
        build_image_encoder("resnet50")
    with pytest.raises(ValueError, match="'max'.*spatial_softmax.*avg"):
        ResNet18Encoder(pool="max")
    with pytest.raises(ValueError, match="feature_dim"):
        ImageEncoder(feature_dim=0)


# --------------------------------------------------------------------------------------------
# Config


def image_config(*overrides: str) -> TrainConfig:
    return load_train_config(None, ["shape_meta.obs.img.type=rgb", *overrides])


def test_config_keys_defaults_and_errors():
    p = PolicyConfig()
    assert (p.image_encoder, p.image_pool, p.image_feature_dim) == ("small", "spatial_softmax", 64)
    cfg = image_config("policy.image_encoder=resnet18", "policy.image_pool=avg",
                       "policy.image_feature_dim=null")
    assert (cfg.policy.image_encoder, cfg.policy.image_pool, cfg.policy.image_feature_dim) == (
        "resnet18", "avg", None)
    for override, key in [("policy.image_encoder=resnet50", "policy.image_encoder"),
                          ("policy.image_pool=max", "policy.image_pool"),
                          ("policy.image_feature_dim=0", "policy.image_feature_dim"),
                          ("policy.crop_shape=[84]", "policy.crop_shape")]:
        with pytest.raises(ConfigError) as err:
            image_config(override)
        assert err.value.key == key, override
    with pytest.raises(ConfigError, match="image_encoder"):  # a misspelt key names the right one
        image_config("policy.image_encodr=resnet18")


def test_a_config_written_before_the_encoder_keys_builds_the_same_model():
    """Checkpoints store their resolved config: one from before these keys lacks them and must
    give the small encoder with spatial softmax, parameter for parameter."""
    from sefa_model.policy.model import FlowPolicyModel

    cfg = image_config("policy.head=mlp", "policy.crop_shape=[84,84]")
    cfg.shape_meta.obs["img"].shape = [3, 96, 96]
    cfg.shape_meta.action.shape = [2]
    old = config_to_dict(cfg)
    for key in ("image_encoder", "image_pool"):
        del old["policy"][key]
    loaded = from_dict(TrainConfig, old)
    assert (loaded.policy.image_encoder, loaded.policy.image_pool) == ("small", "spatial_softmax")
    encoder = FlowPolicyModel(loaded).obs_encoder.image_encoders["rgb_img"]
    assert isinstance(encoder, ImageEncoder) and n_params(encoder) == SMALL_ENCODER_PARAMS
    names = list(encoder.state_dict())
    assert len(names) == 64 and names[:3] == ["stem.0.weight", "stem.1.weight", "stem.1.bias"]
    assert names[-4:] == ["keypoints.keypoint_maps.weight", "keypoints.keypoint_maps.bias",
                          "proj.weight", "proj.bias"]


def test_tiny_encoder_costs_a_fraction_of_the_small_one():
    """The CPU profile's encoder: counted with torch's own FLOP counter at 84x84, "tiny" is under
    a sixth of "small", which costs about what ResNet-18 does; all three give 64 features."""
    from torch.utils.flop_counter import FlopCounterMode

    def flops(name):
        enc = build_image_encoder(name).eval()
        counter = FlopCounterMode(display=False)
        with counter, torch.no_grad():
            out = enc(torch.rand(1, 3, 84, 84))
        assert out.shape == (1, 64)
        return counter.get_total_flops()

    tiny, small, resnet = flops("tiny"), flops("small"), flops("resnet18")
    assert tiny < small / 6 and 0.7 < small / resnet < 1.1, (tiny, small, resnet)

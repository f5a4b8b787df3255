"""ResUNet: torchvision parameter names, strict checkpoint loading, freezing, output shapes."""

from __future__ import annotations

import pytest
import torch

from pcrcg.errors import ConfigError, DataError
from pcrcg.vision.encoders import (
    ResUNet,
    build_encoder,
    save_pri3d_checkpoint,
    torchvision_keys,
)

BN = ("weight", "bias", "running_mean", "running_var", "num_batches_tracked")

# torchvision.models.resnet: (block, blocks per stage); BasicBlock has conv1/bn1/conv2/bn2,
# Bottleneck adds conv3/bn3; stage k>0 (and stage 0 of Bottleneck nets) starts with a downsample.
TORCHVISION_RESNETS = {
    "resnet18": ("basic", (2, 2, 2, 2)),
    "resnet34": ("basic", (3, 4, 6, 3)),
    "resnet50": ("bottleneck", (3, 4, 6, 3)),
}
# len(torchvision.models.<arch>().state_dict()) including fc.weight/fc.bias
TORCHVISION_N_KEYS = {"resnet18": 122, "resnet34": 218, "resnet50": 320}
# a few shapes of torchvision's resnet18 state dict
RESNET18_SHAPES = {
    "conv1.weight": (64, 3, 7, 7),
    "layer1.0.conv1.weight": (64, 64, 3, 3),
    "layer2.0.downsample.0.weight": (128, 64, 1, 1),
    "layer4.1.bn2.running_var": (512,),
    "fc.weight": (1000, 512),
}


def expected_torchvision_keys(arch: str) -> list[str]:
    kind, layers = TORCHVISION_RESNETS[arch]
    convs = ["conv1", "bn1", "conv2", "bn2"] + (["conv3", "bn3"] if kind == "bottleneck" else [])
    keys = ["conv1.weight"] + [f"bn1.{s}" for s in BN]
    for stage, n in enumerate(layers, 1):
        for b in range(n):
            pre = f"layer{stage}.{b}."
            for c in convs:
                keys += [pre + c + ".weight"] if c.startswith("conv") else [pre + c + "." + s for s in BN]
            if b == 0 and (stage > 1 or kind == "bottleneck"):
                keys += [pre + "downsample.0.weight"] + [pre + "downsample.1." + s for s in BN]
    return keys + ["fc.weight", "fc.bias"]


def torchvision_like_state_dict(arch: str, seed: int = 0) -> dict[str, torch.Tensor]:
    """What ``torch.save(torchvision.models.<arch>().state_dict())`` holds, with random values."""
    torch.manual_seed(seed)
    enc = ResUNet(arch, 8).encoder
    sd = {k: v.clone() for k, v in enc.state_dict().items()}
    for k, v in sd.items():
        if v.is_floating_point():
            v.normal_()
    width = 512 if arch != "resnet50" else 2048
    sd["fc.weight"] = torch.randn(1000, width)
    sd["fc.bias"] = torch.randn(1000)
    return sd


@pytest.mark.parametrize("arch", ["resnet18", "resnet34", "resnet50"])
def test_encoder_keys_are_torchvision_keys(arch):
    expected = expected_torchvision_keys(arch)
    assert len(expected) == TORCHVISION_N_KEYS[arch]
    assert torchvision_keys(arch) == [k for k in expected if not k.startswith("fc.")]


def test_resnet18_shapes_match_torchvision():
    sd = torchvision_like_state_dict("resnet18")
    for k, shape in RESNET18_SHAPES.items():
        assert tuple(sd[k].shape) == shape, k


def test_resunet_output_is_per_pixel_at_input_resolution():
    m = ResUNet("resnet18", 16).eval()
    with torch.no_grad():
        y = m(torch.rand(2, 3, 60, 84))  # not a multiple of 32
    assert y.shape == (2, 16, 60, 84)
    assert torch.isfinite(y).all()


def test_torchvision_state_dict_loads_strictly(tmp_path):
    sd = torchvision_like_state_dict("resnet18", seed=1)
    path = tmp_path / "resnet18-imagenet.pth"
    torch.save(sd, path)
    model = build_encoder({"name": "imagenet", "arch": "resnet18", "weights": str(path), "out_dim": 8})
    got = model.encoder.state_dict()
    assert set(got) == {k for k in sd if not k.startswith("fc.")}
    for k, v in got.items():
        assert torch.equal(v, sd[k]), k


def test_mismatching_keys_name_file_and_setting(tmp_path):
    sd = torchvision_like_state_dict("resnet18")
    del sd["layer3.1.conv2.weight"]
    path = tmp_path / "broken.pth"
    torch.save(sd, path)
    with pytest.raises(DataError) as e:
        build_encoder({"name": "imagenet", "arch": "resnet18", "weights": str(path)})
    msg = str(e.value)
    assert str(path) in msg and "encoder2d.weights" in msg and "layer3.1.conv2.weight" in msg


def test_wrong_arch_file_is_a_clear_error(tmp_path):
    path = tmp_path / "r50.pth"
    torch.save(torchvision_like_state_dict("resnet50"), path)
    with pytest.raises(DataError) as e:
        build_encoder({"name": "imagenet", "arch": "resnet18", "weights": str(path)})
    assert str(path) in str(e.value) and "encoder2d.weights" in str(e.value)


def test_missing_weights(tmp_path):
    missing = tmp_path / "nope.pth"
    with pytest.raises(DataError) as e:
        build_encoder({"name": "imagenet", "arch": "resnet18", "weights": str(missing)})
    assert str(missing) in str(e.value) and "encoder2d.weights" in str(e.value)
    with pytest.raises(ConfigError) as e2:
        build_encoder({"name": "pri3d", "arch": "resnet18", "weights": None})
    assert e2.value.setting == "encoder2d.weights"
    with pytest.raises(ConfigError) as e3:
        build_encoder({"name": "scratch", "arch": "resnet101"})
    assert e3.value.setting == "encoder2d.arch"


def test_pri3d_checkpoint_roundtrip(tmp_path):
    torch.manual_seed(3)
    src = ResUNet("resnet18", 8).eval()
    path = save_pri3d_checkpoint(src, tmp_path / "pri3d.pt", {"epochs": 2})
    ckpt = torch.load(path, weights_only=True)
    assert ckpt["arch"] == "resnet18" and ckpt["meta"]["out_dim"] == 8 and ckpt["meta"]["epochs"] == 2
    assert set(ckpt["state_dict"]) == set(src.state_dict())
    dst = build_encoder({"name": "pri3d", "arch": "resnet18", "weights": str(path), "out_dim": 8}).eval()
    x = torch.rand(1, 3, 40, 48)
    with torch.no_grad():
        assert torch.equal(src(x), dst(x))
    # a different decoder width: strict full load fails, encoder-only load works
    with pytest.raises(DataError, match="encoder2d.weights"):
        build_encoder({"name": "pri3d", "arch": "resnet18", "weights": str(path), "out_dim": 16})
    part = build_encoder({"name": "pri3d", "arch": "resnet18", "weights": str(path), "out_dim": 16,
                          "load_decoder": False})
    assert torch.equal(part.encoder.conv1.weight, src.encoder.conv1.weight)
    # a torchvision file is not a pri3d checkpoint
    tv = tmp_path / "tv.pth"
    torch.save(torchvision_like_state_dict("resnet18"), tv)
    with pytest.raises(DataError, match="not a pri3d checkpoint"):
        build_encoder({"name": "pri3d", "arch": "resnet18", "weights": str(tv)})


def test_freeze_encoder():
    m = build_encoder({"name": "scratch", "arch": "resnet18", "out_dim": 4, "freeze": True})
    m.train()
    assert not any(p.requires_grad for p in m.encoder.parameters())
    assert all(p.requires_grad for p in m.decoder.parameters())
    assert not m.encoder.bn1.training and m.decoder.training
    before = m.encoder.bn1.running_mean.clone()
    y = m(torch.rand(2, 3, 32, 32))
    y.sum().backward()
    assert torch.equal(before, m.encoder.bn1.running_mean)
    assert m.decoder.head.weight.grad is not None and m.encoder.conv1.weight.grad is None

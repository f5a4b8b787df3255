"""2D encoders: a ResUNet whose encoder is a ResNet with torchvision's parameter names.

Public API
----------
* :class:`ResUNet` ``(arch="resnet18"|"resnet34"|"resnet50", out_dim, decoder_channels=..., normalize=True,
  output_scale="full"|"half")`` ``nn.Module``: input ``(B, 3, H, W)`` float RGB in [0, 1] (ImageNet
  mean/std normalisation is applied inside when ``normalize``), output ``(B, out_dim, H, W)`` per-pixel
  features at the input resolution, or ``(B, out_dim, H/2, W/2)`` with ``output_scale="half"`` (the
  decoder stops at the stem's scale, as the official PCR-CG Res50 UNet: 128 channels at 120x160 for
  240x320 images, input not normalised). ``model.encoder`` is a :class:`ResNetEncoder` whose ``state_dict()`` keys are exactly
  torchvision's ``resnet18/34/50().state_dict()`` keys without ``fc.*`` (``conv1.weight``,
  ``bn1.running_mean``, ``layer1.0.conv1.weight``, ``layer2.0.downsample.0.weight``, ...).
  ``model.decoder`` is the U-Net decoder (skips from the stem and each ResNet stage).
* :func:`build_encoder` ``(cfg, out_dim=None) -> ResUNet`` for the ``encoder2d`` config group::

      name: scratch | imagenet | pri3d
      arch: resnet18 | resnet34 | resnet50
      weights: PATH or null   # required for imagenet and pri3d
      freeze: false           # encoder parameters frozen (BatchNorm kept in eval mode)
      out_dim: 32             # per-pixel feature width
      normalize: true         # ImageNet mean/std inside (the official code feeds [0, 1] RGB: false)
      output_scale: full      # full | half (features at half the input resolution, as the official code)
      bn_stats: per_image     # per_image | running (see BN_STATS)
      load_decoder: true      # pri3d only: also load the decoder (false: encoder weights only)

  ``imagenet`` weights: a plain torchvision ResNet state dict file
  (``torch.save(torchvision.models.resnet50(weights=...).state_dict(), PATH)``); keys must match the
  encoder exactly (``fc.*`` ignored; a ``module.`` prefix or a ``{"state_dict": ...}`` wrapper is
  accepted). ``pri3d`` weights: a checkpoint written by :func:`save_pri3d_checkpoint`::

      {"format": "pcrcg-resunet", "version": 1, "arch": "resnet50",
       "state_dict": <ResUNet.state_dict()>,           # keys "encoder.*", "decoder.*"
       "meta": {"out_dim": 32, "decoder_channels": [...], ...free-form provenance...}}

  read with ``torch.load(weights_only=True)``. A missing file, a wrong arch or mismatching keys or
  shapes raise :class:`pcrcg.errors.DataError` naming the file and the setting ``encoder2d.weights``;
  ``weights: null`` for imagenet/pri3d raises :class:`pcrcg.errors.ConfigError`. Nothing is ever
  downloaded.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Mapping, Sequence

import torch
import torch.nn.functional as F
from torch import nn

from pcrcg.errors import ConfigError, DataError
from pcrcg.fields import option
from pcrcg.safeload import load_tensors

ARCHS = {"resnet18": ("basic", (2, 2, 2, 2)), "resnet34": ("basic", (3, 4, 6, 3)), "resnet50": ("bottleneck", (3, 4, 6, 3))}
INITS = ("scratch", "imagenet", "pri3d")
PRI3D_FORMAT = "pcrcg-resunet"
OUTPUT_SCALES = ("full", "half")
# What the BatchNorm layers normalise by. ``running``: PyTorch's usual (the batch's statistics in training,
# the running averages at test). ``per_image``: each image by its own per-channel statistics over H x W,
# in training and at test -- what the official PCR-CG computes, whose 2D network stays in train mode and
# is called on one image at a time (BatchNorm over a batch of one); learned affine kept, running
# averages neither used nor updated.
BN_STATS = ("per_image", "running")
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


# --------------------------------------------------------------------------- ResNet (torchvision names)


class PerImageBatchNorm2d(nn.BatchNorm2d):
    """``nn.BatchNorm2d`` (same parameters, buffers and state-dict keys) that normalises every image of
    a ``(B, C, H, W)`` batch by its own per-channel mean and biased variance over ``H x W``, in any mode:
    ``BatchNorm2d.train()`` applied to each image alone, batched. See ``BN_STATS``."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.instance_norm(x, weight=self.weight, bias=self.bias, eps=self.eps)


def per_image_batchnorm(module: nn.Module) -> nn.Module:
    """Make every ``nn.BatchNorm2d`` of ``module`` a :class:`PerImageBatchNorm2d` in place (tensors kept)."""
    for m in module.modules():
        if type(m) is nn.BatchNorm2d:
            m.__class__ = PerImageBatchNorm2d
    return module


def _conv3x3(cin: int, cout: int, stride: int = 1) -> nn.Conv2d:
    return nn.Conv2d(cin, cout, 3, stride=stride, padding=1, bias=False)


def _conv1x1(cin: int, cout: int, stride: int = 1) -> nn.Conv2d:
    return nn.Conv2d(cin, cout, 1, stride=stride, bias=False)


class BasicBlock(nn.Module):
    expansion = 1

    def __init__(self, cin: int, planes: int, stride: int = 1, downsample: nn.Module | None = None):
        super().__init__()
        self.conv1 = _conv3x3(cin, planes, stride)
        self.bn1 = nn.BatchNorm2d(planes)
        self.relu = nn.ReLU(inplace=True)
        self.conv2 = _conv3x3(planes, planes)
        self.bn2 = nn.BatchNorm2d(planes)
        self.downsample = downsample

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        idt = x if self.downsample is None else self.downsample(x)
        y = self.relu(self.bn1(self.conv1(x)))
        y = self.bn2(self.conv2(y))
        return self.relu(y + idt)


class Bottleneck(nn.Module):
    """ResNet v1.5 bottleneck (stride on the 3x3 conv), as in torchvision."""

    expansion = 4

    def __init__(self, cin: int, planes: int, stride: int = 1, downsample: nn.Module | None = None):
        super().__init__()
        self.conv1 = _conv1x1(cin, planes)
        self.bn1 = nn.BatchNorm2d(planes)
        self.conv2 = _conv3x3(planes, planes, stride)
        self.bn2 = nn.BatchNorm2d(planes)
        self.conv3 = _conv1x1(planes, planes * 4)
        self.bn3 = nn.BatchNorm2d(planes * 4)
        self.relu = nn.ReLU(inplace=True)
        self.downsample = downsample

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        idt = x if self.downsample is None else self.downsample(x)
        y = self.relu(self.bn1(self.conv1(x)))
        y = self.relu(self.bn2(self.conv2(y)))
        y = self.bn3(self.conv3(y))
        return self.relu(y + idt)


class ResNetEncoder(nn.Module):
    """torchvision's ResNet without avgpool/fc; ``forward`` returns the 5 feature maps of the U-Net.

    Outputs ``[stem (s/2, 64), layer1 (s/4), layer2 (s/8), layer3 (s/16), layer4 (s/32)]``.
    """

    def __init__(self, arch: str = "resnet18"):
        super().__init__()
        if arch not in ARCHS:
            raise ConfigError("encoder2d.arch", arch, " | ".join(ARCHS))
        kind, layers = ARCHS[arch]
        block = BasicBlock if kind == "basic" else Bottleneck
        self.arch = arch
        self.conv1 = nn.Conv2d(3, 64, 7, stride=2, padding=3, bias=False)
        self.bn1 = nn.BatchNorm2d(64)
        self.relu = nn.ReLU(inplace=True)
        self.maxpool = nn.MaxPool2d(3, stride=2, padding=1)
        self._cin = 64
        self.layer1 = self._make_layer(block, 64, layers[0], 1)
        self.layer2 = self._make_layer(block, 128, layers[1], 2)
        self.layer3 = self._make_layer(block, 256, layers[2], 2)
        self.layer4 = self._make_layer(block, 512, layers[3], 2)
        self.channels = [64] + [p * block.expansion for p in (64, 128, 256, 512)]
        del self._cin
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
            elif isinstance(m, nn.BatchNorm2d):
                nn.init.ones_(m.weight)
                nn.init.zeros_(m.bias)

    def _make_layer(self, block: type, planes: int, n: int, stride: int) -> nn.Sequential:
        down = None
        if stride != 1 or self._cin != planes * block.expansion:
            down = nn.Sequential(_conv1x1(self._cin, planes * block.expansion, stride), nn.BatchNorm2d(planes * block.expansion))
        blocks = [block(self._cin, planes, stride, down)]
        self._cin = planes * block.expansion
        blocks += [block(self._cin, planes) for _ in range(1, n)]
        return nn.Sequential(*blocks)

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        x0 = self.relu(self.bn1(self.conv1(x)))
        x1 = self.layer1(self.maxpool(x0))
        x2 = self.layer2(x1)
        x3 = self.layer3(x2)
        x4 = self.layer4(x3)
        return [x0, x1, x2, x3, x4]


# --------------------------------------------------------------------------- U-Net decoder


class _ConvBNReLU(nn.Sequential):
    def __init__(self, cin: int, cout: int):
        super().__init__(nn.Conv2d(cin, cout, 3, padding=1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True))


class UNetDecoder(nn.Module):
    """Upsample the deepest map and fuse each skip (concat + 3x3 conv-BN-ReLU) up to the input
    resolution: skips layer3 (s/16), layer2 (s/8), layer1 (s/4), stem (s/2), the image (s/1); then a
    1x1 conv to ``out_dim``. ``half``: the last skip is the stem (output at s/2; 4 widths, or the first 4
    of 5)."""

    def __init__(self, enc_channels: Sequence[int], channels: Sequence[int], out_dim: int, half: bool = False):
        super().__init__()
        n = 4 if half else 5
        if len(channels) != n and not (half and len(channels) == 5):
            raise ConfigError("encoder2d.decoder_channels", list(channels),
                              "4 or 5 widths (s/16, s/8, s/4, s/2[, s/1])" if half else "5 widths (s/16, s/8, s/4, s/2, s/1)")
        channels = list(channels)[:n]
        skips = (list(enc_channels[:4])[::-1] + [3])[:n]  # layer3, layer2, layer1, stem[, input image]
        cin = enc_channels[4]
        blocks = []
        for skip, cout in zip(skips, channels):  # one 3x3 conv per scale keeps the CPU budget
            blocks.append(_ConvBNReLU(cin + skip, cout))
            cin = cout
        self.blocks = nn.ModuleList(blocks)
        self.head = nn.Conv2d(cin, out_dim, 1)

    def forward(self, feats: list[torch.Tensor], image: torch.Tensor) -> torch.Tensor:
        skips = (feats[:4][::-1] + [image])[: len(self.blocks)]
        x = feats[4]
        for block, skip in zip(self.blocks, skips):
            x = F.interpolate(x, size=skip.shape[-2:], mode="bilinear", align_corners=False)
            x = block(torch.cat([x, skip], dim=1))
        return self.head(x)


class ResUNet(nn.Module):
    """ResNet encoder (torchvision names) + U-Net decoder: (B, 3, H, W) -> (B, out_dim, H, W)."""

    def __init__(self, arch: str = "resnet18", out_dim: int = 32,
                 decoder_channels: Sequence[int] = (256, 128, 64, 64, 32), normalize: bool = True,
                 output_scale: str = "full", bn_stats: str = "running"):
        super().__init__()
        if int(out_dim) < 1:
            raise ConfigError("encoder2d.out_dim", out_dim, "an integer >= 1")
        if output_scale not in OUTPUT_SCALES:
            raise ConfigError("encoder2d.output_scale", output_scale, " | ".join(OUTPUT_SCALES))
        if bn_stats not in BN_STATS:
            raise ConfigError("encoder2d.bn_stats", bn_stats, " | ".join(BN_STATS))
        self.arch = arch
        self.bn_stats = bn_stats
        self.out_dim = int(out_dim)
        self.decoder_channels = [int(c) for c in decoder_channels]
        self.normalize = bool(normalize)
        self.output_scale = output_scale
        self.encoder = ResNetEncoder(arch)
        self.decoder = UNetDecoder(self.encoder.channels, self.decoder_channels, self.out_dim, half=output_scale == "half")
        if bn_stats == "per_image":
            per_image_batchnorm(self)
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)
        self.frozen = False

    def freeze_encoder(self, frozen: bool = True) -> "ResUNet":
        """Freeze (or unfreeze) the encoder: no gradients, BatchNorm statistics fixed (eval mode)."""
        self.frozen = frozen
        for p in self.encoder.parameters():
            p.requires_grad_(not frozen)
        if frozen:
            self.encoder.eval()
        return self

    def train(self, mode: bool = True) -> "ResUNet":
        super().train(mode)
        if self.frozen:
            self.encoder.eval()
        return self

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        if image.dim() != 4 or image.shape[1] != 3:
            raise ValueError(f"ResUNet expects (B, 3, H, W) images, got {tuple(image.shape)}")
        x = (image - self.mean) / self.std if self.normalize else image
        return self.decoder(self.encoder(x), x)


# --------------------------------------------------------------------------- checkpoints


def torchvision_keys(arch: str) -> list[str]:
    """The encoder's state-dict keys = torchvision's ``<arch>().state_dict()`` keys minus ``fc.*``."""
    return list(ResNetEncoder(arch).state_dict().keys())


def _check_and_load(module: nn.Module, sd: Mapping[str, torch.Tensor], path: Path, what: str) -> None:
    """Strict load with a readable error naming the file, the setting and the first differences."""
    own = module.state_dict()
    missing = [k for k in own if k not in sd]
    unexpected = [k for k in sd if k not in own]
    shapes = [f"{k} {tuple(sd[k].shape)} vs {tuple(own[k].shape)}" for k in own
              if k in sd and hasattr(sd[k], "shape") and tuple(sd[k].shape) != tuple(own[k].shape)]
    if missing or unexpected or shapes:
        parts = []
        if missing:
            parts.append(f"{len(missing)} missing keys (e.g. {missing[:4]})")
        if unexpected:
            parts.append(f"{len(unexpected)} unexpected keys (e.g. {unexpected[:4]})")
        if shapes:
            parts.append(f"{len(shapes)} shape mismatches (file vs model, e.g. {shapes[:3]})")
        raise DataError(path, f"encoder2d.weights: does not match {what}: " + "; ".join(parts))
    module.load_state_dict(sd, strict=True)


def load_torchvision_weights(model: ResUNet, path: str | os.PathLike) -> None:
    """Load a torchvision ResNet state dict file into ``model.encoder`` (strict; ``fc.*`` ignored)."""
    path = Path(path)
    if not path.is_file():
        raise DataError(path, "encoder2d.weights: file does not exist (give a local torchvision ResNet "
                              "state dict; nothing is downloaded)")
    sd = load_tensors(path, "encoder2d.weights")
    if isinstance(sd, Mapping) and "state_dict" in sd and isinstance(sd["state_dict"], Mapping):
        sd = sd["state_dict"]
    if not isinstance(sd, Mapping):
        raise DataError(path, f"encoder2d.weights: expected a state dict, found {type(sd).__name__}")
    sd = {(k[7:] if k.startswith("module.") else k): v for k, v in sd.items()}
    sd = {k: v for k, v in sd.items() if not k.startswith("fc.")}
    _check_and_load(model.encoder, sd, path, f"torchvision {model.arch}")


def save_pri3d_checkpoint(model: ResUNet, path: str | os.PathLike, meta: Mapping[str, Any] | None = None) -> Path:
    """Write ``model`` in the project's pretrained-2D format (see the module docstring)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    m = {"out_dim": model.out_dim, "decoder_channels": list(model.decoder_channels), "normalize": model.normalize,
         "output_scale": model.output_scale}
    m.update(dict(meta or {}))
    ckpt = {"format": PRI3D_FORMAT, "version": 1, "arch": model.arch,
            "state_dict": {k: v.detach().cpu() for k, v in model.state_dict().items()}, "meta": m}
    tmp = path.with_name(path.name + ".partial")
    torch.save(ckpt, tmp)
    os.replace(tmp, path)
    return path


def load_pri3d_checkpoint(model: ResUNet, path: str | os.PathLike, load_decoder: bool = True) -> dict[str, Any]:
    """Load a :func:`save_pri3d_checkpoint` file into ``model`` (strict); returns its ``meta``."""
    path = Path(path)
    if not path.is_file():
        raise DataError(path, "encoder2d.weights: pri3d checkpoint does not exist (written by the 2D "
                              "pretraining stage; nothing is downloaded)")
    ckpt = load_tensors(path, "encoder2d.weights")
    if not (isinstance(ckpt, Mapping) and "state_dict" in ckpt and "arch" in ckpt):
        raise DataError(path, "encoder2d.weights: not a pri3d checkpoint (expected a dict with "
                              "'arch', 'state_dict' and 'meta'; a plain torchvision state dict needs encoder2d=imagenet)")
    if ckpt["arch"] != model.arch:
        raise DataError(path, f"encoder2d.weights: checkpoint arch is {ckpt['arch']} but encoder2d.arch={model.arch}")
    sd = ckpt["state_dict"]
    if load_decoder:
        _check_and_load(model, sd, path, f"ResUNet({model.arch}, out_dim={model.out_dim})")
    else:
        enc = {k[len("encoder."):]: v for k, v in sd.items() if k.startswith("encoder.")}
        _check_and_load(model.encoder, enc, path, f"the {model.arch} encoder")
    return dict(ckpt.get("meta") or {})


def build_encoder(cfg: Any, out_dim: int | None = None) -> ResUNet:
    """A :class:`ResUNet` from an ``encoder2d`` config node (see the module docstring)."""
    name = option(cfg, "name", "scratch")
    if name not in INITS:
        raise ConfigError("encoder2d.name", name, " | ".join(INITS))
    arch = option(cfg, "arch", "resnet18")
    if arch not in ARCHS:
        raise ConfigError("encoder2d.arch", arch, " | ".join(ARCHS))
    width = int(out_dim if out_dim is not None else option(cfg, "out_dim", 32))
    dec = option(cfg, "decoder_channels", None) or (256, 128, 64, 64, 32)
    model = ResUNet(arch, width, decoder_channels=list(dec), normalize=bool(option(cfg, "normalize", True)),
                    output_scale=str(option(cfg, "output_scale", "full") or "full"),
                    bn_stats=str(option(cfg, "bn_stats", "running") or "running"))
    weights = option(cfg, "weights", None)
    if name in ("imagenet", "pri3d") and not weights:
        raise ConfigError("encoder2d.weights", weights,
                          f"a path to a local {'torchvision ResNet state dict' if name == 'imagenet' else 'pri3d checkpoint'} "
                          f"file (encoder2d={name} needs one; nothing is downloaded)")
    if name == "imagenet":
        load_torchvision_weights(model, weights)
    elif name == "pri3d":
        load_pri3d_checkpoint(model, weights, load_decoder=bool(option(cfg, "load_decoder", True)))
    elif weights:
        raise ConfigError("encoder2d.weights", weights, "null for encoder2d=scratch (use imagenet or pri3d to load a file)")
    if bool(option(cfg, "freeze", False)):
        model.freeze_encoder(True)
    return model

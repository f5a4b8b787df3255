"""The KPConv encoder that Predator and GeoTransformer share (the same blocks, widths and radii).

Per level ``l`` of the pyramid the width is ``first_dim * 2**l``:

* level 0: ``SimpleBlock(in_dim -> first_dim / 2)``, ``ResnetBottleneckBlock(first_dim / 2 -> first_dim)``;
* level l >= 1: a strided ``ResnetBottleneckBlock`` (pools level l - 1 onto level l), then two
  ``ResnetBottleneckBlock`` (``dims[l-1] -> dims[l] -> dims[l]``).

This is Predator's 3DMatch encoder and GeoTransformer's KPConv-FPN encoder (its ``init_dim`` is
``first_dim / 2``: 64 at 128). Radii are in voxels of the level: the convolution radius
``conv_radius * voxel * 2**l`` and the kernel extent ``kp_extent * voxel * 2**l``.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any, Mapping

import torch
from torch import nn

from pcrcg.fields import known_fields
from pcrcg.models.kpconv.blocks import ResnetBottleneckBlock, SimpleBlock
from pcrcg.models.kpconv.pyramid import TensorPyramid


@dataclass
class KPConvSettings:
    """What every backbone's config holds for this encoder (``conf/model/common/kpconv.yaml``): the
    input width, the level-0 voxel (m), the levels, level 0's width, the radii in voxels of the level
    and the kernel. Predator's, GeoTransformer's and CoFiNet's configs extend it."""

    in_dim: int = 1
    voxel_size: float = 0.025
    num_layers: int = 4
    first_dim: int = 128
    conv_radius: float = 2.5
    kp_extent: float = 2.0
    num_kernel_points: int = 15
    kernel_seed: int = 0

    @classmethod
    def known(cls, m: Mapping[str, Any], **overrides: Any) -> dict[str, Any]:
        """The entries of ``m`` (a ``model`` config node; other models' keys are ignored) that are
        fields of ``cls``, with ``overrides`` on top."""
        return known_fields(cls, m, **overrides)

    @classmethod
    def from_config(cls, cfg: Any, in_dim: int | None = None) -> Any:
        """``cfg`` as a ``cls``: a ``model`` config node through ``cls.from_mapping``, or a ``cls``
        itself (a copy when ``in_dim`` is given); ``in_dim``, when given, replaces the input width."""
        if isinstance(cfg, cls):
            return cfg if in_dim is None else replace(cfg, in_dim=in_dim)
        return cls.from_mapping(cfg, **({"in_dim": in_dim} if in_dim is not None else {}))

    def metres(self, voxels: float) -> float:
        """A length given in level-0 voxels, in metres."""
        return float(voxels) * float(self.voxel_size)

    @property
    def coarse_level(self) -> int:
        """The coarsest level of the pyramid."""
        return self.num_layers - 1


@dataclass(frozen=True)
class EncoderLayout:
    """Where the encoder's levels start: ``skip_before[k]`` is the index of the first block of level
    ``k + 1`` (its input is the level-``k`` output, kept as a skip), ``dims[l]`` the width of level l."""

    skip_before: tuple[int, ...]
    dims: tuple[int, ...]


def kpconv_encoder(in_dim: int, first_dim: int, num_layers: int, voxel: float, conv_radius: float = 2.5,
                   kp_extent: float = 2.0, n_kernel_points: int = 15,
                   kernel_seed: int = 0) -> tuple[nn.ModuleList, EncoderLayout]:
    """The blocks of the encoder (a ModuleList: parameter names ``<i>.<...>``) and its layout."""
    kp = dict(n_kernel_points=n_kernel_points, kernel_seed=kernel_seed)

    def radius(layer: int) -> float:
        return voxel * conv_radius * 2**layer

    def extent(layer: int) -> float:
        return voxel * kp_extent * 2**layer

    dims = tuple(first_dim * 2**l for l in range(num_layers))
    blocks: list[nn.Module] = [
        SimpleBlock(in_dim, dims[0], radius(0), extent(0), 0, **kp),
        ResnetBottleneckBlock(dims[0] // 2, dims[0], radius(0), extent(0), 0, **kp),
    ]
    skip_before: list[int] = []
    for l in range(1, num_layers):
        skip_before.append(len(blocks))
        blocks.append(ResnetBottleneckBlock(dims[l - 1], dims[l - 1], radius(l - 1), extent(l - 1), l - 1,
                                            strided=True, **kp))
        blocks.append(ResnetBottleneckBlock(dims[l - 1], dims[l], radius(l), extent(l), l, **kp))
        blocks.append(ResnetBottleneckBlock(dims[l], dims[l], radius(l), extent(l), l, **kp))
    return nn.ModuleList(blocks), EncoderLayout(tuple(skip_before), dims)


def run_encoder(blocks: nn.ModuleList, layout: EncoderLayout, x: torch.Tensor,
                pyr: TensorPyramid) -> tuple[torch.Tensor, list[torch.Tensor]]:
    """features (N0, in_dim) -> (coarsest features (N_{L-1}, dims[-1]), skips): ``skips[l]`` is the
    output of level l (N_l, dims[l]) for l < L - 1."""
    skips = []
    for i, block in enumerate(blocks):
        if i in layout.skip_before:
            skips.append(x)
        x = block(x, pyr)
    return x, skips

"""Nearest-neighbour matching of point descriptors (L2), optionally mutual."""

from __future__ import annotations

import numpy as np
import torch


def _nearest(a: torch.Tensor, b: torch.Tensor, chunk: int) -> torch.Tensor:
    """For each row of a (N, D), the index of its L2-nearest row of b (M, D): (N,) int64."""
    bb = (b * b).sum(1)
    out = []
    for s in range(0, a.shape[0], chunk):
        # |a - b|^2 = |a|^2 + |b|^2 - 2 a.b; |a|^2 is constant per row
        d = bb[None, :] - 2.0 * (a[s : s + chunk] @ b.T)
        out.append(torch.argmin(d, dim=1))
    return torch.cat(out) if out else torch.zeros(0, dtype=torch.long, device=a.device)


def match_descriptors(
    desc_src: np.ndarray | torch.Tensor,
    desc_tgt: np.ndarray | torch.Tensor,
    mutual: bool = False,
    device: str | torch.device | None = None,
    chunk: int = 4096,
    threads: int = 1,
) -> np.ndarray:
    """Putative correspondences (K, 2) int64 (source index, target index).

    desc_src (N, D), desc_tgt (M, D). Each source point is matched to its nearest target
    descriptor (K = N); with ``mutual`` only pairs that are each other's nearest neighbour are
    kept, in source order. ``threads``: torch CPU threads meanwhile (0 = torch's setting).
    """
    from pcrcg.registration.ransac import torch_threads

    with torch_threads(threads, device):
        return _match(desc_src, desc_tgt, mutual, device, chunk)


def _match(desc_src, desc_tgt, mutual, device, chunk) -> np.ndarray:
    dev = torch.device(device) if device is not None else torch.device("cpu")
    a = torch.as_tensor(np.asarray(desc_src) if not torch.is_tensor(desc_src) else desc_src, dtype=torch.float32, device=dev)
    b = torch.as_tensor(np.asarray(desc_tgt) if not torch.is_tensor(desc_tgt) else desc_tgt, dtype=torch.float32, device=dev)
    if a.ndim != 2 or b.ndim != 2 or a.shape[1] != b.shape[1]:
        raise ValueError(f"descriptors must be (N, D) and (M, D), got {tuple(a.shape)} and {tuple(b.shape)}")
    if a.shape[0] == 0 or b.shape[0] == 0:
        return np.zeros((0, 2), dtype=np.int64)
    with torch.no_grad():
        ab = _nearest(a, b, chunk)
        src = torch.arange(a.shape[0], device=dev)
        if mutual:
            ba = _nearest(b, a, chunk)
            keep = ba[ab] == src
            src, ab = src[keep], ab[keep]
    return torch.stack([src, ab], 1).cpu().numpy().astype(np.int64)

"""Where torch runs: the ``auto`` device (one resolver for every stage) and how many CPU threads a block of
work uses (no heavy import at module level)."""

from __future__ import annotations

import contextlib
from typing import Any, Iterator


def resolve_device(requested: Any = "auto") -> str:
    """The torch device name for ``requested``: ``None``, ``""`` or ``"auto"`` is ``"cuda"`` when torch has
    CUDA, except inside a DataLoader worker process (CUDA does not survive the fork), else ``"cpu"``
    (also when torch is missing); any other value as a string (``"cpu"``, ``"cuda:1"``, a
    ``torch.device``). Callers that need a ``torch.device`` wrap it: ``torch.device(resolve_device(x))``."""
    if requested not in (None, "", "auto"):
        return str(requested)
    try:
        import torch
        from torch.utils.data import get_worker_info
    except ImportError:  # pragma: no cover
        return "cpu"
    return "cuda" if torch.cuda.is_available() and get_worker_info() is None else "cpu"


@contextlib.contextmanager
def torch_threads(n: int | None, device: Any = None) -> Iterator[None]:
    """Run the block with ``n`` torch CPU threads, then restore the previous number (no-op for ``n`` None or
    <= 0, or a non-CPU ``device``)."""
    import torch

    if not n or n <= 0 or (device is not None and torch.device(device).type != "cpu"):
        yield
        return
    old = torch.get_num_threads()
    if old == n:
        yield
        return
    torch.set_num_threads(int(n))
    try:
        yield
    finally:
        torch.set_num_threads(old)

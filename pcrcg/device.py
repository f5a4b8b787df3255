"""Where the ``auto`` device is: one resolver for every stage (no heavy import at module level)."""

from __future__ import annotations

from typing import Any


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

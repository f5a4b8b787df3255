"""Where torch runs: the ``auto`` device (one resolver for every stage) and how many CPU threads a block of
work uses: torch's (:func:`torch_threads`), and torch's with the native pools of NumPy, SciPy and Open3D
(:func:`cpu_threads`) (no heavy import at module level)."""

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


@contextlib.contextmanager
def cpu_threads(n: int | None, device: Any = None) -> Iterator[None]:
    """:func:`torch_threads` and, for the same block, the native thread pools that NumPy, SciPy and Open3D call
    (OpenBLAS, OpenMP: ``threadpoolctl``) limited to ``n``; the same no-op cases.

    Why: with torch at one thread, the registration's NumPy products still ran OpenBLAS and OpenMP on every core.
    On this 2-core machine that spent CPU without saving time: a cpu-profile evaluation of 30 + 30 pairs
    (2026-12-06, ``python -m pcrcg.evaluate mode=benchmark``) took 49-59 s of CPU (36-44 s wall) with the
    default pools and 38-45 s (38-45 s wall) with them at one thread, the same estimates bit for bit; a whole
    reference run's evaluation (``python -m pcrcg.benchmarks.speed --run``) 127 s of CPU (90 s wall) unpinned
    against 76 s pinned to one core (``taskset -c 0``)."""
    import torch

    if not n or n <= 0 or (device is not None and torch.device(device).type != "cpu"):
        yield
        return
    # NumPy's and SciPy's OpenBLAS loaded before the limits are set: a library first loaded inside the block
    # would keep its default pool
    import numpy  # noqa: F401
    import scipy.linalg  # noqa: F401
    from threadpoolctl import threadpool_limits

    with torch_threads(n, device), threadpool_limits(limits=int(n)):
        yield

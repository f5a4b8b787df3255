"""Where torch runs: the ``auto`` device (one resolver for every stage) and how many CPU threads a block of
work uses: torch's (:func:`torch_threads`), and torch's with the native pools of NumPy, SciPy and Open3D
(:func:`cpu_threads`); how a process keeps freed memory (:func:`keep_freed_memory`); each row's arg-max / arg-min
of a matrix by NumPy's vectorised loops on the CPU (:func:`argmax_rows`, :func:`argmin_rows`) (no heavy import at
module level)."""

from __future__ import annotations

import contextlib
import os
import sys
from typing import Any, Iterator

# glibc's mallopt parameters (malloc.h)
_M_TRIM_THRESHOLD, _M_TOP_PAD, _M_MMAP_MAX = -1, -2, -4
_HEAP_SET: bool | None = None


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


def pin_cores(n: int) -> list[int] | None:
    """Pin every thread of this process, and the threads it starts later, to the first ``n`` CPUs it may run on
    (Linux; elsewhere, or with ``n`` < 1, nothing is done and None is returned): the CPUs kept, sorted.

    For timings on equal terms: a library that starts its own threads (Open3D's RANSAC took ~1.8x its wall time
    in CPU time on 2 cores with ``OMP_NUM_THREADS=1``) then works on the same ``n`` cores as single-threaded code
    beside it, so wall-time ratios compare the same resources."""
    if n < 1 or not hasattr(os, "sched_setaffinity"):
        return None
    keep = sorted(os.sched_getaffinity(0))[:n]
    for task in os.listdir("/proc/self/task"):
        with contextlib.suppress(OSError):  # a thread that ended meanwhile
            os.sched_setaffinity(int(task), keep)
    return keep


def keep_freed_memory() -> bool:
    """Make glibc's malloc serve every allocation from the heap and keep what is freed for the next ones, once
    per process (later calls return the first answer); False where that is not done: not Linux, no glibc, or
    ``PCRCG_MALLOC=default`` in the environment (glibc's own settings).

    Why: glibc maps each allocation of 32 MB or more (less, by its dynamic threshold) afresh and unmaps it when
    freed, so every such tensor of every step is page-faulted and zeroed by the kernel again. GeoTransformer's
    (N, N, C) embeddings and their gradients are ~70-125 MB each at the cpu profile: its training step took
    4.0-4.8 s of CPU, 1.3-1.7 s of it in the kernel (~327k page faults a step); with the heap kept, 2.9-3.9 s
    (0.3-0.7 s in the kernel, 28-47k faults), the same weights bit for bit after 7 steps (2026-12-06, 3
    cpu-profile training pairs, one thread, separate processes). Predator's step, with smaller tensors, was
    within the noise of repeated runs (0.18-0.27 s).
    The cost: memory freed inside the process stays with it (its peak stays its footprint) up to 2 GB above
    the heap's top before glibc gives it back."""
    global _HEAP_SET
    if _HEAP_SET is not None:
        return _HEAP_SET
    _HEAP_SET = False
    if sys.platform != "linux" or os.environ.get("PCRCG_MALLOC", "").strip().lower() == "default":
        return False
    try:
        import ctypes

        mallopt = ctypes.CDLL("libc.so.6").mallopt
    except (OSError, AttributeError):
        return False
    # no mmap for large blocks; trim the heap's top only beyond 2 GB free; grow it 64 MB at a time
    _HEAP_SET = all(mallopt(param, value) == 1 for param, value in
                    ((_M_MMAP_MAX, 0), (_M_TRIM_THRESHOLD, 2**31 - 1), (_M_TOP_PAD, 64 << 20)))
    return _HEAP_SET


def _arg_rows(x: Any, largest: bool) -> Any:
    import numpy as np
    import torch

    if x.device.type != "cpu" or x.dtype not in (torch.float32, torch.float64) or x.ndim != 2:
        return x.argmax(1) if largest else x.argmin(1)
    a = x.detach().numpy()
    return torch.from_numpy(np.asarray(a.argmax(1) if largest else a.argmin(1), dtype=np.int64))


def argmax_rows(x: Any) -> Any:
    """``x.argmax(1)`` of a 2-D tensor x (n, m) -> (n,) int64: the same indices (the first of equal maxima; a NaN
    counts as the largest, its first one taken), on the CPU from NumPy's vectorised loop, which took 8 ms where
    torch's took 37 (512 x 5,700 float32, one thread, 2026-12-06); torch's own elsewhere (other devices, dtypes
    and shapes). No gradient flows through an index."""
    return _arg_rows(x, True)


def argmin_rows(x: Any) -> Any:
    """``x.argmin(1)``, as :func:`argmax_rows` (the first of equal minima; a NaN counts as the smallest)."""
    return _arg_rows(x, False)

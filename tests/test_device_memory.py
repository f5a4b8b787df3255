"""pcrcg.device.keep_freed_memory: large allocations reuse the heap instead of fresh pages (glibc), once
per process, and not at all with PCRCG_MALLOC=default; pcrcg.device.pin_cores: every thread on the same cores."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

# in a fresh process: page faults of 20 allocations (after 5) of a 64 MB torch tensor (torch's CPU allocator calls malloc), each freed before the next, after
# keep_freed_memory() (or without it)
PROBE = """
import json, resource, sys
import torch
from pcrcg.device import keep_freed_memory
kept = keep_freed_memory() if sys.argv[1] == "keep" else None
again = keep_freed_memory() if kept is not None else None
for _ in range(5):  # the first ones page the heap in (kept or not)
    a = torch.ones(16 << 20)
    del a
f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(20):
    a = torch.ones(16 << 20)
    del a
print(json.dumps({"kept": kept, "again": again, "faults": resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0}))
"""


def _probe(mode: str, **env: str) -> dict:
    out = subprocess.run([sys.executable, "-c", PROBE, mode], capture_output=True, text=True, timeout=120,
                         env={**os.environ, **env}, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc")
def test_freed_memory_is_kept_so_large_allocations_stop_faulting_pages():
    plain, kept = _probe("plain"), _probe("keep")
    off = _probe("keep", PCRCG_MALLOC="default")
    assert kept["kept"] is True and kept["again"] is True and off["kept"] is False
    if plain["faults"] < 20 * 10_000:  # a kernel that backs such blocks with huge pages: few faults either way
        pytest.skip(f"{plain['faults']} page faults for 20 fresh 64 MB blocks: nothing to compare here")
    # glibc maps each 64 MB block afresh: ~16k faults per allocation; kept, the heap's pages are reused. A small
    # allocation that lands in a freed block can make the next 64 MB one grow the heap once more (CI of f88330c, under
    # the parallel suite: 16,384 faults, one block): a few such blocks of the 20 at most
    assert kept["faults"] < 3 * 16_384 < plain["faults"] // 4
    assert off["faults"] > 20 * 10_000


def test_pin_cores_pins_the_threads_alive_and_those_started_later():
    """``pin_cores(1)``: every thread of the process, one already running and one started afterwards, runs on the
    first allowed CPU alone (the registration benchmark's Open3D threads with it); 0 pins nothing."""
    import os
    import threading

    from pcrcg.device import pin_cores

    if not hasattr(os, "sched_setaffinity"):
        pytest.skip("no CPU affinity on this platform")
    before = os.sched_getaffinity(0)
    go, seen = threading.Event(), {}

    def report(name):
        go.wait()
        seen[name] = os.sched_getaffinity(0)

    early = threading.Thread(target=report, args=("early",))
    early.start()
    try:
        assert pin_cores(0) is None and os.sched_getaffinity(0) == before
        kept = pin_cores(1)
        assert kept == sorted(before)[:1]
        late = threading.Thread(target=report, args=("late",))
        late.start()
        go.set()
        early.join()
        late.join()
        assert os.sched_getaffinity(0) == seen["early"] == seen["late"] == set(kept)
    finally:
        go.set()
        for task in os.listdir("/proc/self/task"):  # this test process gets all its CPUs back
            os.sched_setaffinity(int(task), before)

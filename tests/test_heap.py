"""heap.held(): freed arrays' pages kept for the next arrays while HybridGI renders (glibc)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from hybridgi_core import heap
from tests.threads import held_on_another_thread

GLIBC = heap._glibc() is not None
MIB = 1 << 20


#: Run in a fresh interpreter: the faults of allocating, writing and freeing a 48 MiB array after
#: one such array was freed before (so that a kept heap has its pages), not held and then held.
#: (In this process another test's viewport worker may still hold the heap.)
PROBE = """
import resource, numpy as np
from hybridgi_core import heap
from tests.threads import held_on_another_thread
def faults(nbytes):
    np.ones(nbytes // 8)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    a = np.ones(nbytes // 8)
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before
released = faults(48 << 20)
with heap.held():
    held = faults(48 << 20)
print(released, held, heap.holders())
"""


@pytest.mark.skipif(not GLIBC, reason="heap tuning is glibc's malloc only")
def test_a_held_heap_serves_a_large_array_again_without_faulting_its_pages_in():
    # 48 MiB: above glibc's largest adaptive mmap threshold (32 MiB), so mmap'd when not held.
    env = {k: v for k, v in os.environ.items() if k not in heap.USER_SETTINGS}
    out = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, check=True, env=env,
                         cwd=Path(__file__).resolve().parents[1])
    released, held, holders = map(int, out.stdout.split())
    # Not held, every page is faulted in afresh: 4 KiB ones, or 2 MiB ones where numpy's
    # transparent huge pages are granted, so at least about one fault per 2 MiB.
    assert released >= (48 << 20) // (4 * MIB), released
    assert held * 8 < released, (held, released)
    assert holders == 0


def test_held_scopes_nest_across_threads_and_the_last_one_releases(monkeypatch):
    calls = []

    class FakeLibc:
        def mallopt(self, param, value):
            calls.append(("mallopt", param, value))
            return 1

        def malloc_trim(self, pad):
            calls.append(("trim", pad))
            return 1

    monkeypatch.setattr(heap, "_libc", [FakeLibc()])
    with held_on_another_thread(heap.held):
        with heap.held():
            assert heap.holders() == 2
        assert heap.holders() == 1 and ("trim", 0) not in calls  # the other thread still holds it
        applied = [c for c in calls if c[0] == "mallopt"]
        assert applied == [("mallopt", p, v) for p, v in heap.HELD]  # applied once, by the first
    assert heap.holders() == 0
    assert calls[-1] == ("trim", 0)
    assert [c for c in calls if c[0] == "mallopt"][len(heap.HELD):] == [("mallopt", p, v) for p, v in heap.RELEASED]


def test_a_failing_block_still_releases_the_heap(monkeypatch):
    trims = []
    fake = type("FakeLibc", (), {"mallopt": lambda self, p, v: 1, "malloc_trim": lambda self, pad: trims.append(pad)})
    monkeypatch.setattr(heap, "_libc", [fake()])
    with pytest.raises(RuntimeError), heap.held():
        raise RuntimeError("a frame failed")
    assert heap.holders() == 0 and trims == [0]


def test_the_users_own_malloc_settings_are_left_alone(monkeypatch):
    monkeypatch.setattr(heap, "_libc", [])
    monkeypatch.setenv("MALLOC_ARENA_MAX", "2")  # not one of ours: still tuned where glibc is
    tuned = heap._glibc()
    monkeypatch.setattr(heap, "_libc", [])
    monkeypatch.setenv("MALLOC_TRIM_THRESHOLD_", "1000000")
    assert heap._glibc() is None
    with heap.held():  # a no-op, not an error
        assert heap.holders() == 0
    assert (tuned is not None) == GLIBC

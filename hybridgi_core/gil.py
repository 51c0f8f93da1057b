"""A short GIL switch interval while HybridGI renders: threads coming back from Embree or numpy
get the interpreter sooner.

Why: a frame runs its work on a pool of one thread per core, a stage thread and the render
thread, each alternating numpy calls and Embree queries (which release the GIL) with Python
between them. A thread that returns from such a call waits for the GIL until the thread holding
it releases it, at the latest after the switch interval (5 ms by default): with 3-4 such threads
on 2 cores, those waits left a core idle. At 0.5 ms, alternating runs on the 2-core VM, 640x360,
the images bit for bit the same, without the GPU passes: the spheres' r32 rung 0.974 -> 0.945 s
(means of nine runs each), the atrium's r48 x16 rung 1.45 -> 1.39 s (three each); set for the
whole process, 0.2 ms gave no more than 0.5 ms, 20 ms less.

`quick_handoff()` is the scope: the interval is set while at least one render or viewport worker
is inside one (counted across threads) and the one before it restored when the last leaves.
"""

from __future__ import annotations

import sys

from .counted_scope import CountedScope

#: Seconds between the interpreter's requests that the thread holding the GIL release it.
SWITCH_INTERVAL_S = 0.0005

_before: list[float] = []


def _shorten() -> None:
    _before[:] = [sys.getswitchinterval()]
    sys.setswitchinterval(SWITCH_INTERVAL_S)


def _restore() -> None:
    if _before:
        sys.setswitchinterval(_before.pop())


#: Run a block with the GIL switch interval at SWITCH_INTERVAL_S (see the module docstring):
#: `with quick_handoff():`; nestable and thread-safe, the first holder sets it, the last one
#: restores the one before.
quick_handoff = CountedScope(_shorten, _restore)


def holders() -> int:
    """How many `quick_handoff()` scopes are open (tests)."""
    return quick_handoff.holders

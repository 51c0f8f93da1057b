"""Freed array memory kept for the next arrays while HybridGI renders (glibc's malloc).

Why: a frame allocates and frees the same large numpy temporaries over and over (rays, hits,
radiance, per-pixel planes: 1-40 MB each), and glibc hands such blocks back to the kernel when
they are freed (mmap'd blocks at once, the heap's top above the trim threshold), so the next
array of that size is faulted in afresh, a page fault and a zeroed page per 4 KiB. On this 2-core
VM the atrium's final render at 640x360 took 138k faults in the render itself and ran 1.50-1.60 s
without its GPU passes; with the heap held (no mmap'd blocks, no trimming) 105-111k and
1.40-1.45 s, the image bit for bit the same (the viewport worker: Cornell's first pass after a
light move published ~5% sooner). Where page faults are cheaper (bare metal) the gain is smaller.

`held()` is the scope: the settings apply while at least one render or viewport worker is inside
one (counted across threads), and when the last leaves, the freed memory goes back to the kernel
(`malloc_trim`) and glibc's thresholds are set to what its own adaptive rule reaches under large
arrays (mmap above 32 MiB, trim above 64 MiB), since any mallopt ends that rule for the process.

Only glibc's malloc is tuned (Linux with glibc; elsewhere `held()` changes nothing), and not at
all when the user set MALLOC_* variables of their own: theirs stand. numpy only, no bpy.
"""

from __future__ import annotations

import contextlib
import ctypes
import logging
import os
import platform
import sys

from .counted_scope import CountedScope

log = logging.getLogger(__name__)

# mallopt parameters (malloc.h)
M_TRIM_THRESHOLD = -1
M_TOP_PAD = -2
M_MMAP_THRESHOLD = -3
M_MMAP_MAX = -4

#: While held: no block is mmap'd (each would be unmapped, and faulted in again, on free), the
#: heap is never trimmed, and it grows 64 MiB at a time.
HELD = ((M_MMAP_MAX, 0), (M_TRIM_THRESHOLD, 2**31 - 1), (M_TOP_PAD, 64 << 20))
#: After the last holder: glibc's defaults as its adaptive threshold leaves them after large
#: frees (DEFAULT_MMAP_THRESHOLD_MAX, twice that for trimming), the default top pad and mmap count.
RELEASED = ((M_MMAP_MAX, 65536), (M_MMAP_THRESHOLD, 32 << 20), (M_TRIM_THRESHOLD, 64 << 20), (M_TOP_PAD, 128 << 10))
#: Environment variables through which a user tunes glibc's malloc: any of them set, we leave it be.
USER_SETTINGS = ("MALLOC_MMAP_MAX_", "MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_", "MALLOC_TOP_PAD_",
                 "GLIBC_TUNABLES")

_libc: list = []


def _glibc():
    """The process's glibc (mallopt, malloc_trim), or None: not Linux, not glibc, user settings."""
    if _libc:
        return _libc[0]
    lib = None
    if sys.platform.startswith("linux") and platform.libc_ver()[0] == "glibc":
        if any(name in os.environ for name in USER_SETTINGS):
            log.info("heap: the user's MALLOC_* / GLIBC_TUNABLES settings stand; malloc left as it is")
        else:
            try:
                lib = ctypes.CDLL(None)
                lib.mallopt.argtypes, lib.mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
                lib.malloc_trim.argtypes, lib.malloc_trim.restype = [ctypes.c_size_t], ctypes.c_int
            except (OSError, AttributeError):
                lib = None
    _libc.append(lib)
    return lib


def _apply(lib, settings) -> bool:
    return all(lib.mallopt(param, value) == 1 for param, value in settings)


def _hold() -> None:
    if not _apply(_glibc(), HELD):
        log.info("heap: mallopt refused a setting; malloc partly tuned")


def _release() -> None:
    lib = _glibc()
    _apply(lib, RELEASED)
    lib.malloc_trim(0)


_scope = CountedScope(_hold, _release)


@contextlib.contextmanager
def held():
    """Keep freed memory in the heap for reuse while the block runs (see the module docstring);
    nestable and thread-safe: the first holder applies the settings, the last one releases."""
    if _glibc() is None:
        yield
        return
    with _scope():
        yield


def holders() -> int:
    """How many `held()` scopes are open (tests)."""
    return _scope.holders

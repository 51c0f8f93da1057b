"""Whole-scene array work in cache-sized blocks of rows, spread over a few threads.

Why: a scene's per-triangle and per-corner passes (the snapshot's checks and normals, the
instances' transforms, the object boxes, the surface table's packing) ran as whole-array numpy
expressions. At millions of triangles each
temporary is tens of MB: freshly mapped pages to fault in, then evicted from the caches before the
next operation reads them (a 2M-triangle mesh's zero-area check: 350-750 ms in one piece). In
blocks of BLOCK_ROWS rows the temporaries stay in the caches and their memory is reused (~270 ms),
and numpy releases the GIL inside its loops, so blocks on two threads take half that again
(~140 ms on this 2-core host).

The blocks write disjoint slices of arrays the caller allocated, so the result does not depend on
the thread count or the order the blocks finish in. numpy only (no bpy): the sync and the core
both use it.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

#: Rows per block: ~64k rows of a few float64 columns is ~1.5 MB of temporaries per operation.
BLOCK_ROWS = 1 << 16
#: Threads at most (the passes are memory-bound: more than a few threads gain nothing).
MAX_THREADS = 4


def block_ranges(n: int, block: int | None = None) -> list[tuple[int, int]]:
    """Consecutive [a, b) row ranges covering n rows, `block` rows each (default BLOCK_ROWS; the
    last one shorter)."""
    step = max(1, int(BLOCK_ROWS if block is None else block))
    return [(a, min(n, a + step)) for a in range(0, max(int(n), 0), step)]


def for_blocks(n: int, work, block: int | None = None, threads: int | None = None) -> list:
    """[work(a, b) for each range of `block_ranges(n, block)`], the calls spread over up to
    `threads` threads (default: the cores, at most MAX_THREADS); in the ranges' order. One block,
    or one thread, runs on the calling thread. work must only write its own rows of shared
    outputs (and must not touch bpy)."""
    ranges = block_ranges(n, block)
    if threads is None:
        threads = min(MAX_THREADS, os.cpu_count() or 1)
    threads = max(1, min(int(threads), len(ranges)))
    if threads == 1:
        return [work(a, b) for a, b in ranges]
    with ThreadPoolExecutor(threads, thread_name_prefix="hybridgi-blocks") as pool:
        return list(pool.map(lambda r: work(*r), ranges))

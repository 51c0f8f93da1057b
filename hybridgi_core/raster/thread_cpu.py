"""CPU time the frame's worker threads spend while the render thread runs a GPU pass.

Why: the benchmark's seconds without the GPU passes (`bench/time_to_quality.py`) subtract each
GPU pass's wall time, which llvmpipe spends on the CPU and a GPU spends in milliseconds. That
is only the seconds a GPU machine would take if nothing else ran meanwhile. A job on the stage
thread or the pool (the glossy light beside the pixel rays' filter and upsampling passes) goes
on during those passes: its CPU time there is subtracted with them, though on a GPU machine it
would still need its CPU. `GPU_OVERLAP_STEP` counts it (milliseconds of one core), so that the
benchmark adds it back.

Linux only (per-thread `/proc/self/task/<tid>/schedstat`, nanoseconds on a CPU); elsewhere
nothing is counted. Threads named VIEWPORT_PREFIX (the viewport's worker, its pixel thread) are
not the frame's and are left out.
"""

from __future__ import annotations

import threading
from pathlib import Path

#: steps_ms key of the worker threads' CPU milliseconds during GPU passes.
GPU_OVERLAP_STEP = "gpu_overlap_cpu"
#: Threads of the viewport's worker, never a final render's.
VIEWPORT_PREFIX = "hybridgi-viewport"
_TASKS = Path("/proc/self/task")
#: Whether this system has per-thread schedstat (checked once: elsewhere nothing is read).
_AVAILABLE = (_TASKS / str(threading.get_native_id()) / "schedstat").exists()


def _run_ns(native_id: int) -> int:
    """Nanoseconds thread `native_id` of this process has run on a CPU (0 if unknown)."""
    try:
        return int((_TASKS / str(native_id) / "schedstat").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return 0


def other_threads_ns() -> dict[int, int]:
    """{native thread id: CPU nanoseconds} of this process's other Python threads (not the
    caller's, not the viewport's), {} where /proc has no per-thread schedstat."""
    if not _AVAILABLE:
        return {}
    me = threading.get_native_id()
    out = {}
    for t in threading.enumerate():
        tid = t.native_id
        if tid is None or tid == me or t.name.startswith(VIEWPORT_PREFIX):
            continue
        out[tid] = _run_ns(tid)
    return out


def cpu_ms_since(before: dict[int, int]) -> float:
    """CPU milliseconds the threads of `before` (an `other_threads_ns()`) ran since then; a
    thread that ended meanwhile counts 0 (its share is lost, a few milliseconds at most)."""
    total = 0
    for tid, ns in before.items():
        now = _run_ns(tid)
        if now >= ns:
            total += now - ns
    return total / 1e6

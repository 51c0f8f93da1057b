"""The CPU time worker threads spend beside a GPU pass (`raster/thread_cpu.py`, `FrameStats`),
which the benchmark adds back to the seconds without GPU passes. Linux only (per-thread
schedstat); no bpy, no GPU: a sleep stands in for the pass."""

from __future__ import annotations

import sys
import threading
import time
from pathlib import Path

import pytest

from hybridgi_core.raster import thread_cpu
from hybridgi_core.raster.frame import GPU_PASS_STEPS, FrameStats

pytestmark = pytest.mark.skipif(not Path("/proc/thread-self/schedstat").exists(),
                                reason="per-thread CPU time from /proc (Linux)")

PASS_S = 0.3


def _busy(stop: threading.Event) -> None:
    x = 0
    while not stop.is_set():
        x += 1  # pure Python: holds the GIL only while the sleeping thread does not need it


def _with_busy_thread(name: str, fn):
    stop = threading.Event()
    t = threading.Thread(target=_busy, args=(stop,), name=name)
    t.start()
    try:
        time.sleep(0.02)  # running before the pass starts
        return fn()
    finally:
        stop.set()
        t.join()


def _gpu_step(stats: FrameStats, name: str = "atrous") -> None:
    with stats.step(name):
        time.sleep(PASS_S)


def test_a_worker_busy_beside_a_gpu_pass_counts_its_cpu_time():
    stats = FrameStats()
    _with_busy_thread("hybridgi-stage", lambda: _gpu_step(stats))
    got = stats.steps_ms[thread_cpu.GPU_OVERLAP_STEP]
    # The busy thread runs on a core of its own while this one sleeps: about the pass's time
    # (a loaded 2-core machine gives it less, never more).
    assert 0.2 * PASS_S * 1e3 < got < 1.3 * PASS_S * 1e3
    assert stats.steps_ms["atrous"] >= PASS_S * 1e3


def test_cpu_steps_count_no_overlap_and_idle_workers_count_about_none():
    stats = FrameStats()
    _with_busy_thread("hybridgi-stage", lambda: _gpu_step(stats, "pixel_rays"))
    assert "pixel_rays" not in GPU_PASS_STEPS
    assert thread_cpu.GPU_OVERLAP_STEP not in stats.steps_ms
    idle = threading.Event()
    t = threading.Thread(target=idle.wait, name="hybridgi-stage")
    t.start()
    try:
        _gpu_step(stats)
    finally:
        idle.set()
        t.join()
    assert stats.steps_ms[thread_cpu.GPU_OVERLAP_STEP] < 0.05 * PASS_S * 1e3


def test_gpu_pass_wrapper_counts_as_a_step_does():
    stats = FrameStats()
    timed = stats.gpu_pass(lambda s: time.sleep(s) or "done")
    assert _with_busy_thread("hybridgi-update_0", lambda: timed(PASS_S)) == "done"
    assert stats.steps_ms[thread_cpu.GPU_OVERLAP_STEP] > 0.2 * PASS_S * 1e3


def test_the_viewport_worker_is_not_the_frames():
    stats = FrameStats()
    _with_busy_thread(thread_cpu.VIEWPORT_PREFIX + "-pixels", lambda: _gpu_step(stats))
    assert stats.steps_ms[thread_cpu.GPU_OVERLAP_STEP] < 0.05 * PASS_S * 1e3


def test_the_benchmark_adds_the_overlap_back():
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
    import time_to_quality as ttq  # noqa: PLC0415

    steps = {"gbuffer": 300.0, "atrous": 100.0, "pixel_rays": 800.0, thread_cpu.GPU_OVERLAP_STEP: 60.0}
    assert ttq.gpu_pass_ms(steps) == pytest.approx(340.0)
    assert ttq.gpu_pass_ms({"gbuffer": 10.0, thread_cpu.GPU_OVERLAP_STEP: 50.0}) == 0.0

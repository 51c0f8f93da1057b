"""The pipeline's worker pool is its parallelism: numpy's OpenBLAS runs on one thread once a
cache updater exists (`blas_threads`), unless the user chose a count."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import pytest

PROBE = textwrap.dedent("""
    import ctypes, numpy as np
    from hybridgi_core import blas_threads
    libs = blas_threads._loaded_openblas()
    if not libs:
        print("none")
        raise SystemExit
    def threads():
        lib = ctypes.CDLL(libs[0])
        for name in ("openblas_get_num_threads64_", "openblas_get_num_threads",
                     "scipy_openblas_get_num_threads64_", "scipy_openblas_get_num_threads"):
            if hasattr(lib, name):
                return getattr(lib, name)()
    before = threads()
    from hybridgi_core.settings import CacheSettings
    from hybridgi_core.snapshot import Material, World, geometry_from_arrays, make_snapshot
    from hybridgi_core.system import GISystem
    quad = geometry_from_arrays([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], [[0, 1, 2], [0, 2, 3]], 0, 0)
    snap = make_snapshot(quad, [Material("m", np.full(3, 0.5, np.float32))], [], World(color=np.ones(3, np.float32)))
    with GISystem(snap, CacheSettings(resolution=4, rays_per_cell=8)):
        print(before, threads())
""")


def _run(env_extra):
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"} | env_extra
    out = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, env=env, timeout=120,
                         cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    assert out.returncode == 0, out.stderr
    return out.stdout.split()


def test_openblas_runs_on_one_thread_under_the_pool():
    words = _run({})
    if words == ["none"]:
        pytest.skip("numpy is not linked against OpenBLAS here")
    before, after = map(int, words)
    assert after == 1, (before, after)


def test_a_users_openblas_num_threads_is_kept():
    words = _run({"OPENBLAS_NUM_THREADS": "2"})
    if words == ["none"]:
        pytest.skip("numpy is not linked against OpenBLAS here")
    assert words == ["2", "2"]

"""One BLAS thread per caller: the pipeline's own worker pool is the parallelism.

numpy's wheels ship OpenBLAS, which runs every matrix product on its own threads (one per core).
The pipeline already splits its work over a pool of one worker per core (`update.py`), so each
worker's small products ((n, 3) @ (3, k), batched SH matmuls) woke a second set of threads that
spin for cores the pool holds: on this 2-core host an (n, 3) @ (3, 2) product cost ~10x its
single-threaded time, and a Cornell frame spent a second of system time in those threads. This
sets the loaded OpenBLAS (or OpenBLAS under SciPy's name) to one thread, through its own C entry
point (no new dependency), unless the user chose a count with OPENBLAS_NUM_THREADS.

Measured (Cornell 640x360, 2 cores, a reference render sharing them): frame 6.36 -> 5.89 s,
system time 2.28 -> 1.30 s.
"""

from __future__ import annotations

import ctypes
import glob
import logging
import os
import sys

log = logging.getLogger(__name__)

#: OpenBLAS' thread-count setters, by the symbol names its builds export (64-bit-integer builds
#: append 64_; SciPy's wheels prefix scipy_).
SETTERS = ("openblas_set_num_threads64_", "openblas_set_num_threads", "scipy_openblas_set_num_threads64_",
           "scipy_openblas_set_num_threads")

_done: list[int] = []


def _loaded_openblas() -> list[str]:
    """Paths of the OpenBLAS libraries this process has loaded (Linux: /proc/self/maps), else
    those numpy bundles next to itself (its wheels' numpy.libs / .libs folders)."""
    paths: list[str] = []
    try:
        with open("/proc/self/maps") as maps:
            for line in maps:
                path = line.rsplit(" ", 1)[-1].strip()
                if "openblas" in os.path.basename(path).lower() and path not in paths:
                    paths.append(path)
    except OSError:
        pass
    if paths:
        return paths
    numpy = sys.modules.get("numpy")
    if numpy is None or not getattr(numpy, "__file__", None):
        return paths
    here = os.path.dirname(numpy.__file__)
    for folder in (os.path.join(os.path.dirname(here), "numpy.libs"), os.path.join(here, ".libs"),
                   os.path.join(here, ".dylibs")):
        paths += sorted(glob.glob(os.path.join(folder, "*openblas*")))
    return paths


def single_threaded_blas() -> int:
    """Set every loaded OpenBLAS to one thread, once per process; returns how many libraries were
    set (0: none found, OPENBLAS_NUM_THREADS set by the user, or not OpenBLAS)."""
    if _done:
        return _done[0]
    count = 0
    if not os.environ.get("OPENBLAS_NUM_THREADS"):
        for path in _loaded_openblas():
            try:
                lib = ctypes.CDLL(path)
            except OSError:
                continue
            for name in SETTERS:
                setter = getattr(lib, name, None)
                if setter is not None:
                    setter.argtypes = [ctypes.c_int]
                    setter(1)
                    count += 1
                    break
    log.debug("single-threaded BLAS in %d libraries", count)
    _done.append(count)
    return count

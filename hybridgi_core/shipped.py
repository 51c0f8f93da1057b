"""Tables shipped with the package as their computation made them, keyed by what they were made from.

Why: a quadrature a render needs once per process (the GGX lobes' albedo and Fresnel tables, the
bent lobe's moments) cost 20-600 ms of a core in every process, and a one-frame headless render
is one process. The file holds the arrays and a key (the grid sizes they were computed for); a
file of another key is ignored, so changing a size never reads a stale table: the table is
computed again then (and the test that compares the file with the computation fails until it
is rebuilt). numpy only, no bpy.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np


def load(path: Path, key: np.ndarray, *names: str) -> tuple | None:
    """The arrays `names` of the table file at `path` when it was made for `key`, else None (no
    file, another key, a missing array)."""
    try:
        with np.load(path) as data:
            if np.array_equal(data["key"], key):
                return tuple(data[name] for name in names)
    except (OSError, KeyError, ValueError):
        pass
    return None


def write(path: Path, key: np.ndarray, **arrays: np.ndarray) -> None:
    """Write `arrays` and their `key` to the table file at `path`."""
    with open(path, "wb") as f:
        np.savez_compressed(f, key=key, **arrays)

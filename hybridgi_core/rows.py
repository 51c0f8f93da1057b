"""Per-row tests and norms of (n, k) arrays with a few columns, computed column by column.

Why: numpy 1.26 reduces an (n, k) array along its rows k values at a time, which for k <= 4 is
5-20x slower than combining its k columns as whole arrays (a 640x360 image's 230k (n, 3) rows:
`np.isfinite(a).all(axis=1)` ~8 ms, these ~1 ms). The results are the same bits: the sums run in
the order numpy's reduction takes for fewer than 8 values.
"""

from __future__ import annotations

import numpy as np


def finite_rows(a: np.ndarray) -> np.ndarray:
    """(n,) bool: every value of the row of a (n, k) is finite (`np.isfinite(a).all(axis=1)`)."""
    out = np.isfinite(a[:, 0])
    for k in range(1, a.shape[1]):
        out &= np.isfinite(a[:, k])
    return out


def row_norms(a: np.ndarray) -> np.ndarray:
    """(n,) the Euclidean norm of each row of a (n, k) (`np.linalg.norm(a, axis=1)`), in a's
    floating dtype."""
    out = a[:, 0] * a[:, 0]
    for k in range(1, a.shape[1]):
        out += a[:, k] * a[:, k]
    return np.sqrt(out, out=out)


def cross_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(n, 3) row-wise cross products of (n, 3) a and b (`np.cross(a, b)`, whose axis moves and
    temporaries cost ~30 us a call on small arrays): the same products, then differences, in
    np.cross's (and Blender's cross_v3_v3v3's) order, so the same bits."""
    out = np.empty(np.broadcast_shapes(a.shape, b.shape), np.result_type(a, b))
    out[:, 0] = a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1]
    out[:, 1] = a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2]
    out[:, 2] = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    return out


def column_bounds(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) (k,) of points (n, k), in their dtype: `points.min(axis=0)`, `.max(axis=0)`, one
    column at a time (the atrium's 960k ray-mesh vertices: 53 -> 2.3 ms)."""
    lo = np.array([points[:, k].min() for k in range(points.shape[1])], points.dtype)
    hi = np.array([points[:, k].max() for k in range(points.shape[1])], points.dtype)
    return lo, hi


def mean_over_rays(x: np.ndarray) -> np.ndarray:
    """(m, ...) float32 mean of x (m, r, ...) over its axis 1 (each pixel's r rays), as one batched
    product with a row of 1/r: numpy's mean over a middle axis of 32 with 6-9 values behind it
    costs ~10x (57.6k pixels x 32 rays x 9 SH terms: 33 -> 3 ms). Rounding differs from
    `x.mean(axis=1)` in the last bits (the order of the sum)."""
    m, r = x.shape[0], x.shape[1]
    flat = np.ascontiguousarray(x, np.float32).reshape(m, r, -1)
    out = np.matmul(np.full((1, r), np.float32(1.0 / r)), flat)
    return out.reshape((m,) + x.shape[2:])


def rows_above(a: np.ndarray, threshold: float) -> np.ndarray:
    """(n,) bool: some value of the row of a (n, k) exceeds threshold (`(a > t).any(axis=1)`;
    `a.max(axis=1) > t` for finite rows)."""
    out = a[:, 0] > threshold
    for k in range(1, a.shape[1]):
        out |= a[:, k] > threshold
    return out


def equal_rows(*columns: np.ndarray) -> np.ndarray:
    """(n,) int64 group ids of the rows whose values are equal in every column (1-D integer
    arrays of n; a float column as `float_bits`), numbered 0..k-1 in the columns' sort order.
    The partition of np.unique(axis=0)'s inverse, ~4x faster: that sorts the rows through a
    structured view (900k mesh corners by vertex and UV: 1338 -> 344 ms)."""
    n = columns[0].shape[0]
    order = np.lexsort(columns[::-1])  # the first column the primary key
    same = np.ones(max(n - 1, 0), bool)
    for c in columns:
        ordered = c[order]
        same &= ordered[1:] == ordered[:-1]
    first = np.ones(n, bool)
    first[1:] = ~same
    group = np.empty(n, np.int64)
    group[order] = np.cumsum(first) - 1
    return group


def float_bits(values: np.ndarray) -> np.ndarray:
    """float32 values as uint32 keys for `equal_rows`: equal keys for equal values (-0.0 as 0.0)."""
    return (np.asarray(values, np.float32) + np.float32(0.0)).view(np.uint32)


def row_patterns(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(patterns (k, L) bool, inverse (n,)): `np.unique(mask, axis=0, return_inverse=True)` of an
    (n, L) bool mask, in its order. Up to 20 columns each row is one integer and the patterns a
    table lookup (`equal_rows`' lexsort would number them alike, for a sort's cost): unique over
    rows sorts them through a structured view, 91 ms of bunny_npm's 640x360 glossy light for its
    one lamp (this: ~2 ms; `reflection.lamp_glossy_without`)."""
    mask = np.asarray(mask, bool)
    columns = mask.shape[1]
    if columns > 20:
        patterns, inverse = np.unique(mask, axis=0, return_inverse=True)
        return patterns, inverse.reshape(-1)
    keys = np.zeros(mask.shape[0], np.int64)
    for j in range(columns):  # the first column the highest bit: the patterns' order is np.unique's
        keys |= mask[:, j].astype(np.int64) << (columns - 1 - j)
    present = np.flatnonzero(np.bincount(keys, minlength=1 << columns))
    index = np.zeros(1 << columns, np.int64)
    index[present] = np.arange(present.size)
    bits = np.left_shift(1, np.arange(columns - 1, -1, -1, dtype=np.int64))
    return (present[:, None] & bits) != 0, index[keys]

"""Row helpers (`hybridgi_core.rows`) against the numpy reductions they replace."""

from __future__ import annotations

import numpy as np

from hybridgi_core.rows import equal_rows, float_bits


def test_equal_rows_groups_as_numpy_unique_over_rows():
    """Rows equal in every column share a group, others do not: the partition of
    np.unique(axis=0)'s inverse of the columns side by side (float columns by `float_bits`,
    which takes -0.0 as 0.0 as np.unique does), numbered 0..k-1 in the columns' sort order."""
    rng = np.random.default_rng(5)
    n = 5000
    vertex = rng.integers(0, 300, n).astype(np.int32)
    uv = (rng.integers(0, 4, (n, 2)) / 4.0).astype(np.float32)
    uv[:10, 0] = -0.0
    uv[10:20, 0] = 0.0
    bits = np.stack([float_bits(uv[:, 0]), float_bits(uv[:, 1])], axis=1)
    group = equal_rows(vertex, bits[:, 0], bits[:, 1])
    key = np.c_[vertex.astype(np.float64), uv.astype(np.float64)]
    _, want = np.unique(key, axis=0, return_inverse=True)
    want = want.reshape(-1)
    groups = len(np.unique(key, axis=0))
    assert groups < n and set(group.tolist()) == set(range(groups))
    # One group id per np.unique group and one np.unique group per id: the same partition.
    assert len(set(zip(group.tolist(), want.tolist(), strict=True))) == groups
    order = np.lexsort((bits[:, 1], bits[:, 0], vertex))
    assert (np.diff(group[order]) >= 0).all()

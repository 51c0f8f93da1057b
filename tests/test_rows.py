"""Row helpers (`hybridgi_core.rows`) against the numpy reductions they replace."""

from __future__ import annotations

import numpy as np

from hybridgi_core.rows import cross_rows, equal_rows, float_bits, row_patterns


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


def test_row_patterns_are_numpy_unique_over_rows():
    """The skip patterns' grouping (`row_patterns`, as `reflection.lamp_glossy_without` groups
    receivers by their skipped lamps) is np.unique(axis=0)'s: the same patterns in the same
    order and the same inverse, for one lamp, several, and more than the integer keys hold (its
    fallback), and for no receivers."""
    rng = np.random.default_rng(3)
    for rows, columns in ((500, 1), (2000, 5), (300, 20), (300, 24), (0, 3)):
        mask = rng.random((rows, columns)) < 0.3
        if rows:
            mask[: rows // 2, :] = mask[0]  # repeated rows
        patterns, inverse = row_patterns(mask)
        want, want_inverse = np.unique(mask, axis=0, return_inverse=True)
        assert patterns.dtype == bool and patterns.shape == want.shape
        assert (patterns == want).all() and (inverse == want_inverse.reshape(-1)).all()
        assert (patterns[inverse] == mask).all()


def test_cross_rows_is_np_cross_bit_for_bit():
    rng = np.random.default_rng(11)
    for dtype in (np.float32, np.float64):
        a = (rng.normal(size=(1000, 3)) * 10.0 ** rng.integers(-8, 8, (1000, 1))).astype(dtype)
        b = rng.normal(size=(1000, 3)).astype(dtype)
        got = cross_rows(a, b)
        assert got.dtype == dtype
        np.testing.assert_array_equal(got, np.cross(a, b))

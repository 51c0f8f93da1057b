"""`hybridgi_core.shipped`: a table file is read only when it was made for the key asked for."""

from __future__ import annotations

import numpy as np

from hybridgi_core import shipped


def test_a_table_reads_back_under_its_key_and_not_under_another(tmp_path):
    path = tmp_path / "t.npz"
    key = np.array([32, 16])
    shipped.write(path, key, a=np.arange(6.0).reshape(2, 3), b=np.ones(4))
    a, b = shipped.load(path, key, "a", "b")
    np.testing.assert_array_equal(a, np.arange(6.0).reshape(2, 3))
    np.testing.assert_array_equal(b, np.ones(4))
    assert shipped.load(path, np.array([32, 17]), "a") is None  # made for other sizes
    assert shipped.load(path, np.array([32]), "a") is None  # another key's shape
    assert shipped.load(path, key, "missing") is None  # an array the file does not hold
    assert shipped.load(tmp_path / "absent.npz", key, "a") is None
    (tmp_path / "bad.npz").write_bytes(b"not a table")
    assert shipped.load(tmp_path / "bad.npz", key, "a") is None

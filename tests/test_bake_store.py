"""The on-disk store of Cycles bakes (addon/bake_store.py): bounded, least recently used first."""

from __future__ import annotations

import importlib.util
import os
import time
from pathlib import Path

import numpy as np

_SPEC = importlib.util.spec_from_file_location("bake_store", Path(__file__).resolve().parents[1] / "addon" / "bake_store.py")
bake_store = importlib.util.module_from_spec(_SPEC)
_SPEC.loader.exec_module(bake_store)


def test_the_disk_keeps_the_most_recently_used_bakes_under_its_limit(tmp_path, monkeypatch):
    """Each bake is ~1 KiB on disk; with room for three, a fourth deletes the least recently used
    one: the oldest written, unless it was read since (a read marks it used). What is left still
    loads, and a deleted bake is simply baked again (get: None)."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    one = np.zeros((16, 16), np.float32)
    size = 1024 + 128  # the array and the .npy header
    store = bake_store.BakeStore("things", kept=0, disk_limit=3 * size)
    folder = store.directory()
    for i, key in enumerate("abc"):
        store.put(key, one + i)
        os.utime(folder / f"{key}.npy", (1000.0 + i, 1000.0 + i))  # written in that order
    assert sorted(p.stem for p in folder.glob("*.npy")) == ["a", "b", "c"]
    np.testing.assert_array_equal(store.get("a"), one)  # read from disk (kept=0): now the newest
    assert os.path.getmtime(folder / "a.npy") > time.time() - 60
    store.put("d", one + 3)
    assert sorted(p.stem for p in folder.glob("*.npy")) == ["a", "c", "d"]  # b: the least recently used
    assert store.get("b") is None
    np.testing.assert_array_equal(store.get("c"), one + 2)
    assert sum(p.stat().st_size for p in folder.glob("*.npy")) <= 3 * size

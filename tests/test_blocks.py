"""Whole-scene passes in blocks over threads (`hybridgi_core.blocks`): the same result whatever the
block size and thread count, on the passes that use them."""

from __future__ import annotations

import numpy as np
import pytest

from hybridgi_core import blocks
from hybridgi_core.shading import SurfaceTable
from hybridgi_core.snapshot import Geometry, Material, sanitized


def test_blocks_cover_every_row_once_in_order():
    seen = np.zeros(1000, int)

    def work(a, b):
        seen[a:b] += 1
        return a, b

    for threads in (1, 3):
        seen[:] = 0
        out = blocks.for_blocks(1000, work, block=64, threads=threads)
        assert out == blocks.block_ranges(1000, 64)
        assert out[0] == (0, 64) and out[-1] == (960, 1000)
        assert np.all(seen == 1)
    assert blocks.for_blocks(0, work) == []


def _messy_geometry(seed: int = 2, n_tri: int = 3000) -> Geometry:
    """Corner-split triangles of 9 interleaved objects, some degenerate, some with NaN corners,
    some normals zero or infinite."""
    rng = np.random.default_rng(seed)
    n_vert = 3 * n_tri
    pos = (rng.random((n_vert, 3)) * 4.0).astype(np.float32)
    tris = rng.permutation(n_vert).astype(np.int32).reshape(n_tri, 3)
    tris[::11, 2] = tris[::11, 1]  # two corners the same vertex
    pos[tris[3::13, 2]] = pos[tris[3::13, 0]]  # two corners at the same place
    pos[rng.integers(0, n_vert, 15)] = np.nan
    normals = rng.standard_normal((n_vert, 3)).astype(np.float32)
    normals[rng.integers(0, n_vert, 40)] = 0.0
    normals[rng.integers(0, n_vert, 4)] = np.inf
    return Geometry(pos, tris, normals, rng.random((n_vert, 2)).astype(np.float32), np.zeros(n_tri, np.int32),
                    rng.integers(0, 9, n_tri).astype(np.int32))


@pytest.mark.parametrize("owned", [False, True])
def test_sanitized_is_the_same_in_small_blocks_on_threads(monkeypatch, owned):
    import copy
    import logging

    logging.disable(logging.WARNING)
    try:
        geometry = _messy_geometry()
        monkeypatch.setattr(blocks, "BLOCK_ROWS", 1 << 30)
        monkeypatch.setattr(blocks, "MAX_THREADS", 1)
        whole = sanitized(copy.deepcopy(geometry), 1, 9, owned=owned)
        monkeypatch.setattr(blocks, "BLOCK_ROWS", 97)
        monkeypatch.setattr(blocks, "MAX_THREADS", 4)
        split = sanitized(copy.deepcopy(geometry), 1, 9, owned=owned)
    finally:
        logging.disable(logging.NOTSET)
    # Some triangles were dropped (NaN corners, no area), the rest kept with unit normals.
    assert 0 < whole.triangle_count < geometry.triangle_count
    assert np.allclose(np.linalg.norm(whole.normals, axis=1), 1.0, atol=1e-5)
    for name in ("positions", "triangles", "normals", "uvs", "material_index", "object_index"):
        assert np.array_equal(getattr(whole, name), getattr(split, name)), name


def test_surface_records_are_the_same_in_small_blocks_on_threads(monkeypatch):
    import logging

    logging.disable(logging.WARNING)
    try:
        geometry = sanitized(_messy_geometry(seed=4), 1, 9)
    finally:
        logging.disable(logging.NOTSET)
    materials = [Material(base_color=np.array([0.5, 0.4, 0.3], np.float32))]
    monkeypatch.setattr(blocks, "BLOCK_ROWS", 1 << 30)
    whole = SurfaceTable(geometry, materials)
    monkeypatch.setattr(blocks, "BLOCK_ROWS", 61)
    monkeypatch.setattr(blocks, "MAX_THREADS", 3)
    split = SurfaceTable(geometry, materials)
    assert np.array_equal(whole.records, split.records)
    assert np.array_equal(whole._positions, split._positions) and np.array_equal(whole._normals, split._normals)
    assert np.array_equal(whole._uvs, split._uvs)


def test_triangle_sizes_fold_each_objects_box_over_blocks(monkeypatch):
    """The per-object box (its squared diagonal is the zero-area test's scale) is folded over every
    block that holds the object's triangles, interleaved or not, NaN corners left out."""
    from hybridgi_core.snapshot import _triangle_sizes

    geometry = _messy_geometry(seed=6)
    pos, tris, obj = geometry.positions, geometry.triangles, geometry.object_index
    finite = np.isfinite(pos).all(axis=1)[tris].all(axis=1)
    corners = pos[tris]
    expect = np.zeros(9)
    for o in range(9):
        sel = corners[(obj == o) & finite].reshape(-1, 3).astype(np.float64)
        expect[o] = np.sum((sel.max(axis=0) - sel.min(axis=0)) ** 2)
    monkeypatch.setattr(blocks, "BLOCK_ROWS", 53)
    got_finite, area2, size2 = _triangle_sizes(pos, tris, obj, 9)
    assert np.array_equal(got_finite, finite)
    assert np.array_equal(size2, expect[obj])
    e1 = corners[:, 1].astype(np.float64) - corners[:, 0]
    e2 = corners[:, 2].astype(np.float64) - corners[:, 0]
    assert np.allclose(area2[finite], np.linalg.norm(np.cross(e1, e2), axis=1)[finite], rtol=1e-12)


@pytest.mark.parametrize("threaded", [False, True])
def test_concat_geometry_joins_parts_as_concatenation_does(monkeypatch, threaded):
    """Copies spread over threads (`concat_geometry`) give the parts' rows in order, triangles
    renumbered past the corners before them, float64 parts cast as astype casts them, the parts
    without tangents zero there and those without normal-map UVs their own UVs."""
    from hybridgi_core import snapshot

    monkeypatch.setattr(snapshot, "CONCAT_THREADED_ROWS", 1 if threaded else 1 << 30)
    monkeypatch.setattr(blocks, "MAX_THREADS", 4)
    rng = np.random.default_rng(7)
    parts = []
    for i, (n_vert, n_tri) in enumerate([(30, 10), (3, 1), (60, 20), (9, 3)]):
        g = Geometry(rng.random((n_vert, 3)) * 1e3,  # float64: cast on the way
                     rng.integers(0, n_vert, (n_tri, 3)).astype(np.int32), rng.random((n_vert, 3)).astype(np.float32),
                     rng.random((n_vert, 2)).astype(np.float32), np.full(n_tri, i % 2, np.int32),
                     np.full(n_tri, i, np.int32),
                     tangents=rng.random((n_vert, 4)).astype(np.float32) if i == 1 else None,
                     normal_uvs=rng.random((n_vert, 2)).astype(np.float32) if i == 2 else None)
        parts.append(g)
    joined = snapshot.concat_geometry(parts)
    offsets = np.cumsum([0] + [p.positions.shape[0] for p in parts[:-1]])
    expected = {
        "positions": np.concatenate([p.positions for p in parts]).astype(np.float32),
        "triangles": np.concatenate([p.triangles + o for p, o in zip(parts, offsets, strict=True)]),
        "normals": np.concatenate([p.normals for p in parts]),
        "uvs": np.concatenate([p.uvs for p in parts]),
        "material_index": np.concatenate([p.material_index for p in parts]),
        "object_index": np.concatenate([p.object_index for p in parts]),
        "tangents": np.concatenate([p.tangents if p.tangents is not None else np.zeros((p.positions.shape[0], 4))
                                    for p in parts]).astype(np.float32),
        "normal_uvs": np.concatenate([p.uvs if p.normal_uvs is None else p.normal_uvs for p in parts]),
    }
    for name, want in expected.items():
        got = getattr(joined, name)
        assert got.dtype == (np.int32 if name.endswith(("triangles", "_index")) else np.float32), name
        assert np.array_equal(got, want), name
    plain = snapshot.concat_geometry([parts[0], parts[3]])
    assert plain.tangents is None and plain.normal_uvs is None
    assert snapshot.concat_geometry([]).triangle_count == 0


def test_concat_geometry_keeps_rows_written_in_place_and_copies_the_rest():
    """`concat_geometry(out=)`: the whole's arrays are the ones given; a part whose positions (or
    normals) are already those rows of them (its maker wrote there: `sync._placed_parts`) is not
    copied, the others are; the result is the plain concatenation's. A wrong array is refused."""
    from hybridgi_core import snapshot

    rng = np.random.default_rng(3)
    sizes = [(12, 4), (6, 2), (9, 3)]
    n_v = sum(v for v, _t in sizes)
    whole = {"positions": np.full((n_v, 3), np.nan, np.float32), "normals": np.full((n_v, 3), np.nan, np.float32)}
    parts, start = [], 0
    for i, (n_vert, n_tri) in enumerate(sizes):
        pos = rng.random((n_vert, 3)).astype(np.float32)
        nrm = rng.random((n_vert, 3)).astype(np.float32)
        if i != 1:  # parts 0 and 2 were written in place, part 1 was not
            whole["positions"][start:start + n_vert], whole["normals"][start:start + n_vert] = pos, nrm
            pos, nrm = whole["positions"][start:start + n_vert], whole["normals"][start:start + n_vert]
        parts.append(Geometry(pos, rng.integers(0, n_vert, (n_tri, 3)).astype(np.int32), nrm,
                              rng.random((n_vert, 2)).astype(np.float32), np.zeros(n_tri, np.int32),
                              np.full(n_tri, i, np.int32)))
        start += n_vert
    want = snapshot.concat_geometry([Geometry(p.positions.copy(), p.triangles, p.normals.copy(), p.uvs,
                                              p.material_index, p.object_index) for p in parts])
    got = snapshot.concat_geometry(parts, out=whole)
    assert got.positions is whole["positions"] and got.normals is whole["normals"]
    for name in ("positions", "normals", "triangles", "uvs", "object_index"):
        assert np.array_equal(getattr(got, name), getattr(want, name)), name
    with pytest.raises(ValueError, match="positions"):
        snapshot.concat_geometry(parts, out={"positions": np.zeros((n_v, 3), np.float64)})

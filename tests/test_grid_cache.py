"""Grid indexing and the cache's exponential moving average."""

import numpy as np
import pytest

from hybridgi_core.cache import CellSamples, IrradianceCache
from hybridgi_core.grid import CacheGrid
from hybridgi_core.settings import CacheSettings


def test_grid_covers_bounds_with_centres_inside():
    g = CacheGrid.from_bounds(np.zeros(3), np.array([2.0, 1.0, 1.5]), 8)
    assert g.dims == (8, 4, 6)
    c = g.centers()
    assert (c > 0).all() and (c < [2.0, 1.0, 1.5]).all()
    flat = np.arange(g.count)
    np.testing.assert_array_equal(g.flatten(g.unflatten(flat)), flat)


def test_flat_scene_gets_cells_off_the_plane():
    g = CacheGrid.from_bounds(np.zeros(3), np.array([4.0, 4.0, 0.0]), 16)
    assert g.dims[2] == 2
    assert np.abs(g.centers()[:, 2]).min() > 0.1


def test_corner_weights_interpolate_positions_exactly():
    g = CacheGrid.from_bounds(np.zeros(3), np.ones(3), 6)
    rng = np.random.default_rng(0)
    p = g.lo + g.cell_size * (0.5 + rng.random((100, 3)) * (np.array(g.dims) - 1))
    flats, w = g.corner_cells(p)
    np.testing.assert_allclose(w.sum(axis=1), 1.0, atol=1e-6)
    recon = np.einsum("nc,nci->ni", w, g.centers(flats.ravel()).reshape(-1, 8, 3))
    np.testing.assert_allclose(recon, p, atol=1e-5)


def test_cells_near_box_respects_radius():
    g = CacheGrid.from_bounds(np.zeros(3), np.full(3, 10.0), 10)
    cells, d = g.cells_near(np.full(3, 5.0), np.full(3, 5.0), 2.0)
    c = g.centers(cells)
    np.testing.assert_allclose(np.linalg.norm(c - 5.0, axis=1), d, atol=1e-5)
    assert (d <= 2.0).all()
    all_d = np.linalg.norm(g.centers() - 5.0, axis=1)
    assert cells.size == int((all_d <= 2.0).sum())


def _samples(cache, cells, value):
    k = cache.settings.sh_coeffs
    t = cache.settings.depth_texels**2
    m = len(cells)
    return CellSamples(
        cells=np.asarray(cells), sh_direct=np.full((m, k, 3), value, np.float32),
        sh_indirect=np.zeros((m, k, 3), np.float32), ao_sh=np.zeros((m, k), np.float32),
        depth_sum=np.ones((m, t, 2), np.float32), depth_count=np.ones(t, np.float32),
        backface=np.zeros(m, np.float32),
    )


@pytest.mark.parametrize("h", [0.5, 0.9, 0.97])
def test_ema_step_response_matches_hysteresis(h):
    cache = IrradianceCache(CacheGrid.from_bounds(np.zeros(3), np.ones(3), 2), CacheSettings(hysteresis=h))
    cells = [0, 3]
    n_warm = int(5 / (1 - h))
    for f in range(n_warm):
        cache.blend(_samples(cache, cells, 1.0), f)
    np.testing.assert_allclose(cache.sh_direct[cells], 1.0, rtol=1e-5)  # a plain mean while young
    for k in range(1, 20):
        cache.blend(_samples(cache, cells, 3.0), n_warm + k)
        expected = 3.0 + (1.0 - 3.0) * h**k
        np.testing.assert_allclose(cache.sh_direct[cells], expected, rtol=1e-4)
    assert (cache.sh_direct[1] == 0).all()  # untouched cells keep their state


def test_urgency_from_geometry_change_is_local_and_quadratic():
    s = CacheSettings(resolution=20, hysteresis=0.95)
    cache = IrradianceCache(CacheGrid.from_bounds(np.zeros(3), np.full(3, 10.0), 20), s)
    cells = cache.on_geometry_changed([(np.full(3, 5.0), np.full(3, 5.0))])
    r = cache.influence_radius()
    d = np.linalg.norm(cache.centers[cells] - 5.0, axis=1)
    np.testing.assert_allclose(cache.urgency[cells], np.clip(1 - (d / r) ** 2, 0, 1), atol=1e-5)
    assert 0 < cells.size < cache.grid.count / 10
    far = np.setdiff1d(np.arange(cache.grid.count), cells)
    assert (cache.urgency[far] == 0).all()


def test_focus_bounds_ignore_a_huge_ground_plane_but_not_room_walls():
    from hybridgi_core.snapshot import ObjectInfo, concat_geometry, geometry_from_arrays, make_snapshot

    def quad(x0, x1, y0, y1, obj):
        return geometry_from_arrays([[x0, y0, 0], [x1, y0, 0], [x1, y1, 0], [x0, y1, 0]], [[0, 1, 2], [0, 2, 3]], 0, obj)

    def block(lo, hi, obj):
        c = np.array([[x, y, z] for z in (lo[2], hi[2]) for y in (lo[1], hi[1]) for x in (lo[0], hi[0])])
        t = [(0, 1, 3), (0, 3, 2), (4, 6, 7), (4, 7, 5), (0, 4, 5), (0, 5, 1), (2, 3, 7), (2, 7, 6), (0, 2, 6), (0, 6, 4), (1, 5, 7), (1, 7, 3)]
        return geometry_from_arrays(c, np.array(t), 0, obj)

    car = block([-2, -1, 0], [2, 1, 1.5], 1)
    snap = make_snapshot(concat_geometry([quad(-50, 50, -50, 50, 0), car]), [], objects=[ObjectInfo("floor"), ObjectInfo("car")])
    lo, hi = snap.focus_bounds()
    assert (hi - lo).max() < 10 and lo[2] == 0.0  # around the car, not the 100 m floor
    cache_grid = CacheGrid.from_bounds(lo, hi, 32)
    assert cache_grid.dims[2] >= 5
    # A floor the size of the objects on it is not a ground plane: full bounds.
    snap2 = make_snapshot(concat_geometry([quad(-3, 3, -3, 3, 0), car]), [], objects=[ObjectInfo("floor"), ObjectInfo("car")])
    np.testing.assert_allclose(np.concatenate(snap2.focus_bounds()), np.concatenate(snap2.bounds()))


def test_focus_bounds_keep_a_room_whose_walls_dwarf_what_moves_inside():
    from hybridgi_core.snapshot import ObjectInfo, concat_geometry, geometry_from_arrays, make_snapshot

    def plane(corners, obj):
        return geometry_from_arrays(corners, [[0, 1, 2], [0, 2, 3]], 0, obj)

    floor = plane([[0, 0, 0], [6, 0, 0], [6, 6, 0], [0, 6, 0]], 0)
    wall = plane([[0, 6, 0], [6, 6, 0], [6, 6, 3], [0, 6, 3]], 1)
    ball = geometry_from_arrays([[2, 2, 0.5], [2.5, 2, 0.5], [2.2, 2.4, 1.0]], [[0, 1, 2]], 0, 2)
    snap = make_snapshot(concat_geometry([floor, wall, ball]), [], objects=[ObjectInfo(n) for n in ("floor", "wall", "ball")])
    np.testing.assert_allclose(np.concatenate(snap.focus_bounds()), np.concatenate(snap.bounds()))


def test_visible_cells_equal_the_corners_the_gather_reads():
    from hybridgi_core.visible import visible_cells

    g = CacheGrid.from_bounds(np.zeros(3), np.array([4.0, 3.0, 2.0]), 12)
    rng = np.random.default_rng(3)
    pts = (rng.random((3000, 3)) * [4.6, 3.6, 2.6] - 0.3).astype(np.float32)  # some outside the grid
    nrm = rng.normal(size=(3000, 3)).astype(np.float32)
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    expected = np.unique(g.corner_cells(pts + nrm * np.float32(0.1 * g.cell_size))[0])
    np.testing.assert_array_equal(visible_cells(g, pts, nrm, 0.1), expected)

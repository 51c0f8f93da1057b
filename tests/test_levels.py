"""Camera-centred cache levels (`hybridgi_core/levels.py`): layout, solve, blend, debug view."""

import numpy as np
import pytest

from hybridgi_core import levels as lv
from hybridgi_core.cache import IrradianceCache
from hybridgi_core.errors import SettingsError
from hybridgi_core.evaluate import corner_visibility, gather
from hybridgi_core.grid import CacheGrid
from hybridgi_core.settings import CacheSettings
from hybridgi_core.snapshot import Material, make_snapshot
from hybridgi_core.system import GISystem
from hybridgi_core.visible import LEVEL_TINTS, cell_debug_colors
from tests.shapes import box


def floor_points(n=4000, seed=3, size=40.0):
    """Points on a z = 0 floor seen from a camera at the origin: depth = distance."""
    rng = np.random.default_rng(seed)
    p = np.zeros((n, 3), np.float32)
    p[:, :2] = rng.uniform(-size / 2, size / 2, (n, 2))
    return p, np.linalg.norm(p, axis=1).astype(np.float32)


def test_layout_is_deterministic_snapped_and_nested():
    base = CacheGrid.from_bounds(np.array([-30, -30, -1.0]), np.array([30, 30, 4.0]), 48)
    p, depth = floor_points()
    up = np.tile(np.float32([[0.0, 0.0, 1.0]]), (p.shape[0], 1))
    a = lv.fit_level_grids(base, p, up, depth, 3, 0.1, budget=1.0)
    b = lv.fit_level_grids(base, p.copy(), up.copy(), depth.copy(), 3, 0.1, budget=1.0)
    assert len(a) == 2
    for ga, gb in zip(a, b, strict=True):
        np.testing.assert_array_equal(ga.lo, gb.lo)
        assert (ga.cell_size, ga.dims) == (gb.cell_size, gb.dims)
    parent = base
    for g in a:
        assert g.cell_size == pytest.approx(parent.cell_size / lv.REFINE)
        # Snapped to the coarser level's cell boundaries, inside its box, no more cells than allowed.
        k = (g.lo - parent.lo) / parent.cell_size
        np.testing.assert_allclose(k, np.round(k), atol=1e-4)
        assert (g.lo >= parent.lo - 1e-4).all() and (g.hi <= parent.hi + 1e-4).all()
        assert g.count <= lv.LEVEL_CELLS * parent.count
        parent = g
    # The budget: the cells the points read in level 1 are no more than in level 0 ...
    level0 = lv.visible_cells(base, p, up, 0.1).size
    rows = lv.level_weight(a[0], p, base) > 0
    assert lv.visible_cells(a[0], p[rows], up[rows], 0.1).size <= level0
    # ... so level 1 holds the nearest points, not all: a camera-centred box.
    assert a[0].count * a[0].cell_size**3 < 0.5 * base.count * base.cell_size**3
    inside = np.all((p >= a[0].lo) & (p <= a[0].hi), axis=1)
    assert depth[inside].mean() < 0.7 * depth.mean()
    # A camera move of a tenth of a cell moves the points a little: the box moves by whole
    # coarse cells or not at all.
    moved = lv.fit_level_grids(base, p + np.float32(0.1 * base.cell_size), up, depth, 2, 0.1, budget=1.0)[0]
    k = (moved.lo - a[0].lo) / base.cell_size
    np.testing.assert_allclose(k, np.round(k), atol=1e-4)
    # Without a budget, every point lies inside level 1 (the quantile is 1).
    whole = lv.fit_level_grids(base, p, up, depth, 2, 0.1, budget=np.inf)[0]
    assert ((p >= whole.lo - 1e-4) & (p <= whole.hi + 1e-4)).all()


def test_settings_range():
    assert CacheSettings().cache_levels == 1
    with pytest.raises(SettingsError, match="cache_levels"):
        CacheSettings(cache_levels=4)
    with pytest.raises(SettingsError, match="cache_levels"):
        CacheSettings(cache_levels=0)


def constant_cache(grid, settings, value):
    """Every cell valid, radiance `value` in every direction (both bands), AO open."""
    cache = IrradianceCache(grid, settings)
    y00 = np.float32(1.0 / 0.28209479177387814)
    cache.sh_direct[:, 0, :] = value * y00
    cache.sh_indirect[:, 0, :] = 2 * value * y00
    cache.ao_sh[:, 0] = y00
    cache.samples[:] = 1
    return cache


def test_no_seam_across_the_level_border():
    """Level 0 holds radiance 1 everywhere, level 1 radiance 3: along a line from outside level 1
    into it, the blend goes from level 0's answer to level 1's without a jump (steps bounded by
    the ramp's slope) and is exactly each level's deep on either side."""
    s = CacheSettings(resolution=8, normal_bias=0.0)
    base = CacheGrid(np.zeros(3, np.float32), 1.0, (8, 8, 8))
    fine_grid = CacheGrid(np.array([2, 2, 2], np.float32), 0.5, (8, 8, 8))
    levels = lv.CacheLevels(constant_cache(base, s, 1.0), [constant_cache(fine_grid, s, 3.0)])
    x = np.linspace(0.5, 4.0, 701, dtype=np.float32)
    pts = np.stack([x, np.full_like(x, 4.0), np.full_like(x, 4.0)], axis=1)
    nrm = np.tile(np.float32([[0.0, 0.0, 1.0]]), (x.size, 1))
    vis = np.ones((x.size, 16), bool)
    g = levels.gather(pts, nrm, vis)
    sd, si, sa, cov = levels.sh_at(pts, nrm, vis)
    assert cov.all()
    e = g.direct[:, 0]
    np.testing.assert_allclose(e[x < 2.0], np.pi, rtol=1e-5)  # level 0 alone outside
    np.testing.assert_allclose(e[x > 2.0 + 0.5 * 0.5 + lv.BLEND_CELLS * 0.5], 3 * np.pi, rtol=1e-5)
    np.testing.assert_allclose(g.indirect[:, 0], 2 * e, rtol=1e-5)
    slope = 2 * np.pi / (lv.BLEND_CELLS * 0.5)  # the ramp's: (3 - 1) pi over BLEND_CELLS fine cells
    assert np.abs(np.diff(e)).max() <= slope * (x[1] - x[0]) * 1.01
    # The SH blend (what pixel rays read) agrees with the irradiance blend here (no clamping).
    from hybridgi_core import sh

    np.testing.assert_allclose(sh.irradiance(sd, nrm)[:, 0], e, rtol=1e-5)


def furnace(rho=0.5, le=1.0):
    mat = Material("furnace", np.full(3, rho, np.float32), None, np.full(3, le, np.float32))
    return make_snapshot(box([0, 0, 0], [4, 4, 4]), [mat])


def test_levels_solve_the_furnace():
    """A closed emissive box: every level must hold the analytic multi-bounce light (direct pi Le,
    indirect pi rho Le / (1 - rho)); level 1 takes its further bounces from level 0 at its hits."""
    rho, le = 0.5, 1.0
    s = CacheSettings(resolution=4, rays_per_cell=64, cache_levels=3)
    with GISystem(furnace(rho, le), s) as gi:
        gi.warm_up(24)
        u = np.linspace(0.2, 1.8, 9, dtype=np.float32)
        a, b = (x.ravel() for x in np.meshgrid(u, u))
        pts = np.stack([a, b, np.zeros_like(a)], 1)
        nrm = np.tile(np.float32([[0.0, 0.0, 1.0]]), (a.size, 1))
        depth = np.linalg.norm(pts - np.float32([0.2, 0.2, 0.0]), axis=1)
        stats = gi.build_levels(pts, nrm, depth, batches=1)
        assert gi.levels is not None and gi.levels.count == 3 and stats.rays > 0
        fine = gi.levels.caches[1]
        assert fine.grid.cell_size == pytest.approx(gi.cache.grid.cell_size / 2)
        g = gi.gather(pts, nrm)
        vis = gi.corner_visibility(pts, nrm)
        assert vis.shape == (pts.shape[0], 24)
        shares = gi.levels.level_shares(pts, nrm, vis)
        assert shares[0].max() == 1.0  # level 1 really answers somewhere
        np.testing.assert_allclose(g.direct, np.pi * le, rtol=1e-2)
        np.testing.assert_allclose(g.indirect, np.pi * rho * le / (1 - rho), rtol=2e-2)
        # Pixel-ray hits read the levels too.
        e = lv.hit_lookup(gi, bounced=True).irradiance(pts, nrm)
        np.testing.assert_allclose(e, np.pi * le / (1 - rho), rtol=2e-2)


def test_default_is_the_single_grid():
    """cache_levels = 1: no level is built, and the system's gather and corner visibility are
    evaluate's own (bit for bit)."""
    s = CacheSettings(resolution=4, rays_per_cell=32)
    with GISystem(furnace(), s) as gi:
        gi.warm_up(8)
        pts = np.float32([[1.0, 1.2, 0.0], [2.5, 0.7, 0.0]])
        nrm = np.float32([[0.0, 0.0, 1.0]] * 2)
        assert gi.build_levels(pts, nrm, np.ones(2, np.float32), 1).rays == 0 and gi.levels is None
        vis = gi.corner_visibility(pts, nrm)
        np.testing.assert_array_equal(vis, corner_visibility(gi.cache, gi.tracer, pts, nrm, float(gi.tracer.epsilon)))
        g, ref = gi.gather(pts, nrm), gather(gi.cache, pts, nrm, corner_visible=vis)
        for name in ("direct", "indirect", "ao"):
            np.testing.assert_array_equal(getattr(g, name), getattr(ref, name))
        assert isinstance(lv.hit_lookup(gi, True), lv.HitLookup)


def test_debug_view_shows_levels():
    s = CacheSettings(resolution=8, normal_bias=0.0)
    base = CacheGrid(np.zeros(3, np.float32), 1.0, (8, 8, 8))
    fine_grid = CacheGrid(np.array([2, 2, 2], np.float32), 0.5, (8, 8, 8))
    levels = lv.CacheLevels(constant_cache(base, s, 1.0), [constant_cache(fine_grid, s, 3.0)])
    pts = np.float32([[1.0, 4.0, 4.0], [4.0, 4.0, 4.0], [4.2, 4.1, 3.9]])
    nrm = np.float32([[0.0, 0.0, 1.0]] * 3)
    np.testing.assert_array_equal(levels.level_at(pts, nrm), [0, 1, 1])
    plain = cell_debug_colors(levels.caches[0], pts, nrm)
    shown = cell_debug_colors(levels.caches[0], pts, nrm, levels=levels)
    np.testing.assert_array_equal(shown[0], plain[0])  # level 0 as before
    assert not np.allclose(shown[1], plain[1])
    # Level 1's colour carries its tint: its hue differs from every level-0 colour's range.
    assert shown[1, 2] > shown[1, 0] and shown[2, 2] > shown[2, 0]


@pytest.mark.blender
@pytest.mark.slow
def test_render_with_levels_and_their_debug_view(tmp_path):
    """Through `hybridgi render`: Cache Levels 2 renders the Cornell box close to the single grid
    (not identically: the finer level is read), and the Cache Cells debug view shows level 1's
    cells in its own hue (the nearest part of the room), which the single grid never shows."""
    import subprocess
    import sys
    from pathlib import Path

    from tests import cli_renders

    root = Path(__file__).resolve().parents[1]
    subprocess.run([sys.executable, str(root / "blend_scenes" / "build.py"), "--only", "cornell", "--out", str(tmp_path)],
                   check=True, capture_output=True, timeout=300)
    blend = tmp_path / "cornell.blend"
    quick = ("--set", "warmup_iterations=2", "--set", "resolution=12", "--set", "rays_per_cell=16",
             "--set", "pixel_samples=1")

    def combined(tag, *extra):
        ch = cli_renders.rendered(blend, tmp_path / tag, "96x72", *quick, *extra)
        return cli_renders.layer(ch, "Combined")

    one, two = combined("one"), combined("two", "--set", "cache_levels=2")
    rel = np.abs(two - one).sum() / np.abs(one).sum()
    assert 0 < rel < 0.05
    tint = np.asarray(LEVEL_TINTS[0], np.float32)

    def tinted(img):
        b = np.maximum(img[..., 2], 1e-6)
        return (img[..., 2] > 0.1) & np.all(np.abs(img[..., :3] / b[..., None] - tint / tint[2]) < 1e-3, axis=-1)

    cells1 = combined("cells1", "--set", "debug_view=CELLS")
    cells2 = combined("cells2", "--set", "debug_view=CELLS", "--set", "cache_levels=2")
    geo = cells1[..., :3].max(axis=-1) > 0.06
    assert not tinted(cells1).any()
    assert tinted(cells2).sum() > 0.05 * geo.sum()


def test_cache_gather_ssao_follows_the_finest_level(monkeypatch):
    """Without pixel rays and with the automatic SSAO radius (one cell), the screen-space pass of
    a levelled gather searches the finest level's cell; a radius the user set stays; the pass's
    own settings are restored after."""
    from types import SimpleNamespace

    from hybridgi_core.evaluate import Gathered
    from hybridgi_core.raster import frame
    from hybridgi_core.raster.settings import RasterSettings

    s = CacheSettings(resolution=8)
    base = CacheGrid(np.zeros(3, np.float32), 1.0, (8, 8, 8))
    fine_grid = CacheGrid(np.array([2, 2, 2], np.float32), 0.5, (8, 8, 8))
    levels = lv.CacheLevels(constant_cache(base, s, 1.0), [constant_cache(fine_grid, s, 3.0)])
    z = np.zeros((1, 3), np.float32)
    monkeypatch.setattr(frame, "gather_levels", lambda *a, **k: Gathered(z, z, np.ones(1, np.float32)))
    monkeypatch.setattr(frame, "upload_texture_2d", lambda array, fmt: array)
    class SSAO:
        def __init__(self, settings):
            self.settings, self.seen = settings, []

        def execute(self, *a, **k):
            self.seen.append(self.settings.ssao_radius)
            return "ssao"

    for auto, radius, want in ((True, 1.0, 0.5), (False, 0.8, 0.8)):
        pipe = SimpleNamespace(gather=None, ssao=SSAO(RasterSettings(ssao_radius=radius, ssao_auto=auto)),
                               gbuffer=SimpleNamespace(bends_normals=False))
        low = SimpleNamespace(height=1, width=1)
        out = frame.FramePipeline._gather_levels(pipe, levels, low, z, z + [0, 0, 1], np.zeros(1, np.int64),
                                                 np.ones((1, 16), bool), None, None, None)
        assert pipe.ssao.seen == [want] and out[2] == "ssao"
        assert pipe.ssao.settings.ssao_radius == radius

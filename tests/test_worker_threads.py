"""The viewport worker on both cores: its pool's thread count changes how fast it converges, never
what it converges to (the cache, the direct light and the visibility mask are bit-identical with
one thread and with two), so a view looks the same on any machine.

bpy-free: the add-on's worker modules are imported as a plain package (as the structural guard in
test_viewport.py does in a subprocess)."""

from __future__ import annotations

import importlib
import sys
import types
from pathlib import Path

import numpy as np
import pytest

from blend_scenes import procedural
from hybridgi_core.settings import CacheSettings
from hybridgi_core.system import GISystem

ADDON = Path(__file__).resolve().parents[1] / "addon"


@pytest.fixture(scope="module")
def worker():
    name = "hybridgi_addon_threads_probe"
    if name not in sys.modules:
        package = types.ModuleType(name)
        package.__path__ = [str(ADDON)]  # the add-on folder, without its __init__ (bpy)
        sys.modules[name] = package
    return importlib.import_module(f"{name}.worker")


def pinhole_gbuffer(scene, settings, w=32, h=24):
    """(position, normal, view) of the Cornell camera, traced as the GPU would rasterize them."""
    cam = procedural.describe("cornell").camera
    m = cam.matrix()
    half_w = 0.5 * cam.sensor_width_mm / cam.lens_mm
    x = ((np.arange(w) + 0.5) / w * 2 - 1) * half_w
    y = ((np.arange(h) + 0.5) / h * 2 - 1) * half_w * h / w
    xx, yy = np.meshgrid(x, y)
    d = np.stack([xx.ravel(), yy.ravel(), -np.ones(xx.size)], 1) @ m[:3, :3].T
    d = (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)
    with GISystem(scene, settings) as primary:
        hits = primary.tracer.intersect(np.repeat(m[None, :3, 3], d.shape[0], 0).astype(np.float32), d)
        ok = hits.prim >= 0
        surf = primary.surfaces.surface(hits.prim[ok], hits.u[ok], hits.v[ok], d[ok])
    pos = np.zeros((h * w, 4), np.float32)
    nrm = np.zeros((h * w, 4), np.float32)
    pos[ok, :3], pos[ok, 3], nrm[ok, :3] = surf.position, 1.0, surf.normal
    return pos.reshape(h, w, 4), nrm.reshape(h, w, 4), np.linalg.inv(m), ok


def converge(worker, scene, settings, view):
    pos, nrm, view_matrix, _ = view
    wk = worker.ViewportWorker(settings, worker.WorkerOptions(direct_passes=3, solver_batches=2, first_batch_rays=8))
    try:
        wk.post_edit(worker.FullScene(scene))
        wk.post_view(worker.ViewRequest(("k",), pos, nrm, pos, nrm, view_matrix, np.eye(4)))
        assert wk.wait_idle(120)
        return wk.latest()
    finally:
        wk.close()


def test_two_threads_converge_to_the_single_thread_result(worker):
    scene = procedural.cornell()
    one = CacheSettings(resolution=12, rays_per_cell=16, threads=1)
    view = pinhole_gbuffer(scene, one)
    a = converge(worker, scene, one, view)
    b = converge(worker, scene, one.with_(threads=2), view)
    assert a.error is None and b.error is None
    ok = view[3].reshape(a.view.direct.shape[:2])
    assert a.view.direct[ok, :3].mean() > 0.1  # lit: the comparison below is not of zeros
    assert a.view.passes == b.view.passes == 3
    np.testing.assert_array_equal(a.view.direct, b.view.direct)
    np.testing.assert_array_equal(a.view.corner_mask, b.view.corner_mask)
    np.testing.assert_array_equal(a.cache.sh_texels, b.cache.sh_texels)
    np.testing.assert_array_equal(a.cache.depth_texels, b.cache.depth_texels)


def test_direct_pass_blocks_cover_every_point_once(worker):
    """The pool's blocks of a direct pass: every point lit once, in order (a point lit by two
    blocks, or left out, would double or drop its light); the blocks' samples differ."""
    scene = procedural.cornell()
    settings = CacheSettings(resolution=8, rays_per_cell=8, threads=2)
    rng = np.random.default_rng(3)
    n = 3 * worker.DIRECT_BLOCK_POINTS + 17
    with GISystem(scene, settings) as gi:
        lo, hi = gi.cache.grid.lo, gi.cache.grid.lo + np.asarray(gi.cache.grid.dims) * gi.cache.grid.cell_size
        pts = (lo + rng.random((n, 3)) * (hi - lo) * 0.5).astype(np.float32)
        pts[:, 2] = lo[2] + 1e-3  # on the floor, facing up to the lamp
        up = np.tile(np.array([[0.0, 0.0, 1.0]], np.float32), (n, 1))
        split = worker._direct_split(gi, pts, up, 5, 4)
        # Each block equals the same call on that block alone (its own frame number).
        bounds = np.linspace(0, n, 5).astype(np.intp)
        for i, (a, b) in enumerate(zip(bounds[:-1], bounds[1:], strict=True)):
            alone = gi.direct(pts[a:b], up[a:b], 5 * worker.MAX_DIRECT_BLOCKS + i, samples=4)
            np.testing.assert_array_equal(split[a:b], alone)
    assert split.shape == (n, 3) and np.isfinite(split).all() and split.mean() > 0

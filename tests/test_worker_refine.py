"""How the viewport worker refines a still view: on both cores (its pool's thread count changes
how fast it converges, never what it converges to: the cache, the direct light and the
visibility mask are bit-identical with one thread and with two), the short first batch re-shaded
first after a lamp edit, and per-pixel final-gather passes once the cache is done.

bpy-free: the add-on's worker modules are imported as a plain package (as the structural guard in
test_viewport.py does in a subprocess)."""

from __future__ import annotations

import contextlib
import dataclasses
import importlib
import sys
import threading
import time
import types
from pathlib import Path
from unittest import mock

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


def cornell_view_with_pattern():
    """(scene, settings, GI (pos, nrm), full-res (pos, nrm), view, proj, half width of the
    camera's image plane at unit distance, the final render's 4-subframe pattern): the Cornell
    camera as `pinhole_gbuffer` traces it, at 32x24 GI and 64x48 full-res pixels, with the
    perspective projection that matches it."""
    from hybridgi_core.raster.subpixel import subpixel_offsets

    scene = procedural.cornell()
    settings = CacheSettings(resolution=10, rays_per_cell=16, threads=2)
    pos, nrm, view_matrix, _ = pinhole_gbuffer(scene, settings)
    full_pos, full_nrm, _, _ = pinhole_gbuffer(scene, settings, 64, 48)
    cam = procedural.describe("cornell").camera
    half_w = 0.5 * cam.sensor_width_mm / cam.lens_mm
    near, far = 0.1, 100.0
    proj = np.array([[1 / half_w, 0, 0, 0], [0, 64 / (48 * half_w), 0, 0],
                     [0, 0, (far + near) / (near - far), 2 * far * near / (near - far)], [0, 0, -1, 0]])
    offsets = subpixel_offsets(4, 1.5, "BLACKMAN_HARRIS").astype(np.float32)
    return scene, settings, (pos, nrm), (full_pos, full_nrm), view_matrix, proj, half_w, offsets


@contextlib.contextmanager
def still_view(worker, scene, settings, options, pos, nrm, view_matrix, full=None):
    """A worker that was given `scene` and one still view (G-buffer pos / nrm; `full`: the
    full-res (pos, nrm), default the same) and went idle; closed on leaving."""
    full_pos, full_nrm = (pos, nrm) if full is None else full
    wk = worker.ViewportWorker(settings, options)
    try:
        wk.post_edit(worker.FullScene(scene))
        wk.post_view(worker.ViewRequest(("k",), pos, nrm, full_pos, full_nrm, view_matrix, np.eye(4)))
        assert wk.wait_idle(120)
        yield wk
    finally:
        wk.close()


def converge(worker, scene, settings, view, **options):
    pos, nrm, view_matrix, _ = view
    options = dict(dict(direct_passes=3, solver_batches=2, first_batch_rays=8, pixel_rays=0), **options)
    with still_view(worker, scene, settings, worker.WorkerOptions(**options), pos, nrm, view_matrix) as wk:
        return wk.latest()


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
    assert a.cache.depth_texels is not None  # packed once the view's own light was complete
    np.testing.assert_array_equal(a.cache.depth_texels, b.cache.depth_texels)


def test_the_first_converged_cache_goes_out_without_the_depth_moments(worker, monkeypatch):
    """A still view with its corner mask reads no depth moments: the first converged cache is
    published without them, and they join the same cache's frame once the view's own light is
    complete (the larger texture: it held back the first GI image)."""
    scene = procedural.cornell()
    settings = CacheSettings(resolution=12, rays_per_cell=16, threads=2)
    pos, nrm, view_matrix, _ = pinhole_gbuffer(scene, settings)
    frames = []
    publish = worker.ViewportWorker._publish

    def record(self, force=True):
        publish(self, force)
        frame = self._published.cache
        if frame is not None and (not frames or frames[-1][0] is not frame):
            frames.append((frame, self._view_state.mask is not None))

    monkeypatch.setattr(worker.ViewportWorker, "_publish", record)
    options = worker.WorkerOptions(direct_passes=1, solver_batches=1, first_batch_rays=8, pixel_rays=4,
                                   pixel_passes=1)
    with still_view(worker, scene, settings, options, pos, nrm, view_matrix):
        assert frames[0][1] and frames[0][0].depth_texels is None
    assert frames[-1][0].depth_texels is not None
    np.testing.assert_array_equal(frames[-1][0].sh_texels, frames[-2][0].sh_texels)  # the depth alone joined


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


def test_interruptible_direct_is_fixed_blocks_and_stops_when_superseded(worker):
    """A still view's full-res direct pass calls `system.direct` block by block (block i with its
    own frame number, the penumbra flags written through), so that an edit drops it between two
    blocks; a superseded pass raises before it traces another block."""
    scene = procedural.cornell()
    settings = CacheSettings(resolution=8, rays_per_cell=8, threads=2)
    rng = np.random.default_rng(4)
    n = 2 * worker.DIRECT_BLOCK_POINTS + 5
    with GISystem(scene, settings) as gi:
        lo, hi = gi.cache.grid.lo, gi.cache.grid.lo + np.asarray(gi.cache.grid.dims) * gi.cache.grid.cell_size
        pts = (lo + rng.random((n, 3)) * (hi - lo)).astype(np.float32)
        pts[:, 2] = lo[2] + 1e-3
        up = np.tile(np.array([[0.0, 0.0, 1.0]], np.float32), (n, 1))
        partial, unshadowed = np.zeros(n, bool), np.zeros((n, 3), np.float32)
        light = worker._interruptible(gi, lambda: False)(pts, up, 7, samples=8, partial=partial,
                                                         unshadowed=unshadowed)
        bounds = np.linspace(0, n, 4).astype(np.intp)
        for i, (a, b) in enumerate(zip(bounds[:-1], bounds[1:], strict=True)):
            flags, open_light = np.zeros(b - a, bool), np.zeros((b - a, 3), np.float32)
            alone = gi.direct(pts[a:b], up[a:b], 7 * worker.MAX_DIRECT_BLOCKS + i, samples=8, partial=flags,
                              unshadowed=open_light)
            np.testing.assert_array_equal(light[a:b], alone)
            np.testing.assert_array_equal(partial[a:b], flags)
            np.testing.assert_array_equal(unshadowed[a:b], open_light)
        assert partial.any() and not partial.all()  # the box's walls shadow part of the floor
        calls = iter([False, True])
        with pytest.raises(worker._Superseded):
            worker._interruptible(gi, lambda: next(calls))(pts, up, 7, samples=8)


def test_a_lamp_edit_relights_the_cache_before_the_full_res_direct_pass(worker, monkeypatch):
    """After a lamp edit of a still view the re-shaded cache solves first (the old cache's GI is
    the image's largest error, the coarse pass shows the lamp's new light meanwhile); the
    full-resolution direct passes follow the solve."""
    scene = procedural.cornell()
    settings = CacheSettings(resolution=10, rays_per_cell=16, threads=2)
    pos, nrm, view_matrix, _ = pinhole_gbuffer(scene, settings)
    full_pos, full_nrm, _, _ = pinhole_gbuffer(scene, settings, 64, 48)  # the direct light's resolution
    fine = []
    original = worker.ViewportWorker._direct_pass

    def record(self, system, state, level=None):
        if level is None:
            fine.append(self._schedule.solved_once)
        return original(self, system, state, level)

    monkeypatch.setattr(worker.ViewportWorker, "_direct_pass", record)
    options = worker.WorkerOptions(direct_passes=2, solver_batches=1, first_batch_rays=8, pixel_rays=0)
    with still_view(worker, scene, settings, options, pos, nrm, view_matrix, (full_pos, full_nrm)) as wk:
        assert len(fine) == 2
        lamps = [dataclasses.replace(lt, power=2.0 * lt.power) for lt in scene.lights]
        wk.post_edit(worker.SetShading(lights=lamps))
        assert wk.wait_idle(120)
    assert fine == [True] * 4


def test_a_lamp_edit_carries_the_views_pixel_passes_until_its_own(worker, monkeypatch):
    """After a lamp edit of a still view with pixel passes, the re-lit cache's solve publishes
    the old passes scaled to it (`gi_carry`): the lamp's power doubled, its GI doubled; the
    first pass over the re-lit cache then replaces them, and it agrees with the carried image
    far better than with the old one."""
    scene = procedural.cornell()
    settings = CacheSettings(resolution=10, rays_per_cell=16, threads=2)
    pos, nrm, view_matrix, ok = pinhole_gbuffer(scene, settings)
    carried, passes = [], []
    carry, pixel_pass = worker.ViewportWorker._carry, worker.ViewportWorker._pixel_pass

    def record_carry(self, system, state):
        old = state.carry[0].copy()
        carry(self, system, state)
        assert state.pixel_sum is None and state.result(0).gi_indirect is state.carried[0]  # what goes out
        carried.append((old, state.carried[0].copy()))

    def record_pass(self, system, state):
        pixel_pass(self, system, state)
        if state.pixel_sum is not None and state.pixel_passes == 1 and carried and not passes:
            passes.append(state.pixel_sum[0].copy())

    monkeypatch.setattr(worker.ViewportWorker, "_carry", record_carry)
    monkeypatch.setattr(worker.ViewportWorker, "_pixel_pass", record_pass)
    options = worker.WorkerOptions(direct_passes=1, solver_batches=1, first_batch_rays=8, pixel_rays=8,
                                   pixel_passes=1)
    with still_view(worker, scene, settings, options, pos, nrm, view_matrix) as wk:
        assert not carried  # no lamp edit yet
        lamps = [dataclasses.replace(lt, power=2.0 * lt.power) for lt in scene.lights]
        wk.post_edit(worker.SetShading(lights=lamps))
        assert wk.wait_idle(120)
    assert len(carried) == 1 and len(passes) == 1
    old, new = (x.reshape(-1, 4)[ok.ravel(), :3] for x in carried[0])
    traced = passes[0].reshape(-1, 4)[ok.ravel(), :3]
    assert old.mean() > 0.05  # lit: the comparisons are not of zeros
    l1 = lambda a, b: float(np.abs(a - b).sum() / np.abs(b).sum())  # noqa: E731
    assert l1(new, 2.0 * old) < 0.05
    assert l1(new, traced) < 0.25 * l1(old, traced)


def test_a_still_view_alternates_pixel_passes_and_full_res_direct_passes(worker, monkeypatch):
    """Once the cache has solved, a still view's pixel passes and full-res direct passes take
    turns, a pixel pass first: the pixel rays' GI removes the larger error."""
    scene = procedural.cornell()
    settings = CacheSettings(resolution=10, rays_per_cell=16, threads=2)
    pos, nrm, view_matrix, _ = pinhole_gbuffer(scene, settings)
    full_pos, full_nrm, _, _ = pinhole_gbuffer(scene, settings, 64, 48)
    order = []
    direct_pass, pixel_pass = worker.ViewportWorker._direct_pass, worker.ViewportWorker._pixel_pass

    def record_direct(self, system, state, level=None):
        direct_pass(self, system, state, level)
        if level is None:
            order.append("d")

    def record_pixels(self, system, state):
        done = state.pixel_passes
        pixel_pass(self, system, state)
        if state.pixel_passes > done:
            order.append("p")

    monkeypatch.setattr(worker.ViewportWorker, "_direct_pass", record_direct)
    monkeypatch.setattr(worker.ViewportWorker, "_pixel_pass", record_pixels)
    options = worker.WorkerOptions(direct_passes=2, solver_batches=1, first_batch_rays=8, pixel_rays=4,
                                   pixel_passes=2)
    with still_view(worker, scene, settings, options, pos, nrm, view_matrix, (full_pos, full_nrm)):
        pass
    assert order == ["p", "d", "p", "d"]


def test_a_first_full_res_pixel_pass_goes_to_the_draw_before_the_workers_resolve(worker, monkeypatch):
    """A still view's first full-res pixel pass is published as soon as its rays are in
    (`ViewResult.gi_pending`, which the draw resolves on the GPU), then the view's first full-res
    direct pass and its edge light are traced, and only then does the worker resolve the rays
    itself (filter, interpolation, detail pixels). The draw's image is that resolve without the
    detail pixels' rays: the same light everywhere else."""
    from hybridgi_core import pixel_gather  # noqa: PLC0415

    pixels = sys.modules[worker.__name__.rsplit(".", 1)[0] + ".worker_pixels"]
    scene, settings, (pos, nrm), (full_pos, full_nrm), view_matrix, proj, _, offsets = cornell_view_with_pattern()
    order, pending, resolved = [], [], []
    direct_pass, edge_pass, publish = (worker.ViewportWorker._direct_pass, worker.ViewportWorker._edge_pass,
                                       worker.ViewportWorker._publish)
    full_res = pixels.full_res

    def record_direct(self, system, state, level=None):
        direct_pass(self, system, state, level)
        if level is None:
            order.append("direct")

    def record_edges(self, system, state):
        edge_pass(self, system, state)
        order.append("edges")

    def record_publish(self, force=True):
        publish(self, force)
        view = self._published.view
        if view is not None and view.gi_pending is not None and not pending:
            assert view.gi_indirect is None  # the draw resolves the rays: no other image goes out with them
            pending.append(view.gi_pending)
            order.append("pending")

    def record_resolve(*args, **kwargs):
        out = full_res(*args, **kwargs)
        resolved.append(out)
        order.append("resolve")
        return out

    monkeypatch.setattr(worker.ViewportWorker, "_direct_pass", record_direct)
    monkeypatch.setattr(worker.ViewportWorker, "_edge_pass", record_edges)
    monkeypatch.setattr(worker.ViewportWorker, "_publish", record_publish)
    monkeypatch.setattr(pixels, "full_res", record_resolve)
    options = worker.WorkerOptions(direct_passes=2, solver_batches=1, first_batch_rays=8, pixel_rays=8,
                                   pixel_passes=1)
    wk = worker.ViewportWorker(settings, options)
    try:
        wk.post_edit(worker.FullScene(scene))
        wk.post_view(worker.ViewRequest(("k",), pos, nrm, full_pos, full_nrm, view_matrix, proj, full_res=True,
                                        aa_offsets=offsets))
        assert wk.wait_idle(120)
        final = wk.latest().view
    finally:
        wk.close()
    assert order[:4] == ["pending", "direct", "edges", "resolve"], order
    assert final.gi_pending is None and final.gi_indirect.shape[:2] == full_pos.shape[:2]
    p = pending[0]
    (h, w), (points, normals, pix) = p.full_shape, p.full
    indirect, direct = pixel_gather.full_res_preview(p.gi, p.position_lo, p.pix, p.points, p.normals, p.view,
                                                     points, normals, pix, (w, h), p.passes, p.plane_sigma,
                                                     p.normal_power)
    lit = np.flatnonzero(full_pos.reshape(-1, 4)[:, 3] > 0)
    a = np.concatenate([indirect, direct], -1).reshape(-1, 8)[lit]
    b = np.concatenate([final.gi_indirect, final.gi_direct], -1).reshape(-1, 8)[lit]
    assert a[:, :3].mean() > 0.05  # lit: the comparison is not of zeros
    differ = ~np.all(np.isclose(a, b, rtol=1e-4, atol=1e-6), axis=1)
    assert 0 < differ.sum() <= resolved[0].detail


def test_a_solved_caches_pixel_pass_starts_before_the_cache_is_packed(worker, monkeypatch):
    """When a pixel pass is a still view's next refinement, the first solve's end starts its rays
    before the converged cache is packed for the draw (the pack, 0.05-0.09 s of the worker thread
    at 640x360, runs beside them: Cornell's first pixel image 1.25 -> 1.0 s in the worker
    timeline)."""
    scene, settings, (pos, nrm), (full_pos, full_nrm), view_matrix, proj, _, _ = cornell_view_with_pattern()
    seen = []
    pack_sh = worker._gather_layout.pack_sh
    workers = []

    def record(cache, size):
        wk = workers[0]
        state = wk._view_state
        if wk._schedule.solved_once and not seen:
            seen.append(state is not None and state.pixel_pass is not None)
        return pack_sh(cache, size)

    monkeypatch.setattr(worker._gather_layout, "pack_sh", record)
    options = worker.WorkerOptions(direct_passes=1, solver_batches=1, first_batch_rays=8, pixel_rays=8,
                                   pixel_passes=1)
    wk = worker.ViewportWorker(settings, options)
    workers.append(wk)
    try:
        wk.post_edit(worker.FullScene(scene))
        wk.post_view(worker.ViewRequest(("k",), pos, nrm, full_pos, full_nrm, view_matrix, proj, full_res=True))
        assert wk.wait_idle(120)
        assert wk.latest().view.pixel_passes == 1
    finally:
        wk.close()
    assert seen == [True]


def test_after_a_lamp_edit_the_other_batches_reshade_as_a_refinement(worker):
    """After a lamp edit the first re-shaded batch's solve is the view's cache (stable: pixel
    passes may be traced over it) and the other batches' re-shade may wait for the view's own
    light (refinable), as a refining batch does; each re-shaded batch is solved again."""
    solve = sys.modules[worker.__name__.rsplit(".", 1)[0] + ".worker_solve"]
    scene = procedural.cornell()
    settings = CacheSettings(resolution=8, rays_per_cell=16, threads=2)
    with GISystem(scene, settings) as gi:
        sched = solve.SolveSchedule(2, first_rays=8)
        sched.attach(gi)
        cells = gi.surface_cells()
        while sched.has_work:
            sched.step(cells)
        assert gi.solver.batches == 2 and sched.stable and not sched.refinable
        epoch = sched.epoch
        lamps = [dataclasses.replace(lt, power=2.0 * lt.power) for lt in scene.lights]
        gi.set_lights(dataclasses.replace(scene, lights=lamps))
        sched.changed(shading=True, geometry=False, materials=False)
        assert not sched.stable
        while not sched.solved_once:
            sched.step(cells)
        assert sched.phase == solve.RELIGHT and sched.stable and sched.refinable
        version = gi.cache.version
        while sched.has_work:
            sched.step(cells)
        assert gi.cache.version > version and sched.epoch == epoch + 1 and sched.stable
        # An edit that cuts a refining batch short: its traced part is in the re-lit solve, whose
        # cache is stable while the rest of the batch waits; each part traced leaves it unstable
        # until the batch is solved.
        old = solve.MORE_PART_RAYS
        solve.MORE_PART_RAYS = 16 * 64  # many parts
        try:
            sched.batches = 3
            sched.phase = solve.MORE
            sched.step(cells)
            assert sched._pending is not None and not sched.stable
            gi.set_lights(scene)
            sched.changed(shading=True, geometry=False, materials=False)
            while not sched.solved_once:
                sched.step(cells)
            assert sched._pending is not None and sched.stable and sched.refinable
            while sched.phase == solve.RELIGHT:
                sched.step(cells)
            while sched.phase != solve.MORE:
                sched.step(cells)
            sched.step(cells)
            assert not sched.stable
            while sched.has_work:
                sched.step(cells)
        finally:
            solve.MORE_PART_RAYS = old
        assert sched.stable and gi.solver.batches == 3


def test_pixel_passes_over_a_further_reshaded_cache_replace_the_shown_ones_when_as_many(worker):
    """Pixel passes over the same cache and epoch, re-shaded further since (a lamp edit's later
    batches), are summed apart: the shown mean stays until they are as many, then they replace it;
    passes over another epoch start over at once."""
    view = sys.modules[worker.__name__.rsplit(".", 1)[0] + ".worker_view"]
    pos = np.zeros((2, 2, 4), np.float32)
    request = worker.ViewRequest(("k",), pos, pos, pos, pos, np.eye(4), np.eye(4))
    state = view.ViewState(request, 0, (np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, np.intp)), np.zeros(0))
    img = lambda v: np.full((2, 2, 4), v, np.float32)  # noqa: E731
    first, later = (1, 5, False), (1, 5, True)
    none = np.zeros((0, 7), np.float32)  # no GI points: no cache values
    state.add_pixels(img(1.0), img(1.0), first, none)
    state.add_pixels(img(3.0), img(3.0), first, none)
    assert state.refines(later) and state.passes_over(later) == 0 and state.passes_over(first) == 2
    state.add_pixels(img(10.0), img(10.0), later, none)
    assert state.pixel_key == first and state.pixel_passes == 2 and state.passes_over(later) == 1
    np.testing.assert_array_equal(state.result(0).gi_indirect, img(2.0))
    state.add_pixels(img(20.0), img(20.0), later, none)
    assert state.pixel_key == later and state.pixel_passes == 2 and state.pixel_next is None
    np.testing.assert_array_equal(state.result(1).gi_indirect, img(15.0))
    state.add_pixels(img(7.0), img(7.0), (1, 6, True), none)  # a new epoch: the passes start over
    assert state.pixel_passes == 1
    np.testing.assert_array_equal(state.result(2).gi_indirect, img(7.0))


def test_a_lamp_edit_traces_pixel_passes_over_the_first_reshaded_batch_then_over_all(worker, monkeypatch):
    """After a lamp edit of a view whose cache holds two batches, the pixel passes are traced
    over the first re-shaded batch's solve, and again once the other batch is re-shaded; the
    settled view shows the latter."""
    scene = procedural.cornell()
    settings = CacheSettings(resolution=10, rays_per_cell=16, threads=2)
    pos, nrm, view_matrix, _ = pinhole_gbuffer(scene, settings)
    keys = []
    pixel_pass = worker.ViewportWorker._pixel_pass

    def record(self, system, state):
        pixel_pass(self, system, state)
        if state.pixel_pass is None:
            keys.append(self._pixel_key(system)[1:])

    monkeypatch.setattr(worker.ViewportWorker, "_pixel_pass", record)
    options = worker.WorkerOptions(direct_passes=1, solver_batches=2, first_batch_rays=8, pixel_rays=4,
                                   pixel_passes=1)
    with still_view(worker, scene, settings, options, pos, nrm, view_matrix) as wk:
        assert wk._session.system.solver.batches == 2
        keys.clear()
        lamps = [dataclasses.replace(lt, power=2.0 * lt.power) for lt in scene.lights]
        wk.post_edit(worker.SetShading(lights=lamps))
        assert wk.wait_idle(120)
        shown = wk._view_state.pixel_key
    epoch = keys[0][0]
    assert keys == [(epoch, False), (epoch, True)] and shown[1:] == (epoch, True)


def test_relight_order_starts_with_the_short_first_batch(worker):
    """After a lamp edit the viewport re-shades the batch with the fewest stored rays first, then
    the one carrying the bounces, then the rest; each batch once."""
    solve = sys.modules[worker.__name__.rsplit(".", 1)[0] + ".worker_solve"]
    s = CacheSettings(resolution=6, rays_per_cell=16, threads=1)
    with GISystem(procedural.cornell(), s) as gi:
        sol = gi.solver
        sol.begin(gi.surface_cells())
        sol.trace_batch(0, rays=4)
        for b in (1, 2, 3):
            sol.trace_batch(b)
        sol.bounce_from = 3
        assert solve.relight_order(sol) == [0, 3, 1, 2]
        sol.bounce_from = 0
        assert solve.relight_order(sol) == [0, 1, 2, 3]
        sol.begin(gi.surface_cells())
        for b in (0, 1, 2):
            sol.trace_batch(b)  # equal batches: the bouncing one first
        sol.bounce_from = 2
        assert solve.relight_order(sol) == [2, 0, 1]
        # A batch traced in part only (a refinement cut short by the edit) never comes first,
        # however few its rays: the first solve needs a source in every cell.
        sol.trace_batch(3, gi.surface_cells()[:5])
        sol.bounce_from = 0
        assert solve.relight_order(sol) == [0, 1, 2, 3]


def test_a_lamp_edit_during_a_refining_batch_keeps_solving(worker):
    """A lamp edit that arrives while a refining batch is traced in parts: the re-shade and the
    solves that follow run (no step may fail on the partial batch) and the view settles lit."""
    solve = sys.modules[worker.__name__.rsplit(".", 1)[0] + ".worker_solve"]
    scene = procedural.cornell()
    settings = CacheSettings(resolution=12, rays_per_cell=32, threads=2)
    with GISystem(scene, settings) as gi:
        sched = solve.SolveSchedule(3, first_rays=8)
        sched.attach(gi)
        cells = gi.surface_cells()
        while sched.phase != solve.MORE:
            sched.step(cells)
        old = solve.MORE_PART_RAYS
        solve.MORE_PART_RAYS = 32 * 64  # many parts: the edit lands mid-batch
        try:
            sched.step(cells)
            assert sched._pending is not None
            lamps = [dataclasses.replace(lt, power=2.0 * lt.power) for lt in scene.lights]
            gi.set_lights(dataclasses.replace(scene, lights=lamps))
            sched.changed(shading=True, geometry=False, materials=False)
            for _ in range(400):
                if not sched.has_work:
                    break
                sched.step(cells)
        finally:
            solve.MORE_PART_RAYS = old
        assert not sched.has_work and gi.solver.batches == 3
        assert np.isfinite(gi.cache.sh_indirect).all() and gi.cache.sh_indirect[cells, 0].sum() > 0


def test_pixel_passes_of_a_still_view_agree_with_the_converged_cache(worker):
    """Once the cache is done the worker traces per-pixel final-gather passes for the still view
    and publishes their mean (the textures that replace the gather and SSAO): finite, AO in
    [0, 1], background as the GPU gather writes it, and the same light on average as the
    final render's converged cache gathered at those pixels (both estimate the irradiance there;
    the rays add what the cache's cells smear, a few percent of the mean)."""
    scene = procedural.cornell()
    settings = CacheSettings(resolution=10, rays_per_cell=32, threads=2)
    view = pinhole_gbuffer(scene, settings, 40, 30)
    pos, nrm, _, ok = view
    p = converge(worker, scene, settings, view, pixel_rays=16, pixel_passes=2)
    assert p.error is None and p.view.pixel_passes == 2
    ind, dirc = p.view.gi_indirect.reshape(-1, 4), p.view.gi_direct.reshape(-1, 4)
    assert np.isfinite(ind).all() and np.isfinite(dirc).all()
    assert (ind[ok, 3] >= 0).all() and (ind[ok, 3] <= 1).all() and (ind[ok, :3] >= 0).all()
    np.testing.assert_array_equal(ind[~ok], np.tile([0.0, 0.0, 0.0, 1.0], ((~ok).sum(), 1)))
    with GISystem(scene, settings) as final:
        final.warm_up(16)
        g = final.gather(pos.reshape(-1, 4)[ok, :3], nrm.reshape(-1, 4)[ok, :3])
    ratio = float(ind[ok, :3].sum() / g.indirect.sum())
    assert 0.85 < ratio < 1.15, ratio
    # Without pixel rays nothing is published in their place.
    q = converge(worker, scene, settings, view, pixel_rays=0)
    assert q.view.gi_indirect is None and q.view.pixel_passes == 0


def test_a_pixel_pass_makes_the_final_renders_textures_and_a_dropped_one_stops(worker):
    """A viewport pixel pass (`worker_pixels`: traced on a thread of its own, filtered at the end)
    is exactly `pixel_gather.gi_images` (the same rays, the same filter); a dropped one stops
    (`trace_pixels(stop=)`)."""
    from concurrent import futures  # noqa: PLC0415

    from hybridgi_core import pixel_gather  # noqa: PLC0415
    from hybridgi_core.raster.settings import RasterSettings  # noqa: PLC0415
    from hybridgi_core.visible import pixels_to_points  # noqa: PLC0415

    pixels = sys.modules[worker.__name__.rsplit(".", 1)[0] + ".worker_pixels"]
    scene = procedural.cornell()
    settings = CacheSettings(resolution=10, rays_per_cell=32, threads=2)
    pos, nrm, view_matrix, _ = pinhole_gbuffer(scene, settings, 64, 48)
    raster = RasterSettings()
    with GISystem(scene, settings) as gi, futures.ThreadPoolExecutor(1) as thread:
        gi.warm_up(8)
        points, normals, pix = pixels_to_points(pos, nrm)
        visible = gi.corner_visibility(points, normals)
        ref_ind, ref_dir, _ = pixel_gather.gi_images(
            gi, pos, nrm, pix, points, normals, visible, view_matrix, pixels.FRAME_BASE, 16,
            passes=raster.pixel_filter, plane_sigma=raster.bilateral_plane_sigma,
            normal_power=raster.bilateral_normal_power)
        done = threading.Event()
        p = pixels.PixelPass("k", 0)
        p.start(thread, gi, points, normals, visible, 16, on_done=done.set)
        assert done.wait(60) and p.done
        out = pixels.images(p.result(), pos, pix, points, normals, view_matrix, raster)
        # A pass dropped before its thread begins traces nothing: every work item sees the stop.
        q = pixels.PixelPass("k", 1)
        q.drop()
        q.start(thread, gi, points, normals, visible, 16)
        futures.wait([q._future])
        assert not np.any(q.result().sh)
    np.testing.assert_array_equal(out[0], ref_ind)
    np.testing.assert_array_equal(out[1], ref_dir)


def test_a_still_view_finishes_its_pixel_passes_and_goes_idle(worker):
    """Pixel passes traced on their own thread end: the worker waits for each, completes the
    passes asked for and then has nothing left to do."""
    scene = procedural.cornell()
    settings = CacheSettings(resolution=8, rays_per_cell=16, threads=2)
    view = pinhole_gbuffer(scene, settings, 40, 30)
    p = converge(worker, scene, settings, view, pixel_rays=4, pixel_passes=3)
    assert p.stats.idle and p.view.pixel_passes == 3 and p.view.gi_indirect is not None


def _glossy_cornell():
    """The Cornell box with the default specular layer (roughness 0.3) on every material."""
    from hybridgi_core import specular as sp  # noqa: PLC0415

    scene = procedural.cornell()
    layer = sp.SpecularLayer(roughness=0.3)
    return dataclasses.replace(scene, materials=[dataclasses.replace(m, specular=layer) for m in scene.materials])


def _full_res_glossy_request(worker, scene, settings, samples: int):
    """A still view's request with the G-buffer's material and albedo at the direct light's
    resolution (every pixel one material: the box's walls differ only in colour here)."""
    pos, nrm, view_matrix, ok = pinhole_gbuffer(scene, settings)
    material = np.where(ok, 1.0, 0.0).astype(np.float32).reshape(pos.shape[:2])
    albedo = np.zeros(pos.shape, np.float32)
    albedo[ok.reshape(pos.shape[:2])] = (0.7, 0.7, 0.7, 1.0)
    return worker.ViewRequest(("k",), pos, nrm, pos, nrm, view_matrix, np.eye(4), material=material,
                              full_material=material, full_albedo=albedo, glossy_samples=samples, reflection_rays=2)


def test_a_still_view_takes_the_final_renders_glossy_light_and_an_edit_drops_it(worker):
    """Once a still view has a full-res direct pass and its pixel rays, the worker publishes the
    final render's glossy light at every pixel of the direct light's resolution
    (`glossy_image.frame_glossy`), made once per cache and lighting; a newer view arriving while
    it is made drops it between its steps."""
    from hybridgi_core import glossy_image  # noqa: PLC0415

    scene = _glossy_cornell()
    settings = CacheSettings(resolution=10, rays_per_cell=16, threads=2)
    request = _full_res_glossy_request(worker, scene, settings, samples=8)
    options = worker.WorkerOptions(direct_passes=2, solver_batches=1, first_batch_rays=8, pixel_rays=4,
                                   pixel_passes=1, glossy_passes=2)
    wk = worker.ViewportWorker(settings, options)
    try:
        wk.post_edit(worker.FullScene(scene))
        wk.post_view(request)
        assert wk.wait_idle(120)
        result = wk.latest().view
        state = wk._view_state
        assert state.fine_glossy is not None and state.fine_glossy_key is not None
        assert result.glossy.shape == request.full_albedo.shape and result.glossy_position is request.direct_position
        on = request.direct_position[..., 3] > 0.5
        glossy = np.asarray(result.glossy)
        assert (glossy[on, 3] == 1.0).all() and glossy[on, :3].mean() > 0 and np.isfinite(glossy).all()
        # Made once: the idle worker has no more glossy work over this cache.
        assert not wk._fine_glossy_due(state)
        # Its light is `frame_glossy`'s: the lamps' part and the reflections, from the fine
        # direct light's irradiance (another frame's samples: equal in the mean).
        level = state.fine_level()
        points, normals, pix = level.points
        again = glossy_image.frame_glossy(
            wk._session.system, points, normals, pix, on.shape, request.full_material.reshape(-1)[pix],
            request.full_albedo.reshape(-1, 4)[pix, :3], level.mean().reshape(-1, 4)[pix, :3], request.view,
            worker.camera_eye(request.view, request.proj), 12345, 8, 2)
        mine = glossy.reshape(-1, 4)[pix, :3]
        assert 0.9 < mine.sum() / again.radiance.sum() < 1.1
        # Texels of a material the system does not know (a G-buffer drawn after a material edit
        # the worker has not taken yet) reflect nothing instead of failing.
        unknown = np.full(pix.size, 99.0, np.float32)
        none = glossy_image.frame_glossy(
            wk._session.system, points, normals, pix, on.shape, unknown, request.full_albedo.reshape(-1, 4)[pix, :3],
            level.mean().reshape(-1, 4)[pix, :3], request.view, worker.camera_eye(request.view, request.proj), 1, 8, 2)
        assert not none.radiance.any()
        # Its first stop comes after the lamps' samples, before the reflection rays are traced.
        class Stop(Exception):
            pass

        def stop():
            raise Stop

        with mock.patch.object(glossy_image, "traced_reflection") as traced, pytest.raises(Stop):
            glossy_image.frame_glossy(
                wk._session.system, points, normals, pix, on.shape, request.full_material.reshape(-1)[pix],
                request.full_albedo.reshape(-1, 4)[pix, :3], level.mean().reshape(-1, 4)[pix, :3], request.view,
                worker.camera_eye(request.view, request.proj), 1, 8, 2, between=stop)
        assert not traced.called
        # A newer view waits: the next fine glossy pass stops between its steps.
        with wk._cond:  # the idle worker thread waits on it meanwhile
            state.fine_glossy, state.fine_glossy_key = None, None
            wk._view = dataclasses.replace(request, key=("other",))
            try:
                wk._fine_glossy(wk._session.system, state)
            finally:
                wk._view = request
        assert state.fine_glossy is None and "fine_glossy_dropped" in wk._steps
    finally:
        wk.close()


def test_pixel_rays_read_the_views_lamp_light_of_its_finest_lit_level(worker):
    """The pixel passes' hits that the camera sees read the view's own lamp light
    (`ViewState.screen_light`, as final renders' hits read theirs): none before a direct pass,
    the coarse level's after the first, the full-res level's once it has a pass."""
    view = sys.modules[worker.__name__.rsplit(".", 1)[0] + ".worker_view"]
    from hybridgi_core.visible import pixels_to_points  # noqa: PLC0415

    scene = procedural.cornell()
    settings = CacheSettings(resolution=10, rays_per_cell=8)
    w, h = 32, 24
    pos, nrm, view_matrix, ok = pinhole_gbuffer(scene, settings, w, h)
    full_pos, full_nrm, _, _ = pinhole_gbuffer(scene, settings, 2 * w, 2 * h)
    cam = procedural.describe("cornell").camera
    half_w = 0.5 * cam.sensor_width_mm / cam.lens_mm  # the pinhole's tan(horizontal half-angle)
    proj = np.array([[1 / half_w, 0, 0, 0], [0, w / (h * half_w), 0, 0], [0, 0, -1.0, -0.2], [0, 0, -1, 0]])
    request = worker.ViewRequest(("k",), pos, nrm, full_pos, full_nrm, view_matrix, proj)
    gi_points = pixels_to_points(pos, nrm)
    state = view.ViewState(request, 0, gi_points, np.zeros(0))
    assert state.screen_light() is None
    points, normals, _ = gi_points
    coarse_light = np.repeat(points[:, :1] + 10.0, 3, axis=1).astype(np.float32)
    state.coarse.add(coarse_light, 4)
    found, light = state.screen_light().lookup(points, normals)
    assert found.size > 0.95 * points.shape[0]
    np.testing.assert_allclose(light, coarse_light[found], rtol=1e-6)
    fine = state.fine_level()
    fine.add(np.full((fine.points[0].shape[0], 3), 5.0, np.float32), 16)
    found, light = state.screen_light().lookup(points, normals)
    assert found.size > 0.9 * points.shape[0]
    np.testing.assert_array_equal(light, 5.0)


def test_edits_and_views_that_arrive_while_a_pixel_pass_traces_stop_it_and_the_view_still_settles(worker):
    """Lamp edits and new views posted while a pixel pass traces on its thread (at random moments
    of it) drop the pass; the worker never fails or hangs, and the last view settles with its
    pixel passes, traced over the last lamps."""
    scene = procedural.cornell()
    settings = CacheSettings(resolution=10, rays_per_cell=16, threads=2)
    pos, nrm, view_matrix, _ = pinhole_gbuffer(scene, settings, 96, 72)
    options = worker.WorkerOptions(direct_passes=2, solver_batches=1, first_batch_rays=8, pixel_rays=64,
                                   pixel_passes=2)
    wk = worker.ViewportWorker(settings, options)
    rng = np.random.default_rng(7)
    dropped = 0
    try:
        wk.post_edit(worker.FullScene(scene))
        lamps = scene.lights
        for i in range(6):
            # A new request object each time: a new view for the worker (same camera).
            wk.post_view(worker.ViewRequest(("k", i), pos, nrm, pos, nrm, view_matrix, np.eye(4)))
            key = ("k", i)
            assert wk.wait(lambda p, key=key: p.error is not None or p.view is not None and p.view.key == key, 60)
            deadline = time.perf_counter() + 5.0
            while not wk._tracing() and time.perf_counter() < deadline:  # a pass under way
                time.sleep(0.002)
            dropped += wk._tracing()
            time.sleep(float(rng.uniform(0.0, 0.05)))
            lamps = [dataclasses.replace(lt, power=lt.power * float(rng.uniform(0.5, 1.5))) for lt in lamps]
            wk.post_edit(worker.SetShading(lights=lamps))
        assert wk.wait_idle(120)
        p = wk.latest()
    finally:
        wk.close()
    assert dropped >= 3  # the edits did arrive while passes traced
    assert p.error is None and p.view.key == ("k", 5)
    assert p.view.pixel_passes == 2 and p.view.gi_indirect is not None
    assert np.isfinite(p.view.gi_indirect).all()
    # The same view of the last lamps, lit by a worker that saw nothing else: the same light
    # (to the rays' noise; other frame numbers).
    final = dataclasses.replace(scene, lights=lamps)
    with still_view(worker, final, settings, options, pos, nrm, view_matrix) as fresh:
        q = fresh.latest()
    ours, theirs = p.view.gi_indirect[..., :3].sum(), q.view.gi_indirect[..., :3].sum()
    assert abs(ours / theirs - 1.0) < 0.03


def test_a_still_view_traces_each_subframes_light_at_its_light_edges(worker):
    """With the draw's subframe pattern in the request, a still view's result carries the lamps'
    light of every subframe at the pixels whose light or surface changes within them
    (`EdgeLight`), traced at what the subframe's ray through the pixel meets: within the pixel
    of the centre's point, about the centre light there on average; made again after a lamp
    edit; none without a pattern."""
    scene, settings, (pos, nrm), (full_pos, full_nrm), view_matrix, proj, half_w, offsets = cornell_view_with_pattern()
    options = worker.WorkerOptions(direct_passes=2, solver_batches=1, first_batch_rays=8, pixel_rays=0)
    wk = worker.ViewportWorker(settings, options)
    try:
        wk.post_edit(worker.FullScene(scene))
        wk.post_view(worker.ViewRequest(("k",), pos, nrm, full_pos, full_nrm, view_matrix, proj, aa_offsets=offsets))
        assert wk.wait_idle(120)
        result = wk.latest().view
        edges = result.edges
        assert edges is not None and result.direct.shape[:2] == (48, 64)
        m = edges.pix.size
        assert m > 20 and edges.light.shape == edges.point.shape == edges.normal.shape == (4, m, 3)
        np.testing.assert_array_equal(edges.offsets, offsets)
        assert np.isfinite(edges.light).all() and (edges.light >= 0).all()
        hit = np.linalg.norm(edges.normal, axis=2) > 0.5
        np.testing.assert_allclose(np.linalg.norm(edges.normal[hit], axis=1), 1.0, atol=1e-4)
        assert (edges.light[~hit] == 0).all()
        # Where the pixel's centre sees geometry its subframes' rays mostly meet it too (beside
        # the box's outer edges some pass by), near the centre's point (within the pixel but
        # where the ray meets another surface behind an edge).
        centre_points = full_pos.reshape(-1, 4)[edges.pix]
        on = centre_points[:, 3] > 0.5
        assert hit[:, on].mean() > 0.9 and not hit[:, ~on].all()
        depth = -(centre_points[:, :3] @ view_matrix[2, :3] + view_matrix[2, 3])
        pixel = 2.0 * half_w * depth / 64  # a pixel's width at the centre's depth
        step = (np.linalg.norm(edges.point - centre_points[None, :, :3], axis=2) / pixel[None, :])[hit & on[None, :]]
        assert np.median(step) < 1.0, np.median(step)
        centre = result.direct.reshape(-1, 4)[edges.pix, :3].sum()
        assert edges.light.mean(axis=0).sum() == pytest.approx(centre, rel=0.35)
        lamps = [dataclasses.replace(lt, power=2.0 * lt.power) for lt in scene.lights]
        wk.post_edit(worker.SetShading(lights=lamps))
        assert wk.wait_idle(120)
        relit = wk.latest().view.edges
        assert relit is not None and relit is not edges
        assert relit.light.sum() == pytest.approx(2.0 * edges.light.sum() * relit.pix.size / m, rel=0.3)
    finally:
        wk.close()
    with still_view(worker, scene, settings, options, pos, nrm, view_matrix, (full_pos, full_nrm)) as wk:
        assert wk.latest().view.passes == 2 and wk.latest().view.edges is None  # no pattern, no edges


def test_edge_light_leaves_translucent_pixels_to_the_resolve(worker):
    """A translucent surface's pixels take their lamps' light on the back too, which the
    full-res light has and the edge rays do not: the edge light leaves them out (the draw
    resolves the full-res light there), while the same material opaque has edge pixels."""
    scene, settings, (pos, nrm), (full_pos, full_nrm), view_matrix, proj, half_w, offsets = cornell_view_with_pattern()
    cam = procedural.describe("cornell").camera
    # The full-res material texels (index + 1, 0 = background), as the G-buffer's.
    m = cam.matrix()
    x = ((np.arange(64) + 0.5) / 64 * 2 - 1) * half_w
    y = ((np.arange(48) + 0.5) / 48 * 2 - 1) * half_w * 48 / 64
    xx, yy = np.meshgrid(x, y)
    d = np.stack([xx.ravel(), yy.ravel(), -np.ones(xx.size)], 1) @ m[:3, :3].T
    d = (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)
    with GISystem(scene, settings) as primary:
        prim = primary.tracer.intersect(np.repeat(m[None, :3, 3], d.shape[0], 0).astype(np.float32), d).prim
    texels = np.where(prim >= 0, scene.geometry.material_index[np.maximum(prim, 0)] + 1, 0).astype(np.float32)
    options = worker.WorkerOptions(direct_passes=1, solver_batches=1, first_batch_rays=8, pixel_rays=0)

    def edge_materials(snapshot) -> np.ndarray:
        wk = worker.ViewportWorker(settings, options)
        try:
            wk.post_edit(worker.FullScene(snapshot))
            wk.post_view(worker.ViewRequest(("k",), pos, nrm, full_pos, full_nrm, view_matrix, proj,
                                            direct_material=texels.reshape(48, 64), aa_offsets=offsets))
            assert wk.wait_idle(120)
            return texels[wk.latest().view.edges.pix]
        finally:
            wk.close()

    opaque = edge_materials(scene)
    walls = np.unique(opaque[opaque > 0], return_counts=True)
    leaf = walls[0][np.argmax(walls[1])]  # the material with the most edge pixels
    materials = list(scene.materials)
    materials[int(leaf) - 1] = dataclasses.replace(materials[int(leaf) - 1], translucent=[0.5, 0.5, 0.5])
    translucent = edge_materials(dataclasses.replace(scene, materials=materials))
    assert (translucent != leaf).all() and translucent.size > 0


def test_a_lamp_edit_shades_the_views_last_pass_again_before_tracing_new_rays(worker, monkeypatch):
    """After a lamp edit of a still view, the first pixel pass over the re-lit cache shades the
    rays of the view's last pass again (`PixelPass.start_reshade`: none traced again) and the
    passes after it trace directions of their own (numbers past every one used before the
    edit). The lamp's power doubled: the re-shaded pass is twice the pass whose rays it shades
    (the same hits; its light differs only by the shading's own samples) and far closer to that
    than the fresh pass after it, whose directions differ."""
    scene = procedural.cornell()
    settings = CacheSettings(resolution=10, rays_per_cell=16, threads=2)
    pos, nrm, view_matrix, ok = pinhole_gbuffer(scene, settings)
    events, images = [], []
    pass_type = worker._pixels.PixelPass
    start, reshade = pass_type.start, pass_type.start_reshade
    add = worker.ViewState.add_pixels

    def record_start(self, *args, **kwargs):
        events.append(("trace", self.index))
        return start(self, *args, **kwargs)

    def record_reshade(self, executor, system, traced, *args, **kwargs):
        events.append(("reshade", self.index, id(traced)))
        return reshade(self, executor, system, traced, *args, **kwargs)

    def record_add(self, indirect, direct, key, cache):
        images.append((indirect + direct).reshape(-1, 4)[ok.ravel(), :3].copy())
        kept.append(id(self.kept) if self.kept is not None else None)
        return add(self, indirect, direct, key, cache)

    kept = []
    monkeypatch.setattr(pass_type, "start", record_start)
    monkeypatch.setattr(pass_type, "start_reshade", record_reshade)
    monkeypatch.setattr(worker.ViewState, "add_pixels", record_add)
    options = worker.WorkerOptions(direct_passes=1, solver_batches=1, first_batch_rays=8, pixel_rays=8,
                                   pixel_passes=2)
    with still_view(worker, scene, settings, options, pos, nrm, view_matrix) as wk:
        assert [e[0] for e in events] == ["trace", "trace"]
        before = len(images)
        lamps = [dataclasses.replace(lt, power=2.0 * lt.power) for lt in scene.lights]
        wk.post_edit(worker.SetShading(lights=lamps))
        assert wk.wait_idle(120)
    assert [e[0] for e in events[2:]] == ["reshade", "trace"]
    assert events[2][2] == kept[before]  # the last pass's rays before the edit
    numbers = [e[1] for e in events]
    assert len(set(numbers)) == len(numbers)  # no pass draws another's directions
    last, again, fresh = images[before - 1], images[before], images[before + 1]
    assert last.mean() > 0.05  # lit: the comparisons are not of zeros
    l1 = lambda a, b: float(np.abs(a - b).sum() / np.abs(b).sum())  # noqa: E731
    assert l1(again, 2.0 * last) < 0.5 * l1(fresh, 2.0 * last)


def test_lamp_edits_that_arrive_while_a_view_reshades_its_rays_stop_it_and_the_view_still_settles(worker,
                                                                                                   monkeypatch):
    """A still view under a run of lamp edits, each posted while a pixel pass (traced or
    re-shaded) is under way: every edit's first pass re-shades the kept rays, a re-shade an edit
    cuts short leaves them kept for the next, and the view settles with its pixel passes over
    the last lamps, as lit as a worker that saw only those lamps."""
    scene = procedural.cornell()
    settings = CacheSettings(resolution=10, rays_per_cell=16, threads=2)
    pos, nrm, view_matrix, _ = pinhole_gbuffer(scene, settings, 96, 72)
    options = worker.WorkerOptions(direct_passes=2, solver_batches=1, first_batch_rays=8, pixel_rays=64,
                                   pixel_passes=2)
    reshades = []
    reshade = worker._pixels.PixelPass.start_reshade

    def record(self, executor, system, traced, *args, **kwargs):
        reshades.append(id(traced))
        return reshade(self, executor, system, traced, *args, **kwargs)

    monkeypatch.setattr(worker._pixels.PixelPass, "start_reshade", record)
    rng = np.random.default_rng(11)
    dropped = 0
    with still_view(worker, scene, settings, options, pos, nrm, view_matrix) as wk:
        lamps = scene.lights
        for _ in range(6):
            lamps = [dataclasses.replace(lt, power=lt.power * float(rng.uniform(0.5, 1.5))) for lt in lamps]
            wk.post_edit(worker.SetShading(lights=lamps))
            deadline = time.perf_counter() + 5.0
            while not wk._tracing() and time.perf_counter() < deadline:  # the edit's pass under way
                time.sleep(0.002)
            dropped += wk._tracing()
            time.sleep(float(rng.uniform(0.0, 0.03)))
        # The last edit's passes run to their end.
        lamps = [dataclasses.replace(lt, power=lt.power * 1.25) for lt in lamps]
        wk.post_edit(worker.SetShading(lights=lamps))
        assert wk.wait_idle(120)
        p = wk.latest()
    assert dropped >= 3 and len(reshades) >= 2  # the edits did arrive while passes ran
    assert p.error is None and p.view.pixel_passes == 2 and np.isfinite(p.view.gi_indirect).all()
    final = dataclasses.replace(scene, lights=lamps)
    with still_view(worker, final, settings, options, pos, nrm, view_matrix) as fresh:
        q = fresh.latest()
    ours, theirs = p.view.gi_indirect[..., :3].sum(), q.view.gi_indirect[..., :3].sum()
    assert abs(ours / theirs - 1.0) < 0.03


def test_a_colour_edit_keeps_the_view_and_its_lamp_light_and_shades_its_rays_again(worker, monkeypatch):
    """A diffuse colour's edit (`SceneChanges.colours_only`) of a still view is lit again as a
    lamp's is, and keeps the lamps' light too: no new view (its cells and mask stay), no lamp
    pass, the first pixel pass re-shades the kept rays over the re-solved cache; the view
    settles where a worker given the new colours from the start does, away from the old colours'.
    An emission's edit still starts the view over."""
    scene = procedural.cornell()
    settings = CacheSettings(resolution=10, rays_per_cell=16, threads=2)
    view = pinhole_gbuffer(scene, settings)
    pos, nrm, view_matrix, ok = view
    events = []
    for name in ("_begin_view", "_direct_pass"):
        original = getattr(worker.ViewportWorker, name)
        monkeypatch.setattr(worker.ViewportWorker, name,
                            lambda self, *a, _f=original, _n=name, **k: events.append(_n) or _f(self, *a, **k))
    pass_type = worker._pixels.PixelPass
    start, reshade = pass_type.start, pass_type.start_reshade
    monkeypatch.setattr(pass_type, "start", lambda self, *a, **k: events.append("trace") or start(self, *a, **k))
    monkeypatch.setattr(pass_type, "start_reshade",
                        lambda self, *a, **k: events.append("reshade") or reshade(self, *a, **k))
    options = dict(direct_passes=1, solver_batches=1, first_batch_rays=8, pixel_rays=16, pixel_passes=2)
    # The red wall turned blue: the other walls and the floor take blue light instead of red.
    blue = [dataclasses.replace(m, base_color=np.array([0.05, 0.08, 0.6], np.float32)) if m.name == "red" else m
            for m in scene.materials]
    gi = lambda published: published.view.gi_indirect.reshape(-1, 4)[ok.ravel(), :3].copy()  # noqa: E731
    with still_view(worker, scene, settings, worker.WorkerOptions(**options), pos, nrm, view_matrix) as wk:
        before_edit, old = len(events), gi(wk.latest())
        wk.post_edit(worker.SetShading(materials=blue))
        assert wk.wait_idle(120)
        recoloured = events[before_edit:]
        new = gi(wk.latest())
        glowing = [dataclasses.replace(m, emission=np.full(3, 2.0, np.float32)) if m.name == "green" else m
                   for m in blue]
        before_glow = len(events)
        wk.post_edit(worker.SetShading(materials=glowing))
        assert wk.wait_idle(120)
        glowed = events[before_glow:]
    assert "_begin_view" not in recoloured and "_direct_pass" not in recoloured, recoloured
    assert recoloured[0] == "reshade" and "trace" in recoloured
    assert "_begin_view" in glowed  # an emission is a light source: the view starts over
    with still_view(worker, dataclasses.replace(scene, materials=blue), settings, worker.WorkerOptions(**options),
                    pos, nrm, view_matrix) as fresh_wk:
        fresh = gi(fresh_wk.latest())
    l1 = lambda a, b: float(np.abs(a - b).sum() / np.abs(b).sum())  # noqa: E731
    assert l1(old, fresh) > 0.1  # the colour matters to the view's GI
    assert l1(new, fresh) < 0.25 * l1(old, fresh), (l1(new, fresh), l1(old, fresh))
    assert (new[:, 2] / new.sum(axis=1)).mean() > (old[:, 2] / old.sum(axis=1)).mean()  # bluer


def test_the_glossy_passes_count_by_their_samples(worker):
    """GlossyLevel: a new view's first glossy pass takes the coarse pass's samples (16 and more),
    the next ones one each: their mean weighs each pass by its samples, as the direct light's
    levels do (an even mean of a sixteen-sample pass and a one-sample pass doubled the noise of
    the first: bunny_npm's viewport image 0.0333 -> 0.0376 when the second pass came in)."""
    view = importlib.import_module(worker.__name__.rsplit(".", 1)[0] + ".worker_view")
    rng = np.random.default_rng(3)
    h, w = 4, 5
    pos = np.ones((h, w, 4), np.float32)
    pos[..., :3] = rng.random((h, w, 3))
    nrm = np.zeros((h, w, 4), np.float32)
    nrm[..., 2] = 1.0
    pix = np.arange(h * w)
    level = view.DirectLevel(pos, nrm, (pos.reshape(-1, 4)[:, :3], nrm.reshape(-1, 4)[:, :3], pix), samples=16)
    glossy = view.GlossyLevel(level, np.ones((h, w), np.float32), (0.0, 0.0, 5.0, 1.0),
                              types.SimpleNamespace(layers=[None], reflects=[True]))
    first, second = rng.random((h * w, 3), np.float32), rng.random((h * w, 3), np.float32)
    glossy.add(first, 16)
    glossy.add(second, 1)
    assert glossy.passes == 2
    np.testing.assert_allclose(glossy.image()[..., :3].reshape(-1, 3), (16 * first + second) / 17, rtol=1e-6)
    glossy.reset_lamps()
    glossy.add(second, 1)
    np.testing.assert_allclose(glossy.image()[..., :3].reshape(-1, 3), second, rtol=1e-6)

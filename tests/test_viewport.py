"""Live viewport GI: the HYBRIDGI engine's view_update / view_draw and the Solid-mode GI overlay,
driven the way Blender drives them but from the test (timers and draw handlers never run in the
bpy module): a fake engine and context with a viewport camera, an offscreen target, pixels read
back. Every wait on the worker has a timeout; nothing sleeps.

The Cornell box is built from `blend_scenes/build.py` into a temporary folder. Images are tiny
(96x72) and the cache coarse so the whole file stays within a few seconds on two shared cores.
"""

from __future__ import annotations

import contextlib
import importlib
import json
import os
import subprocess
import sys
import textwrap
import threading
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

pytestmark = pytest.mark.blender

REPO = Path(__file__).resolve().parents[1]
W, H = 96, 72
TIMEOUT_S = 60.0
LUMA = np.array([0.2126, 0.7152, 0.0722], np.float32)


# ----------------------------------------------------------------------------------------------
# fixtures: the scene, the add-on, a fake viewport
# ----------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def cornell_blend(tmp_path_factory):
    out = tmp_path_factory.mktemp("scenes")
    env = dict(os.environ)
    env.pop("BLENDER_USER_RESOURCES", None)
    run = subprocess.run([sys.executable, str(REPO / "blend_scenes" / "build.py"), "--only", "cornell", "--out", str(out)],
                         capture_output=True, text=True, timeout=120, env=env, cwd=REPO)
    assert run.returncode == 0, run.stderr[-2000:]
    return out / "cornell.blend"


@pytest.fixture
def addon(bpy_module, gpu_context, cornell_blend):
    """The Cornell box open with the add-on enabled; returns the add-on's modules."""
    bpy = bpy_module
    from hybridgi_cli import dev_install  # noqa: PLC0415

    bpy.ops.wm.open_mainfile(filepath=str(cornell_blend))
    package = dev_install.enable()
    scene = bpy.context.scene
    scene.render.engine = "HYBRIDGI"
    props = scene.hybridgi
    props.resolution = 10  # coarse cache and few rays: converges in about a second here
    props.rays_per_cell = 32
    modules = SimpleNamespace(
        bpy=bpy,
        viewport=importlib.import_module(f"{package.__name__}.viewport"),
        overlay=importlib.import_module(f"{package.__name__}.overlay"),
        worker=importlib.import_module(f"{package.__name__}.worker"),
    )
    yield modules
    modules.overlay.close_all()


class FakeEngine:
    """What view_update / view_draw use of a RenderEngine (one cannot be made from Python)."""

    def __init__(self):
        self.viewport = None
        self.redraws = 0
        self.status = ""

    def tag_redraw(self):
        self.redraws += 1

    def get_preview_pixel_size(self, scene):
        return 1

    def bind_display_space_shader(self, scene):
        pass  # Blender binds its IMAGE shader here; view_draw draws with that same shader

    def unbind_display_space_shader(self):
        pass

    def update_stats(self, stats, info):
        self.status = info


class View:
    """A fake 3D View: region, region_data with the scene camera's matrices, an offscreen target."""

    def __init__(self, m, ortho_scale=None):
        import gpu  # noqa: PLC0415

        self.m = m
        bpy = m.bpy
        scene = bpy.context.scene
        depsgraph = bpy.context.evaluated_depsgraph_get()
        cam = scene.camera.evaluated_get(depsgraph)
        window = cam.calc_matrix_camera(depsgraph, x=W, y=H)
        if ortho_scale is not None:
            window = _orthographic(ortho_scale)
        self.region_data = SimpleNamespace(
            view_matrix=cam.matrix_world.inverted(), window_matrix=window,
            is_perspective=ortho_scale is None, view_perspective="CAMERA" if ortho_scale is None else "ORTHO",
        )
        self.context = SimpleNamespace(
            region=SimpleNamespace(width=W, height=H), region_data=self.region_data, scene=scene,
            evaluated_depsgraph_get=bpy.context.evaluated_depsgraph_get,
        )
        self.engine = FakeEngine()
        self.offscreen = gpu.types.GPUOffScreen(W, H, format="RGBA16F")
        self._handler = None

    @property
    def session(self):
        return self.engine.viewport

    def update(self):
        self.m.viewport.view_update(self.engine, self.context, self.m.bpy.context.evaluated_depsgraph_get())

    def draw(self, fill=(0.0, 0.0, 0.0, 0.0), overlay=False) -> np.ndarray:
        """One redraw into the offscreen; (H, W, 4) float32 rows bottom-up."""
        import gpu  # noqa: PLC0415

        out = np.empty((H, W, 4), np.float32)
        with self.offscreen.bind():
            fb = gpu.state.active_framebuffer_get()
            fb.clear(color=fill)
            if overlay:
                self.m.overlay.draw_overlay(self.context)
            else:
                self.m.viewport.view_draw(self.engine, self.context, self.m.bpy.context.evaluated_depsgraph_get())
            fb.read_color(0, 0, W, H, 4, 0, "FLOAT", data=gpu.types.Buffer("FLOAT", out.size, out))
        return out

    def converge(self, session=None):
        session = session or self.session
        assert session.worker.wait_idle(TIMEOUT_S), "the worker did not converge in time"
        published = session.worker.latest()
        assert published.error is None, published.error
        assert published.stats.scene_gen >= session.last_edit_gen
        return published

    def follow_edits(self):
        """Call view_update after each depsgraph evaluation, as Blender does for a viewport."""
        def handler(scene, depsgraph):
            self.m.viewport.view_update(self.engine, self.context, depsgraph)

        self._handler = handler
        self.m.bpy.app.handlers.depsgraph_update_post.append(handler)

    def close(self):
        if self._handler is not None:
            self.m.bpy.app.handlers.depsgraph_update_post.remove(self._handler)
        if self.session is not None:
            self.m.viewport.free(self.engine)
        self.offscreen.free()


@pytest.fixture
def view(addon):
    v = View(addon)
    yield v
    v.close()


def _orthographic(half_height, near=0.1, far=100.0):
    from mathutils import Matrix  # noqa: PLC0415

    half_width = half_height * W / H
    return Matrix(((1 / half_width, 0, 0, 0), (0, 1 / half_height, 0, 0),
                   (0, 0, -2 / (far - near), -(far + near) / (far - near)), (0, 0, 0, 1)))


def _luma(img):
    return img[..., :3] @ LUMA


def _off_a_new_view(view, addon) -> float:
    """Relative L1 of luminance between the edited `view`, settled, and a new view of the scene
    as it is now, settled."""
    view.converge()
    live = _finish_redraws(view)
    fresh = View(addon)
    try:
        _converged_image(fresh)
        want = _finish_redraws(fresh)
    finally:
        fresh.close()
    return float(np.abs(_luma(live) - _luma(want)).mean() / _luma(want).mean())


def _converged_image(view):
    view.update()
    view.draw()  # posts the first view request
    view.converge()
    return view.draw()


# ----------------------------------------------------------------------------------------------
# the worker alone, with bpy blocked
# ----------------------------------------------------------------------------------------------
WORKER_WITHOUT_BPY = textwrap.dedent("""
    import importlib, json, sys, types
    import numpy as np
    for name in ("bpy", "gpu", "mathutils", "bmesh", "gpu_extras"):
        sys.modules[name] = None  # any import of these raises ImportError
    package = types.ModuleType("hybridgi_addon_probe")
    package.__path__ = [sys.argv[1]]  # the add-on folder, without running its __init__ (bpy)
    sys.modules[package.__name__] = package
    worker = importlib.import_module("hybridgi_addon_probe.worker")

    from blend_scenes import procedural
    from hybridgi_core.settings import CacheSettings
    from hybridgi_core.system import GISystem

    scene = procedural.cornell()
    settings = CacheSettings(resolution=8, rays_per_cell=16, threads=1)
    cam = procedural.describe("cornell").camera
    w, h = 32, 24
    m = cam.matrix()
    half_w = 0.5 * cam.sensor_width_mm / cam.lens_mm
    x = ((np.arange(w) + 0.5) / w * 2 - 1) * half_w
    y = ((np.arange(h) + 0.5) / h * 2 - 1) * half_w * h / w
    xx, yy = np.meshgrid(x, y)
    d = np.stack([xx.ravel(), yy.ravel(), -np.ones(xx.size)], 1) @ m[:3, :3].T
    d = (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)
    with GISystem(scene, settings) as primary:  # a pinhole G-buffer, as the GPU would read back
        hits = primary.tracer.intersect(np.repeat(m[None, :3, 3], d.shape[0], 0).astype(np.float32), d)
        ok = hits.prim >= 0
        surf = primary.surfaces.surface(hits.prim[ok], hits.u[ok], hits.v[ok], d[ok])
    pos = np.zeros((h * w, 4), np.float32)
    nrm = np.zeros((h * w, 4), np.float32)
    pos[ok, :3], pos[ok, 3], nrm[ok, :3] = surf.position, 1.0, surf.normal
    pos, nrm = pos.reshape(h, w, 4), nrm.reshape(h, w, 4)

    wk = worker.ViewportWorker(settings, worker.WorkerOptions(direct_passes=4))
    gen = wk.post_edit(worker.FullScene(scene))
    wk.post_view(worker.ViewRequest(("k",), pos, nrm, pos, nrm, np.linalg.inv(m), np.eye(4)))
    idle = wk.wait_idle(60)
    p = wk.latest()
    wk.close()
    k = settings.sh_coeffs
    texels = p.cache.sh_texels.reshape(-1, 4)[: p.cache.grid.count * 2 * k].reshape(-1, 2 * k, 4)
    valid = texels[:, k, 3]
    with GISystem(scene, settings) as final:  # the final render's warm-up of the same settings
        final.warm_up(16)
        both = (valid > 0.5) & final.cache.valid
        indirect_ratio = float(texels[both, k, :3].sum() / final.cache.sh_indirect[both, 0].sum())
    print(json.dumps({
        "idle": idle, "error": p.error, "scene_gen": p.stats.scene_gen, "gen": gen,
        "converged": p.stats.converged, "visible": p.stats.visible_cells,
        "direct_mean": float(p.view.direct[..., :3][ok.reshape(h, w)].mean()),
        "passes": p.view.passes, "has_mask": p.view.corner_mask is not None,
        "valid_cells": int(valid.sum()), "writeable": bool(p.cache.sh_texels.flags.writeable),
        "blocked": all(sys.modules.get(n) is None for n in ("bpy", "gpu", "mathutils")),
        "threads_alive": wk.alive, "indirect_ratio": indirect_ratio,
    }))
""")


def test_worker_runs_with_bpy_gpu_mathutils_blocked():
    """Structural guard: the worker module imports nothing of Blender's, and a whole worker
    session (sync, view light, visibility mask, cache updates) runs in a process without them."""
    env = dict(os.environ, PYTHONPATH=str(REPO))
    run = subprocess.run([sys.executable, "-c", WORKER_WITHOUT_BPY, str(REPO / "addon")], capture_output=True,
                         text=True, timeout=120, env=env, cwd=REPO)
    assert run.returncode == 0, run.stderr[-3000:]
    r = json.loads(run.stdout.strip().splitlines()[-1])
    assert r["blocked"] and r["idle"] and r["error"] is None
    assert r["scene_gen"] == r["gen"] == 1
    assert r["visible"] > 0 and r["converged"] == 1.0
    assert r["direct_mean"] > 0.5 and r["passes"] == 4 and r["has_mask"]  # the box is lit by its lamp
    assert r["valid_cells"] > 0 and not r["writeable"]  # published arrays are read-only copies
    assert not r["threads_alive"]
    # Converged means the final render's fixed point (the EMA updates it replaced stopped ~25% low).
    assert 0.95 < r["indirect_ratio"] < 1.05, r["indirect_ratio"]


# ----------------------------------------------------------------------------------------------
# the engine's viewport
# ----------------------------------------------------------------------------------------------
@pytest.mark.smoke
def test_viewport_frame_of_cornell_box_shows_colour_bleeding(view):
    img = _converged_image(view)
    assert np.isfinite(img).all()
    session = view.session
    albedo = session.gpu.pipeline.deferred.read("diffuse_color")
    geometry = session.gpu.pipeline.gbuffer.read("position")[..., 3] > 0.5
    assert geometry.mean() > 0.3 and _luma(img)[geometry].mean() > 0.05  # a lit box, not black
    assert np.all(img[..., 3] == 1.0)  # opaque: the film is not transparent
    # White surfaces (floor, ceiling, back wall, blocks) pick up the red wall's light on the left
    # and the green wall's on the right.
    white = geometry & (np.abs(albedo[..., 0] - albedo[..., 1]) < 0.02) & (albedo[..., 0] > 0.5)
    cols = np.arange(W)[None, :].repeat(H, 0)
    left, right = white & (cols < W * 0.4), white & (cols > W * 0.6)
    assert left.sum() > 50 and right.sum() > 50
    rg_left = img[left, 0].mean() / img[left, 1].mean()
    rg_right = img[right, 0].mean() / img[right, 1].mean()
    assert rg_left > 1.1 and rg_right < 0.93, (rg_left, rg_right)
    # Converged and drawn: the anti-aliasing subframes follow, one a redraw (`viewport_aa`), then
    # nothing more to redraw, and a redraw reuses the image.
    for _ in range(session.aa.total - 1):
        assert session.needs_redraw()
        img = view.draw()
        assert session.last_stats.subframe > 0
    assert not session.needs_redraw()
    again = view.draw()
    assert not session.last_stats.redrawn and np.array_equal(again, img)


def test_camera_move_keeps_previous_gi_without_a_black_frame(view):
    from mathutils import Matrix  # noqa: PLC0415

    before = _converged_image(view)
    session = view.session
    geometry_before = session.gpu.pipeline.gbuffer.read("position")[..., 3] > 0.5
    for step in range(3):
        # Orbit a little: the very next frame must show GI at once (the cache is world space,
        # the direct light is reprojected from the previous camera).
        view.region_data.view_matrix = (Matrix.Rotation(0.04, 4, "Y") @ Matrix.Translation((0.08, 0.02, 0.0))
                                        @ view.region_data.view_matrix)
        img = view.draw()
        stats = session.last_stats
        assert stats.redrawn and stats.posted_view and not stats.view_current
        geometry = session.gpu.pipeline.gbuffer.read("position")[..., 3] > 0.5
        luma = _luma(img)
        assert np.isfinite(img).all()
        assert luma[geometry].mean() > 0.6 * _luma(before)[geometry_before].mean(), step
        assert (luma[geometry] < 1e-3).mean() < 0.02, step  # no black patches
    view.converge()
    settled = view.draw()
    assert session.last_stats.view_current
    assert _luma(settled)[geometry].mean() > 0.05


def test_orthographic_view_draws(addon):
    v = View(addon, ortho_scale=1.4)
    try:
        img = _converged_image(v)
        geometry = v.session.gpu.pipeline.gbuffer.read("position")[..., 3] > 0.5
        assert geometry.mean() > 0.3 and np.isfinite(img).all()
        assert _luma(img)[geometry].mean() > 0.05
    finally:
        v.close()


def test_light_energy_doubling_brightens_the_view(view, addon):
    before = _converged_image(view)
    view.follow_edits()
    light = next(o for o in addon.bpy.data.objects if o.type == "LIGHT")
    energy = light.data.energy
    light.data.energy *= 2.0
    addon.bpy.context.view_layer.update()  # -> depsgraph_update_post -> view_update
    mirror = view.session.mirror
    assert mirror.snapshot.lights[0].power == pytest.approx(2.0 * energy, rel=1e-5)
    view.converge()
    after = view.draw()
    geometry = view.session.gpu.pipeline.gbuffer.read("position")[..., 3] > 0.5
    ratio = _luma(after)[geometry].mean() / _luma(before)[geometry].mean()
    assert 1.8 < ratio < 2.2, ratio  # direct and bounced light both scale with the lamp


def test_film_exposure_scales_the_view_as_it_scales_final_renders(view, addon):
    """Cycles' Film > Exposure: final renders scale their light passes by it (pipeline.film_exposure);
    the viewport showed the unscaled image."""
    before = _converged_image(view)
    scene = addon.bpy.context.scene
    scene.cycles.film_exposure = 2.0
    try:
        after = view.draw()
    finally:
        scene.cycles.film_exposure = 1.0
    geometry = view.session.gpu.pipeline.gbuffer.read("position")[..., 3] > 0.5
    ratio = _luma(after)[geometry].mean() / _luma(before)[geometry].mean()
    assert ratio == pytest.approx(2.0, rel=0.02)


def test_moving_an_object_resyncs_only_that_object(view, addon):
    _converged_image(view)
    view.follow_edits()
    session = view.session
    snapshot = session.mirror.snapshot
    block = addon.bpy.data.objects["short_block"]
    before_gen = session.mirror.geometry_gen
    block.location.x += 0.25
    addon.bpy.context.view_layer.update()
    # A transform update moves the block's vertices (no new snapshot of the whole scene) and the
    # G-buffer takes new positions only.
    assert session.mirror.snapshot is snapshot
    assert session.mirror.geometry_gen == before_gen + 1
    assert session.mirror.gpu_dirty == "positions"
    view.draw()
    view.converge()
    moved = view.draw()
    position = session.gpu.pipeline.gbuffer.read("position")
    xs = position[..., 0][position[..., 3] > 0.5]
    assert np.isfinite(moved).all() and xs.size
    # The worker traced the moved block: its snapshot holds the new vertex positions.
    names = [o.name for o in snapshot.objects]
    idx = names.index("short_block")
    g = snapshot.geometry
    verts = np.unique(g.triangles[g.object_index == idx])
    assert np.allclose(session.mirror.gpu_snapshot().geometry.positions[verts, 0],
                       g.positions[verts, 0] + 0.25, atol=1e-4)


def test_moving_an_object_after_two_objects_swapped_names_moves_that_object(view, addon):
    """Renames send no depsgraph update: after the blocks swapped names the view's mirror still
    knew each name as the other block, and a move of one displaced the other's vertices (the
    view 12% off a new one)."""
    bpy = addon.bpy
    _converged_image(view)
    view.follow_edits()
    tall, short = bpy.data.objects["tall_block"], bpy.data.objects["short_block"]
    tall.name, short.name = "swap", "tall_block"
    tall.name = "short_block"
    bpy.context.view_layer.update()
    view.draw()
    tall.location.y += 0.2  # the tall block, now named short_block
    bpy.context.view_layer.update()
    view.draw()
    error = _off_a_new_view(view, addon)
    assert error < 0.02, error


@pytest.mark.parametrize("flat", [(0.0, 1.0, 1.0), (0.0, 0.0, 0.0)])
def test_an_object_scaled_to_zero_and_back_shows_again(view, addon, flat):
    """An object scaled flat is synced with a singular matrix; the move back was computed
    relative to it: inverting it raised LinAlgError in view_update at every later move of the
    object (flattened on one axis), or the object had no triangles left to move and the move
    was dropped (scaled to 0): the view kept the flat object (20% off a new view)."""
    bpy = addon.bpy
    _converged_image(view)
    failures = []

    def handler(_scene, depsgraph):  # Blender prints a handler's exception and goes on
        try:
            addon.viewport.view_update(view.engine, view.context, depsgraph)
        except Exception as err:
            failures.append(err)

    bpy.app.handlers.depsgraph_update_post.append(handler)
    try:
        block = bpy.data.objects["short_block"]
        block.scale = flat
        bpy.context.view_layer.update()
        view.draw()
        view.converge()
        block.scale = (1.0, 1.0, 1.0)
        bpy.context.view_layer.update()
        view.draw()
    finally:
        bpy.app.handlers.depsgraph_update_post.remove(handler)
    assert not failures, failures
    error = _off_a_new_view(view, addon)
    assert error < 0.02, error


def test_deleting_an_object_while_the_worker_traces_is_safe(view, addon):
    from mathutils import Matrix  # noqa: PLC0415

    _converged_image(view)
    view.follow_edits()
    view.region_data.view_matrix = Matrix.Translation((0.1, 0.0, 0.0)) @ view.region_data.view_matrix
    view.draw()  # the worker starts lighting the new view
    assert not view.session.worker.idle
    addon.bpy.data.objects.remove(addon.bpy.data.objects["tall_block"])
    addon.bpy.context.view_layer.update()
    img = view.draw()  # no exception; the next frame draws
    assert np.isfinite(img).all()
    published = view.converge()
    assert published.error is None
    img = view.draw()
    assert np.isfinite(img).all() and _luma(img).mean() > 0.02
    assert "tall_block" not in [o.name for o in view.session.mirror.snapshot.objects]


# ----------------------------------------------------------------------------------------------
# the worker never touches Blender, checked at run time
# ----------------------------------------------------------------------------------------------
BLENDER_MODULES = ("bpy", "gpu", "mathutils", "bmesh", "gpu_extras", "bpy_extras", "addon_utils", "_bpy", "_bpy_types")
BPY_SIDE = (".viewport", ".viewport_mirror", ".viewport_stats", ".overlay", ".engine", ".sync", ".updates", ".ui",
            ".properties", ".pipeline", ".animation")


class BlenderAccessGuard:
    """A profile hook on every thread started while installed: records each Python call into a
    Blender module or a bpy-side add-on module, and each C call on a Blender object (RNA data,
    collections, mathutils values, gpu objects) or into a Blender module, made by a HybridGI
    worker thread (`hybridgi-*`). Bare attribute reads make no call: the structural test above
    covers those (the worker cannot even import bpy)."""

    def __init__(self):
        import bpy  # noqa: PLC0415
        import gpu  # noqa: PLC0415
        import mathutils  # noqa: PLC0415

        self.violations = []
        self.events = 0
        self.blender_types = (
            bpy.types.bpy_struct, bpy.types.bpy_prop_collection, bpy.types.bpy_prop_array, type(bpy.data),
            mathutils.Vector, mathutils.Matrix, mathutils.Quaternion, mathutils.Euler, mathutils.Color,
            gpu.types.GPUTexture, gpu.types.GPUFrameBuffer, gpu.types.GPUShader, gpu.types.GPUBatch,
            gpu.types.GPUOffScreen, gpu.types.Buffer,
        )

    def __call__(self, frame, event, arg):
        name = threading.current_thread().name
        if not name.startswith("hybridgi"):
            return
        self.events += 1
        if event == "call":
            module = frame.f_globals.get("__name__", "") or ""
            if module.split(".")[0] in BLENDER_MODULES or module.endswith(BPY_SIDE):
                self.violations.append((name, module, frame.f_code.co_name))
        elif event == "c_call":
            owner = getattr(arg, "__self__", None)
            module = getattr(arg, "__module__", None) or getattr(owner, "__name__", "") or ""
            if isinstance(owner, self.blender_types) or str(module).split(".")[0] in BLENDER_MODULES:
                self.violations.append((name, type(owner).__name__, getattr(arg, "__name__", "?")))


def test_worker_threads_never_touch_bpy(addon):
    guard = BlenderAccessGuard()
    threading.setprofile(guard)
    try:
        # The guard itself catches a thread that does touch Blender.
        probe = threading.Thread(target=lambda: (addon.bpy.data.objects.get("floor"),
                                                 addon.bpy.context.scene.name), name="hybridgi-probe")
        probe.start()
        probe.join()
        assert guard.violations, "the guard missed a bpy access"
        guard.violations.clear()
        v = View(addon)
        try:
            _converged_image(v)
            v.follow_edits()
            light = next(o for o in addon.bpy.data.objects if o.type == "LIGHT")
            light.data.energy *= 1.5
            addon.bpy.data.objects["short_block"].location.y += 0.1
            addon.bpy.context.view_layer.update()
            v.draw()
            v.converge()
            v.draw()
        finally:
            v.close()
    finally:
        threading.setprofile(None)
    assert guard.events > 1000  # the worker and its update pool ran under the guard
    assert not guard.violations, guard.violations[:5]


# ----------------------------------------------------------------------------------------------
# the Solid-mode overlay
# ----------------------------------------------------------------------------------------------
def test_gi_overlay_multiplies_indirect_light_into_the_view(view, addon):
    overlay = addon.overlay
    scene = addon.bpy.context.scene
    grey = (0.5, 0.5, 0.5, 1.0)
    assert not overlay.is_enabled(scene)
    untouched = view.draw(fill=grey, overlay=True)
    assert np.all(untouched[..., :3] == 0.5)  # off: nothing drawn
    overlay.set_enabled(scene, True)
    try:
        view.draw(fill=grey, overlay=True)
        session = overlay.session_for(scene)
        assert session.worker.wait_idle(TIMEOUT_S)
        img = view.draw(fill=grey, overlay=True)
        geometry = session.gpu.pipeline.gbuffer.read("position")[..., 3] > 0.5
        assert np.isfinite(img).all()
        assert np.all(img[~geometry, :3] == pytest.approx(0.5, abs=1e-3))  # background untouched
        changed = np.abs(img[geometry, :3] - 0.5).max(axis=1) > 0.01
        assert changed.mean() > 0.5  # the GI changed most pixels it was drawn over
        cols = np.arange(W)[None, :].repeat(H, 0)
        left, right = geometry & (cols < W * 0.4), geometry & (cols > W * 0.6)
        # Red bounce light on the left, green on the right, multiplied into the grey view.
        assert img[left, 0].mean() > img[left, 1].mean()
        assert img[right, 1].mean() > img[right, 0].mean()
    finally:
        overlay.set_enabled(scene, False)
    assert overlay.session_for(scene) is None


@pytest.mark.smoke
def test_cells_overlay_draws_a_point_per_valid_cell(view, addon):
    import gpu  # noqa: PLC0415

    scene = addon.bpy.context.scene
    _converged_image(view)
    frame = addon.viewport.drawn_cache(scene.name)
    assert frame is view.session.gpu.cache_frame
    centres, colours = addon.overlay.cell_points(frame)
    assert centres.shape[0] > 0 and colours.shape == (centres.shape[0], 4)
    assert np.isfinite(colours).all() and colours[:, :3].max() < 1.0  # Reinhard-mapped radiance
    assert not addon.overlay.draw_cells(scene)  # off by default
    scene.hybridgi.use_viewport_overlay = True
    out = np.empty((H, W, 4), np.float32)
    with view.offscreen.bind():
        fb = gpu.state.active_framebuffer_get()
        fb.clear(color=(0.0, 0.0, 0.0, 0.0))
        # POST_VIEW draws with the view's matrices on the stack.
        gpu.matrix.load_matrix(view.region_data.view_matrix)
        gpu.matrix.load_projection_matrix(view.region_data.window_matrix)
        assert addon.overlay.draw_cells(scene)
        fb.read_color(0, 0, W, H, 4, 0, "FLOAT", data=gpu.types.Buffer("FLOAT", out.size, out))
    assert (out[..., 3] > 0).sum() > 20  # points landed on the image


class PanelLayout:
    """Records what a panel draws (props must exist on their data)."""

    def __init__(self):
        self.props, self.labels, self.operators = [], [], []
        self.use_property_split = False
        self.use_property_decorate = True

    def column(self, **_kwargs):
        return self

    row = box = column

    def prop(self, data, name, **_kwargs):
        assert name in data.bl_rna.properties, f"{type(data).__name__} has no property {name!r}"
        self.props.append(name)

    def label(self, text="", **_kwargs):
        self.labels.append(text)

    def operator(self, idname, **_kwargs):
        self.operators.append(idname)


def test_sidebar_tab_shows_settings_and_live_stats(view, addon):
    import bpy  # noqa: PLC0415

    ui = sys.modules[addon.viewport.__name__.rsplit(".", 1)[0] + ".ui"]
    scene = bpy.context.scene
    context = SimpleNamespace(scene=scene, space_data=None)
    panels = {cls.__name__: cls for cls in ui.view3d_classes}
    assert all(cls.bl_space_type == "VIEW_3D" and cls.bl_region_type == "UI" and cls.bl_category == "HybridGI"
               for cls in panels.values())
    addon.viewport.LIVE_STATS.pop(scene.name, None)
    layout = PanelLayout()
    panels["HYBRIDGI_PT_view3d_stats"].draw(SimpleNamespace(layout=layout), context)
    assert layout.labels == ["No live view yet"]
    _converged_image(view)
    drawn = PanelLayout()
    for cls in panels.values():
        cls.draw(SimpleNamespace(layout=drawn), context)
    assert {"engine", "resolution", "rays_per_cell", "downsample", "debug_view", "use_viewport_overlay"} <= set(drawn.props)
    assert "hybridgi.gi_overlay" in drawn.operators or "use_gi_overlay" in drawn.props
    text = "\n".join(drawn.labels)
    assert "Converged: 100%" in text and "GI updates" in text and "Main thread" in text, text


@pytest.mark.smoke
def test_material_edit_reaches_the_image_without_a_full_resync(view, addon):
    bpy = addon.bpy
    before = _converged_image(view)
    albedo = view.session.gpu.pipeline.deferred.read("diffuse_color")
    green = (albedo[..., 1] > 2.0 * albedo[..., 0]) & (albedo[..., 1] > 0.2)  # the right wall
    assert green.sum() > 50
    view.follow_edits()
    geometry = view.session.mirror.snapshot.geometry
    material = bpy.data.materials["green"]
    material.node_tree.nodes["Principled BSDF"].inputs["Base Color"].default_value = (0.05, 0.05, 0.8, 1.0)
    bpy.context.view_layer.update()
    assert view.session.mirror.snapshot.geometry is geometry  # only the materials were read again
    view.draw()
    view.converge()
    after = view.draw()
    assert before[green, 1].mean() > 2.0 * before[green, 2].mean()
    assert after[green, 2].mean() > 2.0 * after[green, 1].mean()  # the wall is blue now


def test_cache_cells_view_matches_the_final_render_colours(view, addon):
    """The viewport's Cache Cells view shows `visible.cell_debug_colors` (the final render's), made
    by the worker at the GI pixels and upsampled: hash colours, full brightness once converged."""
    scene = addon.bpy.context.scene
    scene.hybridgi.debug_view = "CELLS"
    try:
        img = _converged_image(view)
    finally:
        scene.hybridgi.debug_view = "FINAL"
    result = view.session.worker.latest().view
    assert result.cells is not None and result.cells.shape[:2] == result.gi_position.shape[:2]
    geometry = view.session.gpu.pipeline.gbuffer.read("position")[..., 3] > 0.5
    rgb = img[geometry, :3]
    assert np.isfinite(rgb).all()
    # Converged cells are drawn at full brightness (0.35 + 0.65 x hash bytes per channel).
    assert np.median(rgb.min(axis=1)) > 0.3
    colours = np.unique(np.round(rgb * 255).astype(np.int32), axis=0)
    assert colours.shape[0] > 10  # many cells, each its own colour
    on_geometry = result.cells[..., 3] > 0.5
    assert (result.cells[on_geometry, :3] >= 0.35 - 1e-6).all()  # the worker's colours, all converged


def test_an_invalid_setting_is_shown_as_an_error_not_as_converged(view, addon):
    """A NaN typed into a setting: every redraw says what is wrong (never "converged"), the view
    keeps drawing, and fixing the value converges again."""
    scene = addon.bpy.context.scene
    view.update()
    view.draw()
    view.converge()
    old = scene.hybridgi.hysteresis
    scene.hybridgi.hysteresis = float("nan")
    try:
        view.update()  # raised on every update before
        img = view.draw()
        assert view.engine.status.startswith("Error:") and "hysteresis" in view.engine.status
        assert np.isfinite(img).all()
    finally:
        scene.hybridgi.hysteresis = old
    view.update()
    view.draw()
    view.converge()
    view.draw()
    assert not view.engine.status.startswith("Error") and "cells" in view.engine.status


def test_the_view_asks_for_redraws_right_after_an_edit(view, addon):
    """The draw right after an edit (or a new view's first draw) sees the worker's last record,
    which is idle until the worker takes the edit up: it must still ask Blender for another
    redraw, or the view shows the old image (status "converged") until the idle redraw timer's
    next check, up to `overlay.POLL_IDLE_S` later."""
    bpy = addon.bpy
    view.update()
    view.draw()
    assert view.session.needs_redraw()
    view.converge()
    _finish_redraws(view)
    view.follow_edits()
    light = next(o for o in bpy.data.objects if o.type == "LIGHT")
    for _ in range(3):
        light.data.energy *= 1.1
        bpy.context.view_layer.update()  # view_update: the edit is posted
        tagged = view.engine.redraws
        view.draw()
        assert view.engine.redraws > tagged, "the draw after an edit asked for no redraw"
        view.converge()
        _finish_redraws(view)


def test_a_slot_given_another_material_relights_the_view_as_a_new_view_lights_it(view, addon):
    """The short block's slot given the red material: a full sync whose positions are all the
    same, which the worker's diff took for no change (the cache kept the white block's light:
    7.7% off a new view of the edited scene)."""
    bpy = addon.bpy
    _converged_image(view)
    view.follow_edits()
    bpy.data.objects["short_block"].data.materials[0] = bpy.data.materials["red"]
    bpy.context.view_layer.update()
    view.draw()
    error = _off_a_new_view(view, addon)
    assert error < 0.02, error


def test_a_cache_setting_edited_without_a_depsgraph_update_reaches_the_view(view, addon):
    """A Python-defined setting set from a script tags no depsgraph update (no view_update
    follows: the bpy module's `view_layer.update()` calls no handler for it); the next redraw
    reads the settings, as Cycles re-reads its own in draw. The view kept the old cache: 441
    cells at Resolution 10 after Resolution 4 (62 cells in a new view)."""
    bpy = addon.bpy
    _converged_image(view)
    view.follow_edits()
    before = view.session.worker.latest().cache.grid.dims
    bpy.context.scene.hybridgi.resolution = 4
    bpy.context.view_layer.update()
    view.draw()
    published = view.converge()
    view.draw()
    assert published.cache.settings.resolution == 4
    assert published.cache.grid.dims != before
    assert not view.engine.status.startswith("Error")


def test_a_sky_world_bakes_in_the_background_then_lights_the_view(view, addon, tmp_path, monkeypatch):
    """The viewport never waits for a world bake: it draws with the world's uniform colour, the
    map bakes on a thread, and the next redraw reads the world again: its sun becomes a lamp."""
    import time  # noqa: PLC0415

    bpy = addon.bpy
    bake = sys.modules[addon.viewport.__name__.rsplit(".", 1)[0] + ".world_bake"]
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))  # no map from an earlier run
    scene = bpy.context.scene
    old = scene.world
    from hybridgi_cli import blender_compat  # noqa: PLC0415

    world = blender_compat.new_world(bpy, "sky")  # use_nodes only where needed (deprecated in 5.x)
    sky = world.node_tree.nodes.new("ShaderNodeTexSky")
    world.node_tree.links.new(sky.outputs["Color"], world.node_tree.nodes["Background"].inputs["Color"])
    scene.world = world
    try:
        t0 = time.perf_counter()
        view.update()
        view.draw()
        assert time.perf_counter() - t0 < 5.0  # no bake on the main thread
        suns = lambda: [lt for lt in view.session.mirror.snapshot.lights if lt.name == "sky/sun"]  # noqa: E731
        assert not suns() and bake.pending() and view.session.needs_redraw()
        deadline = time.perf_counter() + 120
        while bake.pending() and time.perf_counter() < deadline:
            time.sleep(0.2)
        assert not bake.pending()
        view.draw()  # reads the baked world
        assert len(suns()) == 1 and suns()[0].kind == "SUN"
        assert view.session.mirror.snapshot.world.sky_sh is not None
        view.converge()
        assert np.isfinite(view.draw()).all()
    finally:
        scene.world = old
        bpy.data.worlds.remove(world)


def test_the_view_shows_an_hdri_world_behind_the_scene(view, addon):
    """An Environment Texture world: the view's pixels without geometry show the map along their
    rays, as final renders and Cycles show it (`world_background`), not the uniform colour the
    light keeps of it; the still view's anti-aliasing subframes read it along their own rays."""
    from mathutils import Matrix  # noqa: PLC0415

    from hybridgi_cli import blender_compat  # noqa: PLC0415
    from hybridgi_core.raster.world_background import pixel_directions  # noqa: PLC0415

    bpy = addon.bpy
    scene = bpy.context.scene
    old = scene.world
    world = blender_compat.new_world(bpy, "hdri")
    env = world.node_tree.nodes.new("ShaderNodeTexEnvironment")
    env.image = bpy.data.images.load(os.path.join(bpy.utils.system_resource("DATAFILES"), "studiolights", "world",
                                                  "sunrise.exr"))
    world.node_tree.links.new(env.outputs["Color"], world.node_tree.nodes["Background"].inputs["Color"])
    scene.world = world
    # The camera turned half a turn about its own vertical: it looks away from the box, at the sky.
    cam = scene.camera.matrix_world
    eye = cam.translation.copy()
    turned = Matrix.Translation(eye) @ Matrix.Rotation(np.pi, 4, "Z") @ Matrix.Translation(-eye) @ cam
    view.region_data.view_matrix = turned.inverted()
    try:
        image = _converged_image(view)
        image = _finish_redraws(view)
        seen = view.session.mirror.snapshot.world.background_map
        assert seen is not None
        want = seen.radiance(pixel_directions(np.array(view.region_data.view_matrix),
                                              np.array(view.region_data.window_matrix), W, H)).reshape(H, W, 3)
        error = float(np.abs(image[..., :3] - want).sum() / np.abs(want).sum())
        uniform = float(np.abs(want.mean(axis=(0, 1)) - want).sum() / np.abs(want).sum())
        print(f"view background vs the map: {error:.4f} (their mean colour: {uniform:.4f})")
        assert uniform > 0.05  # the sky varies across the view: the check could fail
        assert error < 0.04, (error, uniform)
    finally:
        scene.world = old
        bpy.data.worlds.remove(world)


def test_a_procedural_material_bakes_in_the_background_then_textures_the_view(view, addon, tmp_path, monkeypatch):
    """As a world bake: the view draws the material's constant colour at once, Blender bakes the
    colour input on a thread, and the next redraw reads the materials again with the texture."""
    import time  # noqa: PLC0415

    from hybridgi_cli import blender_compat  # noqa: PLC0415

    bpy = addon.bpy
    bake = sys.modules[addon.viewport.__name__.rsplit(".", 1)[0] + ".material_bake"]
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))  # nothing baked by an earlier run
    material = blender_compat.new_material(bpy, "viewport_checker")
    checker = material.node_tree.nodes.new("ShaderNodeTexChecker")
    material.node_tree.links.new(checker.outputs["Color"], material.node_tree.nodes["Principled BSDF"].inputs["Base Color"])
    mesh = bpy.data.meshes.new("checker_quad")
    mesh.from_pydata([(-1, -1, 0.01), (1, -1, 0.01), (1, 1, 0.01), (-1, 1, 0.01)], [], [(0, 1, 2, 3)])
    mesh.materials.append(material)
    obj = bpy.data.objects.new("checker_quad", mesh)
    bpy.context.scene.collection.objects.link(obj)
    baked = lambda: [m for m in view.session.mirror.snapshot.materials if m.name == "viewport_checker"]  # noqa: E731
    try:
        t0 = time.perf_counter()
        view.update()
        view.draw()
        assert time.perf_counter() - t0 < 5.0  # no bake on the main thread
        assert baked() and baked()[0].texture is None and bake.pending() and view.session.needs_redraw()
        deadline = time.perf_counter() + 120
        while bake.pending() and time.perf_counter() < deadline:
            time.sleep(0.2)
        assert not bake.pending()
        view.draw()  # reads the baked material
        (got,) = baked()
        assert got.texture is not None and got.texture.std() > 0.1  # the checker's two colours
        view.converge()
        assert np.isfinite(view.draw()).all()
    finally:
        bpy.data.objects.remove(obj)
        bpy.data.meshes.remove(mesh)
        bpy.data.materials.remove(material)


# ----------------------------------------------------------------------------------------------
# the viewport shows what the final render shows (issue #10): the glossy layers' light the worker
# computes and the anti-aliasing subframes a still view accumulates, each against a final render
# of the same scene, camera and settings made here (`FramePipeline.render`, as the engine runs
# it). The Cornell box's materials are Principled BSDFs: every surface has a glossy layer.
# ----------------------------------------------------------------------------------------------
#: Redraws at most while a still view adds its anti-aliasing subframes.
MAX_REDRAWS = 64


def _finish_redraws(view) -> np.ndarray:
    """Redraw while the session asks for it (Blender's redraw loop); the last image."""
    img = view.draw()
    for _ in range(MAX_REDRAWS):
        if not view.session.needs_redraw():
            break
        img = view.draw()
    assert not view.session.needs_redraw(), "the view kept asking for redraws"
    return img


def _make_glossy(m, roughness: float = 0.35) -> None:
    """Give every Principled BSDF of the Cornell box (built without one) the default specular
    layer (Specular IOR Level 0.5, IOR 1.5) at `roughness`: highlights of the ceiling lamp."""
    for material in m.bpy.data.materials:
        nodes = material.node_tree.nodes if material.node_tree is not None else ()
        for node in nodes:
            if node.type == "BSDF_PRINCIPLED":
                node.inputs["Specular IOR Level"].default_value = 0.5
                node.inputs["Roughness"].default_value = roughness


def _final_render(m, view, subframes: int, reflection_rays: int | None = None, filter_size: float = 1.5,
                  lens=None) -> dict:
    """The final render's filtered passes for the viewport's camera and the scene it synced
    (with `reflection_rays` instead of the scene's setting when given; Cycles' Blackman-Harris
    pixel filter of `filter_size` px)."""
    from hybridgi_core.raster.frame import FramePipeline  # noqa: PLC0415
    from hybridgi_core.system import GISystem  # noqa: PLC0415

    viewport_stats = importlib.import_module(m.viewport.__name__.rsplit(".", 1)[0] + ".viewport_stats")
    scene = m.bpy.context.scene
    props = scene.hybridgi
    snapshot = view.session.mirror.snapshot
    camera = viewport_stats.ViewCamera.from_region_data(view.region_data)
    with GISystem(snapshot, props.cache_settings(scene)) as system:
        raster = props.raster_settings(cell_size=system.cache.grid.cell_size)
        if reflection_rays is not None:
            raster = raster.with_(reflection_rays=reflection_rays)
        pipe = FramePipeline(raster, subframes=subframes, filter_size=filter_size, lens=lens)
        try:
            pipe.resize(W, H)
            pipe.upload(snapshot)
            pipe.render(system, camera.view.astype(np.float32), camera.proj.astype(np.float32), frame=0,
                        warmup=props.warmup_iterations, world_color=snapshot.world.color)
            names = ("combined", "glossy_color", "glossy_direct", "glossy_indirect")
            passes = {name: pipe.film.read(name).copy() for name in names}
            passes["position"] = pipe.gbuffer.read("position").copy()
            return passes
        finally:
            pipe.free()


def _rel_l1(a, b, mask) -> float:
    return float(np.abs(a - b)[mask].sum() / max(np.abs(b)[mask].sum(), 1e-12))


def _blocks(img: np.ndarray, factor: int) -> np.ndarray:
    h, w = img.shape[0] // factor, img.shape[1] // factor
    return img[: h * factor, : w * factor].reshape(h, factor, w, factor, -1).mean(axis=(1, 3))


def test_settled_view_has_the_final_renders_glossy_light(view, addon):
    """Once a still view has its pixel rays, the worker computes the final render's glossy light
    at every pixel (`glossy_image.frame_glossy`: adaptive lamp samples, reflection rays for the
    lobes sharp enough, the filters): it agrees with a final render's Glossy Color x (Glossy
    Direct + Indirect) of the same camera, reflection rays included, and the settled,
    anti-aliased Combined is within a few % of the final render's."""
    _make_glossy(addon)
    _converged_image(view)
    shown = _finish_redraws(view)
    result = view.session.worker.latest().view
    assert result.glossy is not None and result.glossy.shape[:2] == (H, W)  # every pixel's, not the GI pixels'
    samples = addon.bpy.context.scene.hybridgi.pixel_samples
    final = _final_render(addon, view, subframes=samples)
    glossy_final = final["glossy_color"] * (final["glossy_direct"] + final["glossy_indirect"])
    mine = np.asarray(result.glossy)[..., :3]
    on = (np.asarray(result.glossy_position)[..., 3] > 0.5) & (final["position"][..., 3] > 0.99)
    assert on.mean() > 0.3
    share = glossy_final[on].sum() / final["combined"][..., :3][on].sum()
    assert share > 0.03, share  # the glossy light is a visible part of the image
    # Measured 0.067 per pixel (the lamps' and rays' samples differ; the final render's passes
    # are filtered over its subframes, the worker's are the pixel centres') and a mean ratio of 1.01.
    error = _rel_l1(mine, glossy_final, on)
    assert error < 0.15, error
    assert 0.95 < mine[on].sum() / glossy_final[on].sum() < 1.05
    # The reflection rays are in it (roughness 0.35 < `reflection.TRACE_ROUGHNESS`): the final
    # render without them is farther off.
    without_rays = _final_render(addon, view, subframes=samples, reflection_rays=0)
    glossy_plain = without_rays["glossy_color"] * (without_rays["glossy_direct"] + without_rays["glossy_indirect"])
    assert error < 0.5 * _rel_l1(glossy_plain, glossy_final, on)  # measured 0.067 against 0.35
    geometry = final["position"][..., 3] > 0.5
    # Settled viewport vs final render, Combined: measured 0.028 (0.071 with the GI pixels' glossy
    # light without reflection rays, the viewport's own before the final render's).
    combined = _rel_l1(shown[..., :3], final["combined"][..., :3], geometry)
    assert combined < 0.05, combined


def _upsampled(img: np.ndarray, factor: int) -> np.ndarray:
    return np.repeat(np.repeat(img, factor, axis=0), factor, axis=1)[:H, :W]


def test_still_view_antialiases_towards_the_final_render_and_restarts_on_a_camera_move(view, addon):
    """Redraws of a still, converged view add jittered subframes (the final render's pattern)
    until the sum is complete; edges then match the final render's anti-aliased edges better than
    the pixel-centre image does. A camera move starts over from the centre image."""
    centre = _converged_image(view)
    session = view.session
    assert session.last_stats.subframe == 0 and session.aa.drawn == 1
    assert session.needs_redraw()  # subframes to add
    settled = _finish_redraws(view)
    assert session.aa.drawn == session.aa.total == addon.bpy.context.scene.hybridgi.pixel_samples + 1
    # The worker traced each subframe's own light where a pixel's light or surface changes within
    # it (`worker.EdgeLight`), for this pattern.
    edges = session.worker.latest().view.edges
    assert edges is not None and edges.pix.size > 0
    np.testing.assert_allclose(edges.offsets, session.aa.offsets, atol=1e-6)
    final = _final_render(addon, view, subframes=addon.bpy.context.scene.hybridgi.pixel_samples)
    combined = final["combined"][..., :3]
    # Where the subframes changed the image (edges: silhouettes, creases, shadow boundaries).
    luma_c, luma_s = _luma(centre), _luma(settled)
    edge = np.abs(luma_s - luma_c) > 0.1 * np.maximum(luma_c, 0.02)
    assert edge.sum() > 30, edge.sum()
    err_centre = _rel_l1(centre[..., :3], combined, edge)
    err_settled = _rel_l1(settled[..., :3], combined, edge)
    whole = np.ones(edge.shape, bool)
    all_centre, all_settled = _rel_l1(centre[..., :3], combined, whole), _rel_l1(settled[..., :3], combined, whole)
    # Measured at the edge pixels 0.344 -> 0.050, the whole image 0.054 -> 0.020 (with the
    # subframes shaded from the pixel centres' light alone: 0.354 -> 0.065 and 0.055 -> 0.027).
    assert err_settled < 0.17 * err_centre, (err_settled, err_centre)
    assert all_settled < 0.43 * all_centre, (all_settled, all_centre)
    # A camera move (the view turns slightly): the sum starts over at the pixel centre.
    from mathutils import Matrix  # noqa: PLC0415

    view.region_data.view_matrix = Matrix.Rotation(0.02, 4, "Y") @ view.region_data.view_matrix
    view.draw()
    assert session.last_stats.redrawn and session.last_stats.subframe == 0 and session.aa.drawn == 1


def test_a_view_through_a_camera_with_depth_of_field_settles_on_the_final_renders_blur(view, addon):
    """Looking through the scene camera with depth of field, the still view's subframes each take
    a lens point too (`viewport_aa.Accumulation.next_camera`), as final renders' do: the settled
    image is the final render's blurred one, far from the pinhole image it starts from."""
    scene = addon.bpy.context.scene
    dof = scene.camera.data.dof
    dof.use_dof, dof.aperture_fstop, dof.focus_distance = True, 0.05, 2.0
    centre = _converged_image(view)
    session = view.session
    assert session.aa.lens is not None and session.aa.total >= 17  # at least lens.MIN_SUBFRAMES
    settled = _finish_redraws(view)
    pipeline = importlib.import_module(addon.viewport.__name__.rsplit(".", 1)[0] + ".pipeline")
    lens = pipeline.camera_lens(addon.bpy.context.evaluated_depsgraph_get(), scene)
    final = _final_render(addon, view, subframes=scene.hybridgi.pixel_samples, lens=lens)
    combined = final["combined"][..., :3]
    whole = np.ones(combined.shape[:2], bool)
    err_centre, err_settled = _rel_l1(centre[..., :3], combined, whole), _rel_l1(settled[..., :3], combined, whole)
    print(err_centre, err_settled)
    assert err_settled < 0.5 * err_centre, (err_settled, err_centre)


def test_a_shadow_catcher_in_the_view_is_named_as_a_final_render_feature(addon, caplog):
    """Final renders compose a shadow catcher (`catcher.py`); the viewport draws the plain
    surface, and says so once per sync rather than silently."""
    import logging  # noqa: PLC0415

    bpy = addon.bpy
    floor = next(o for o in bpy.context.scene.objects if o.type == "MESH")
    floor.is_shadow_catcher = True
    v = View(addon)
    try:
        with caplog.at_level(logging.WARNING):
            v.update()
        notes = [r.getMessage() for r in caplog.records if "shadow catcher" in r.getMessage()]
        assert len(notes) == 1 and floor.name in notes[0] and "final renders only" in notes[0], notes
    finally:
        v.close()
        floor.is_shadow_catcher = False


def test_a_view_of_one_sample_per_pixel_is_filtered_as_its_final_render(view, addon):
    """With one pixel sample the view shows its pixel-centre image through Cycles' pixel filter
    over the neighbours, as a final render of one sample writes it (`subpixel.reconstruction_taps`,
    the present pass's taps): nearer that render than the same render unfiltered, at the edges
    (the box's silhouettes and creases) where the filter mixes two surfaces."""
    addon.bpy.context.scene.hybridgi.pixel_samples = 1
    _converged_image(view)
    shown = _finish_redraws(view)
    assert view.session.aa.offsets.shape[0] == 0  # no subframes: the centre image alone
    filtered = _final_render(addon, view, subframes=1)["combined"][..., :3]
    bare = _final_render(addon, view, subframes=1, filter_size=0.01)["combined"][..., :3]
    edge = np.abs(_luma(filtered) - _luma(bare)) > 0.05 * np.maximum(_luma(bare), 0.02)
    assert edge.sum() > 30, edge.sum()
    near, far = _rel_l1(shown[..., :3], filtered, edge), _rel_l1(shown[..., :3], bare, edge)
    # Measured on 917 edge pixels: 0.019 against 0.161 (the view unfiltered: 0.155 against 0.023).
    assert near < 0.4 * far, (near, far)


@contextlib.contextmanager
def _resolve_held(view, addon, monkeypatch):
    """Post the view and hold the worker at its own resolve of the first pixel pass (its rays in,
    published for the draw, `gi_pending`) for the block's length."""
    pixels = addon.worker._pixels
    full_res = pixels.full_res
    entered, release = threading.Event(), threading.Event()

    def held(*args, **kwargs):
        entered.set()
        release.wait(TIMEOUT_S)
        return full_res(*args, **kwargs)

    monkeypatch.setattr(pixels, "full_res", held)
    view.update()
    view.draw()  # posts the view
    try:
        assert entered.wait(TIMEOUT_S), "no pixel pass reached the worker's resolve"
        yield
    finally:
        release.set()


def test_the_draw_resolves_a_pixel_pass_the_worker_has_not_resolved_yet(view, addon, monkeypatch):
    """While the worker resolves a still view's first pixel pass (filter, interpolation and detail
    pixels in numpy: 0.3-0.4 s at 640x360), the draw already shows the pass's light: it resolves
    the published rays (`ViewResult.gi_pending`) with the GPU's filter and upsample passes, as
    `pixel_gather.full_res_preview` does in numpy, and the image is then near the settled one."""
    from hybridgi_core import pixel_gather  # noqa: PLC0415

    with _resolve_held(view, addon, monkeypatch):
        result = view.session.worker.latest().view
        pending = result.gi_pending
        assert pending is not None and result.gi_indirect is None
        early = view.draw()
        gpu_state = view.session.gpu
        assert gpu_state.pixel_serial == ("pending", pending.serial)
        shown = np.array(gpu_state.pixel_tx[0].read().to_list(), np.float32).reshape(-1, 4)
    (h, w), (points, normals, pix) = pending.full_shape, pending.full
    indirect, _ = pixel_gather.full_res_preview(pending.gi, pending.position_lo, pending.pix, pending.points,
                                                pending.normals, pending.view, points, normals, pix, (w, h),
                                                pending.passes, pending.plane_sigma, pending.normal_power)
    ref = indirect.reshape(-1, 4)[pix]
    assert ref[:, :3].mean() > 0.02  # lit: the comparison is not of zeros
    np.testing.assert_allclose(shown[pix], ref, rtol=2e-3, atol=2e-4)
    settled = _converged_image(view)
    geometry = result.position[..., 3] > 0 if result.position.shape[:2] == (H, W) else np.ones((H, W), bool)
    assert _rel_l1(early[..., :3], settled[..., :3], geometry) < 0.05


def test_a_glossy_view_shows_the_final_renders_glossy_light_before_the_worker_resolves_its_rays(
        view, addon, monkeypatch):
    """A glossy view's first pixel pass: once its rays are in (the draw shows them, `gi_pending`)
    and its first full-res direct pass is done, the final render's glossy light comes next, before
    the worker's own resolve of those rays (0.3-0.4 s of numpy at 640x360 that changed the image
    far less: bunny_npm 0.0333 -> 0.0335, the glossy light then 0.0237)."""
    _make_glossy(addon)
    with _resolve_held(view, addon, monkeypatch):
        result = view.session.worker.latest().view
        assert result.gi_pending is not None and result.gi_indirect is None  # not resolved yet
        assert result.glossy is not None and result.glossy.shape[:2] == (H, W)  # the final render's, every pixel


def test_a_lamp_edit_updates_the_glossy_light_at_once(view, addon):
    """The lamp-edit fast path relights the glossy layers too: the first publication after the
    edit already has the lamps' glossy light of the new lamp at the GI pixels (one pass, the
    cache's part still the old one), and the converged view's glossy light (the final render's,
    at every pixel) scales with the lamp."""
    _make_glossy(addon)
    _converged_image(view)
    session = view.session
    settled = np.asarray(session.worker.latest().view.glossy)
    assert settled.shape[:2] == (H, W)  # the final render's glossy light
    state = session.worker._view_state.glossy  # the idle worker's (nothing writes it now)
    before = float(state.image()[..., :3].sum())  # the GI pixels' running glossy light
    lamps = float(state.lamp_mean().sum())
    assert lamps > 0.05 * before, (lamps, before)  # the lamp's highlights are part of it
    view.follow_edits()
    light = next(o for o in addon.bpy.data.objects if o.type == "LIGHT")
    light.data.energy *= 2.0
    addon.bpy.context.view_layer.update()  # -> view_update -> the worker's lamp edit
    gen = session.last_edit_gen
    assert session.worker.wait(lambda p: p.stats.scene_gen >= gen and p.view is not None
                               and 1 <= p.view.glossy_passes < 16, 60.0)
    first = session.worker.latest().view
    assert first.glossy is not None and first.glossy.shape == state.image().shape
    # The lamps' part doubled at once (one noisy pass), the cache's part not yet: +lamps.
    gain = float(np.asarray(first.glossy)[..., :3].sum() - before)
    assert 0.6 * lamps < gain < 1.4 * lamps, (gain, lamps)
    view.converge()
    after = np.asarray(session.worker.latest().view.glossy)
    assert after.shape[:2] == (H, W)
    ratio = after[..., :3].sum() / settled[..., :3].sum()
    assert 1.8 < ratio < 2.2, ratio  # the single lamp lights everything

"""Animation: final renders in both animation modes, localized cache updates, and the handlers that
feed live sessions named cache events.

Pixels come from the real engine: headless CLI runs (a subprocess each) for whole frame ranges,
and in-process renders (`bpy.ops.render.render`) where a test edits the scene between frames.
Small on purpose (96x54, 4 warm-up updates, a 16-cell grid where the scene allows it).
"""

from __future__ import annotations

import importlib
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from blend_scenes import procedural
from hybridgi_cli import blender_compat, exr

pytestmark = pytest.mark.blender

REPO = Path(__file__).resolve().parents[1]
SCENES = blender_compat.scenes_dir()  # this Blender's own build of the bundled scenes
ANIMATED = SCENES / "animated.blend"
CORNELL = SCENES / "cornell.blend"
W, H = 96, 54
# One sample per pixel: the bounce metric's 0.8 m around the ball takes in its silhouette, whose
# frame-to-frame flicker made up most of that region's change at 96x54 (frames 11-12: 0.0123 on
# the 21 floor pixels next to the ball vs 0.0021 inside; the pixel filter halves the edge part,
# and the near / far ratio of that pair drops to 1.36). The test is about the cache, not edges.
#: One unfiltered sample per pixel (a filter width of 0.01 px): the metrics below mask floor pixels
#: by their Normal and Diffuse Color, which Cycles' pixel filter mixes with the ball's next to it
#: (`subpixel.reconstruction_taps`), the pixels where the bounce changes most.
FAST = ("--res", f"{W}x{H}", "--set", "warmup_iterations=4", "--set", "pixel_samples=1",
        "--set", "cycles.filter_width=0.01")


@pytest.fixture(scope="module", autouse=True)
def bundled_scenes():
    """The bundled .blend files are build outputs (not in git): build the missing ones."""
    for blend in (ANIMATED, CORNELL):
        if not blend.exists():
            subprocess.run([sys.executable, str(REPO / "blend_scenes" / "build.py"), "--only", blend.stem, "--out", str(SCENES)],
                           check=True, capture_output=True, timeout=300)


# --- helpers -------------------------------------------------------------------------------------


def hybridgi(*args: str) -> list[dict]:
    """Run `hybridgi render ...`; returns its JSON lines (fails the test on a non-zero exit)."""
    script = Path(sys.executable).with_name("hybridgi")
    command = [str(script)] if script.exists() else [sys.executable, "-m", "hybridgi_cli.main"]
    env = dict(os.environ)
    env.pop("BLENDER_USER_RESOURCES", None)  # the command makes (and removes) its own
    run = subprocess.run([*command, "render", *args], capture_output=True, text=True, timeout=240, env=env, cwd=REPO)
    assert run.returncode == 0, run.stderr[-3000:]
    return [json.loads(line) for line in run.stdout.splitlines()]


def passes(path) -> dict[str, np.ndarray]:
    """{pass name: (h, w, c) float32} of a CLI EXR, row 0 at the top."""
    channels = exr.read_channels(path)
    out: dict[str, list] = {}
    for key in sorted(channels):
        _layer, name, chan = key.split(".")
        out.setdefault(name, []).append((chan, channels[key]))
    order = {c: i for i, c in enumerate("RGBAXYZ")}
    return {name: np.stack([a for _c, a in sorted(chans, key=lambda t: order.get(t[0], 9))], -1)
            for name, chans in out.items()}


def rel_l1(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.abs(a - b).sum() / max(np.abs(b).sum(), 1e-12))


def blur3(a: np.ndarray) -> np.ndarray:
    p = np.pad(a, 1, mode="edge")
    return sum(p[i : i + a.shape[0], j : j + a.shape[1]] for i in range(3) for j in range(3)) / 9.0


def floor_points(width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Where each pixel's camera ray meets the floor (z = 0) of the animated scene: (h, w, 2) x, y
    and (h, w) bool in front of the camera. Analytic, from procedural.py's camera."""
    cam = procedural.camera("animated")
    m = cam.matrix()
    f = cam.lens_mm / cam.sensor_width_mm * width  # sensor fit HORIZONTAL
    yy, xx = np.mgrid[0:height, 0:width] + 0.5
    d = np.stack([(xx - width / 2) / f, -(yy - height / 2) / f, -np.ones_like(xx)], -1) @ m[:3, :3].T
    t = -m[2, 3] / d[..., 2]
    return m[:2, 3] + t[..., None] * d[..., :2], t > 0


# --- CLI: whole frame ranges ---------------------------------------------------------------------


def test_independent_frame_renders_the_same_whatever_came_before(tmp_path):
    alone = hybridgi(str(ANIMATED), "--out", str(tmp_path / "alone"), "--frames", "5", *FAST)
    after = hybridgi(str(ANIMATED), "--out", str(tmp_path / "after"), "--frames", "4-5", *FAST)
    assert alone[0]["animation_mode"] == "INDEPENDENT"
    a, b = exr.read_channels(alone[0]["exr"]), exr.read_channels(after[1]["exr"])
    assert sorted(a) == sorted(b)
    for key in a:
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)


@pytest.fixture(scope="module")
def ball_frames(tmp_path_factory):
    """Frames 10-16 of the animated scene (the ball falls onto the floor, squashes, rises again)
    in both modes: {mode: [(frame, record), ...]}."""
    out = tmp_path_factory.mktemp("ball")
    runs = {}
    for mode in ("INDEPENDENT", "INCREMENTAL"):
        records = hybridgi(str(ANIMATED), "--out", str(out / mode), "--frames", "10-16", *FAST,
                           "--set", f"animation_mode={mode}")
        runs[mode] = [(r["frame"], r) for r in records]
    return runs


def _floor_maps(record, frame):
    p = passes(record["exr"])
    xy, ahead = floor_points(W, H)
    ball = procedural.ball_transform(frame)
    bunny = procedural.bunny_transform(frame)
    # Floor pixels: an upward normal and the floor's grey albedo (the ball's top is orange).
    floor = (p["Normal"][..., 2] > 0.9) & (p["Diffuse Color"][..., 1] > 0.5) & ahead
    to_ball = np.linalg.norm(xy - np.asarray(ball.location[:2]), axis=-1)
    to_bunny = np.linalg.norm(xy - np.asarray(bunny.location[:2]), axis=-1)
    return p["Diffuse Indirect"], floor, to_ball, to_bunny


@pytest.mark.parametrize("mode", ["INDEPENDENT", "INCREMENTAL"])
def test_bounce_light_follows_the_ball(ball_frames, mode):
    """Metric, per frame f of 10-16, on floor pixels of Diffuse Indirect (irradiance / pi):

    1. where: the floor within 0.5 m of the ball's analytic floor contact point is redder on
       average (3x3-blurred chromaticity R / (R + G + B); only the ball is orange, the floor is
       grey, the lamp warm white, a wall blue) than 99% of the floor more than 1.5 m from the ball
       and 1.2 m from the bunny (the floor is 6 m x 6 m). A mean against a percentile, not the
       single reddest pixel: at 96x54 one noisy far pixel could outrank the whole contact
       (Cycles at 256 spp, frame 13: 0.39 near against 0.31; HybridGI 0.32 against 0.31);
    2. what changes: the mean 3x3-blurred |L_f - L_f-1| (L = mean of R, G, B) over floor pixels
       within 0.8 m of the ball is more than the mean over floor pixels more than 1.5 m from the
       ball and 1.2 m from the bunny at every frame, and at least 1.5x over the frames (the mean
       of the ratios): frame to frame, the bounce changes where the ball moves. Not 1.5x at each
       frame: between frames 10 and 11 the falling ball's bounce moves little, and the ratio was
       2.0 only while the pixel rays' noise near the contact added to it (rays of neighbouring
       pixels that stratify together, `tiled_nets`: near 0.0061 -> 0.0033, far 0.0030 -> 0.0028,
       the later frames 2.0-4.3 as before).
    """
    prev = None
    ratios = []
    for frame, record in ball_frames[mode]:
        indirect, floor, to_ball, to_bunny = _floor_maps(record, frame)
        red = blur3(indirect[..., 0] / np.maximum(indirect.sum(-1), 1e-6))
        far = floor & (to_ball > 1.5) & (to_bunny > 1.2)
        contact = red[floor & (to_ball < 0.5)].mean()
        elsewhere = np.percentile(red[far], 99)
        assert contact > elsewhere, f"frame {frame}: floor redness at the ball {contact:.3f} <= 99th percentile far from it {elsewhere:.3f}"
        lum = indirect.mean(-1)
        if prev is not None:
            change = blur3(np.abs(lum - prev))
            near = floor & (to_ball < 0.8)
            ratio = change[near].mean() / change[far].mean()
            assert ratio > 1.0, f"frames {frame - 1}-{frame}: change near the ball / far = {ratio:.2f}"
            ratios.append(ratio)
        prev = lum
    assert np.mean(ratios) > 1.5, f"change near the ball / far, frames 10-16: {np.round(ratios, 2).tolist()}"


def test_incremental_frames_after_the_first_skip_the_warm_up(ball_frames):
    independent = dict(ball_frames["INDEPENDENT"])
    records = ball_frames["INCREMENTAL"]
    first = records[0][1]
    assert first["job_frames"] == 1 and "warmup" in first["steps_ms"]
    for frame, record in records[1:]:
        assert record["job_frames"] == frame - 9
        assert "warmup" not in record["steps_ms"] and "update" in record["steps_ms"]
        assert set(record["moved"]) == {"ball", "bunny"} and not record["rebuilt"]  # dynamic from the start
        assert record["lights_changed"]  # the lamp moves every frame
        # Localized: the cells near ball and bunny, not the whole grid, get urgency.
        assert 0 < record["touched_cells"] < 0.2 * np.prod(record["grid"])
        # The job's cache was solved from stored hits: a frame traces again only the probe rays
        # the moving ball and bunny reach (the lamp's move re-shades the stored hits), then solves
        # again, instead of 4 warm-up updates of every surface cell.
        assert record["refresh"] == "resolve"
        assert 0 < record["rays"] < 0.6 * independent[frame]["rays"], (record["rays"], independent[frame]["rays"])


@pytest.fixture(scope="module")
def cornell_frames(tmp_path_factory):
    out = tmp_path_factory.mktemp("static")
    return {
        mode: hybridgi(str(CORNELL), "--out", str(out / mode), "--frames", "1-3", *FAST,
                       "--set", "resolution=16", "--set", f"animation_mode={mode}")
        for mode in ("INDEPENDENT", "INCREMENTAL")
    }


def test_static_scene_is_stable_over_frames(cornell_frames):
    """INDEPENDENT: frames 1-3 of a static scene are bit-identical (the warm-up and the shadow rays
    do not depend on the frame). INCREMENTAL: each frame adds one EMA update with new rays, so
    consecutive frames differ by the cache's noise only: relative L1 of Combined < 3%, of Diffuse
    Indirect < 6%, Diffuse Direct identical."""
    frames = [passes(r["exr"]) for r in cornell_frames["INDEPENDENT"]]
    for other in frames[1:]:
        for name in frames[0]:
            np.testing.assert_array_equal(frames[0][name], other[name], err_msg=name)
    frames = [passes(r["exr"]) for r in cornell_frames["INCREMENTAL"]]
    for a, b in zip(frames, frames[1:], strict=False):
        np.testing.assert_array_equal(a["Diffuse Direct"], b["Diffuse Direct"])
        assert rel_l1(b["Combined"][..., :3], a["Combined"][..., :3]) < 0.03
        assert rel_l1(b["Diffuse Indirect"], a["Diffuse Indirect"]) < 0.06
    # The job's first frame converges as an independent frame does.
    first = passes(cornell_frames["INCREMENTAL"][0]["exr"])
    assert rel_l1(first["Combined"][..., :3], passes(cornell_frames["INDEPENDENT"][0]["exr"])["Combined"][..., :3]) < 0.03


# --- in-process: edits between the frames of one job ---------------------------------------------


@pytest.fixture(scope="module")
def addon(bpy_module):
    """The checkout's add-on, with the animation handlers registered (registered here too, and
    unregistered afterwards, while addon/__init__.py does not register them itself)."""
    from hybridgi_cli import dev_install

    package = dev_install.enable()
    animation = importlib.import_module(f"{package.__name__}.animation")
    ours = animation.on_frame_change_post not in bpy_module.app.handlers.frame_change_post
    if ours:
        animation.register()
    yield package
    if ours:
        animation.unregister()


@pytest.fixture
def modules(addon):
    names = ("animation", "pipeline", "engine", "updates")
    return type("Modules", (), {n: importlib.import_module(f"{addon.__name__}.{n}") for n in names})


def open_scene(bpy, path: Path, mode: str, resolution: int | None = None):
    from hybridgi_cli import main as cli

    bpy.ops.wm.open_mainfile(filepath=str(path), load_ui=False)
    scene = bpy.context.scene
    scene.render.engine = "HYBRIDGI"
    scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage = W, H, 100
    for flag in cli.PASS_FLAGS:
        setattr(scene.view_layers[0], flag, True)
    scene.hybridgi.warmup_iterations = 4
    scene.hybridgi.animation_mode = mode
    if resolution:
        scene.hybridgi.resolution = resolution
    return scene


def render(bpy, modules, scene, frame: int, tmp_path: Path) -> tuple[dict, dict]:
    """Render `frame` through the engine; returns (passes, the pipeline's stats of the frame)."""
    from hybridgi_cli import main as cli

    scene.frame_set(frame)
    bpy.ops.render.render()
    assert modules.engine.LAST_ERROR is None, modules.engine.LAST_ERROR
    stem = tmp_path / f"{scene.name}_{frame:04d}"
    cli.save(bpy, scene, stem.with_suffix(".png"), stem.with_suffix(".exr"))
    return passes(stem.with_suffix(".exr")), dict(modules.pipeline.LAST_STATS)


def test_moving_one_object_refreshes_only_cells_near_it(bpy_module, modules, tmp_path):
    """The animated room held still (animation cleared), then the bunny moves 10 cm: only cells
    within the indirect range of its old and new place get urgency and extra rays."""
    bpy = bpy_module
    scene = open_scene(bpy, ANIMATED, "INCREMENTAL")
    for obj in scene.objects:
        obj.animation_data_clear()
    render(bpy, modules, scene, 1, tmp_path)
    job = modules.pipeline._JOBS[modules.animation.render_job_key(scene.name_full, scene.view_layers[0].name)]
    cache = job.session.system.cache
    samples = cache.samples.copy()
    assert cache.urgency.max() == 0  # converged, nothing changed yet

    bunny = bpy.data.objects["bunny"]
    bunny.location.x += 0.1
    _, stats = render(bpy, modules, scene, 2, tmp_path)
    assert stats["moved"] == ["bunny"] and stats["job_frames"] == 2
    cache = job.session.system.cache  # a static object that starts moving rebuilds the ray scene
    assert cache.samples.max() > 0  # ... and keeps the cache

    touched = np.flatnonzero(cache.urgency > 0)
    refreshed = np.flatnonzero(cache.samples != samples)
    twice = np.flatnonzero(cache.samples - samples >= 2)
    total = cache.grid.count
    print(f"grid {total} cells: {touched.size} touched, {refreshed.size} refreshed "
          f"({stats['cells']} visible), {twice.size} with an extra update")
    assert touched.size == stats["touched_cells"]
    assert 0 < touched.size < 0.1 * total
    # Everything refreshed is a visible cell or one near the bunny; extra rays only near it.
    assert refreshed.size <= stats["cells"] + touched.size < 0.25 * total
    assert 0 < twice.size and np.isin(twice, touched).all()
    g = job.session.snapshot.geometry
    index = [o.name for o in job.session.snapshot.objects].index("bunny")
    verts = g.positions[g.triangles[g.object_index == index].ravel()]
    lo, hi = verts.min(0) - np.array([0.1, 0, 0]), verts.max(0)  # old and new place
    centres = cache.centers[touched]
    dist = np.linalg.norm(np.maximum(np.maximum(lo - centres, centres - hi), 0), axis=1)
    assert (dist <= cache.influence_radius() + 1e-4).all()


@pytest.mark.parametrize("mode", ["INDEPENDENT", "INCREMENTAL"])
def test_light_energy_change_between_frames_reaches_the_image(bpy_module, modules, tmp_path, mode):
    bpy = bpy_module
    scene = open_scene(bpy, CORNELL, mode, resolution=16)
    lamp = bpy.data.lights["ceiling_light"]
    lamp.keyframe_insert("energy", frame=1)
    lamp.energy *= 2.0
    lamp.keyframe_insert("energy", frame=2)
    before, _ = render(bpy, modules, scene, 1, tmp_path)
    after, stats = render(bpy, modules, scene, 2, tmp_path)
    direct = after["Diffuse Direct"].sum() / before["Diffuse Direct"].sum()
    indirect = after["Diffuse Indirect"].sum() / before["Diffuse Indirect"].sum()
    assert direct == pytest.approx(2.0, rel=1e-3)  # same shadow rays, twice the power
    if mode == "INCREMENTAL":
        # A jump this large re-converges the kept cache (pipeline.LIGHT_JUMP); starting from the
        # kept cache it holds a few more bounces than frame 1's short warm-up did.
        assert stats["lights_changed"] and stats["light_jump"] and stats["job_frames"] == 2
        assert indirect == pytest.approx(2.0, rel=0.15)
    else:
        assert indirect == pytest.approx(2.0, rel=0.02)


def test_deleting_objects_between_frames_of_a_job_is_safe(bpy_module, modules, tmp_path):
    bpy = bpy_module
    scene = open_scene(bpy, ANIMATED, "INCREMENTAL")
    first, _ = render(bpy, modules, scene, 10, tmp_path)
    orange = (first["Diffuse Color"][..., 0] > 0.7) & (first["Diffuse Color"][..., 2] < 0.1)
    assert orange.sum() > 10  # the ball is in view

    bpy.data.objects.remove(bpy.data.objects["ball"])
    after, stats = render(bpy, modules, scene, 11, tmp_path)
    assert stats["job_frames"] == 2 and stats["rebuilt"]  # the job went on with a new ray scene
    assert stats["touched_cells"] > 0  # cells around where the ball was refresh quickly
    assert not ((after["Diffuse Color"][..., 0] > 0.7) & (after["Diffuse Color"][..., 2] < 0.1)).any()
    for name, pixels in after.items():
        assert np.isfinite(pixels).all(), name

    for obj in [o for o in scene.objects if o.type == "MESH"]:
        bpy.data.objects.remove(obj)
    empty, stats = render(bpy, modules, scene, 12, tmp_path)
    assert stats["rays"] == 0  # only the world: the job ends
    assert modules.animation.live_session(modules.animation.render_job_key(scene.name_full, scene.view_layers[0].name)) is None
    again, stats = render(bpy, modules, scene, 13, tmp_path)
    assert np.isfinite(again["Combined"]).all()


def test_deforming_mesh_is_retraced_in_the_dynamic_scene(bpy_module, modules, tmp_path):
    """A shape-key animation: the mesh is animated from the job's start (no rebuild when it
    deforms), and the deformation reaches the image."""
    bpy = bpy_module
    scene = open_scene(bpy, CORNELL, "INCREMENTAL", resolution=16)
    block = bpy.data.objects["tall_block"]
    block.shape_key_add(name="Basis")
    key = block.shape_key_add(name="squash")
    for point in key.data:
        point.co.z *= 0.5
    key.value = 0.0
    key.keyframe_insert("value", frame=1)
    key.value = 1.0
    key.keyframe_insert("value", frame=2)
    assert "tall_block" in modules.updates.animated_object_names(scene.objects)
    before, _ = render(bpy, modules, scene, 1, tmp_path)
    after, stats = render(bpy, modules, scene, 2, tmp_path)
    assert stats["moved"] == ["tall_block"] and not stats["rebuilt"]
    # The block is half as tall: the pixels that saw its top half now see the wall behind it.
    deeper = after["Depth"][..., 0] > before["Depth"][..., 0] * 1.05
    assert deeper.mean() > 0.01


def test_animated_object_names_follow_parents_armatures_and_shape_keys(bpy_module, modules, empty_scene):
    bpy = bpy_module
    scene = empty_scene

    def mesh_object(name):
        obj = bpy.data.objects.new(name, bpy.data.meshes.new(name))
        scene.collection.objects.link(obj)
        return obj

    still, mover, child, keyed, rigged = (mesh_object(n) for n in ("still", "mover", "child", "keyed", "rigged"))
    mover.keyframe_insert("location", frame=1)
    child.parent = mover
    keyed.shape_key_add(name="Basis")
    keyed.shape_key_add(name="k").keyframe_insert("value", frame=1)
    rig = bpy.data.objects.new("rig", bpy.data.armatures.new("rig"))
    scene.collection.objects.link(rig)
    rig.keyframe_insert("rotation_euler", frame=1)
    rigged.modifiers.new("Armature", "ARMATURE").object = rig
    names = modules.updates.animated_object_names(scene.objects)
    assert names == {"mover", "child", "keyed", "rig", "rigged"}


def test_handlers_feed_named_events_to_live_sessions(bpy_module, modules, tmp_path):
    bpy = bpy_module
    animation = modules.animation
    scene = open_scene(bpy, ANIMATED, "INDEPENDENT")
    dropped = []
    animation.register_session("viewport", object(), scene=scene.name_full, on_drop=lambda: dropped.append(1))
    animation.register_session("elsewhere", object(), scene="another scene")
    try:
        scene.frame_set(20)
        events = animation.take_events("viewport")
        assert events.frame == 20 and events.moved == {"ball", "bunny"} and events.lights
        assert len(events.swept) == 2
        ball = procedural.ball_transform(20).location
        assert any(((lo - 1e-3 <= ball) & (ball <= hi + 1e-3)).all() for lo, hi in events.swept.values())
        assert not animation.take_events("viewport").dirty  # taken
        assert not animation.take_events("elsewhere").dirty  # another scene's session heard nothing

        bpy.data.objects["back_wall"].location.y -= 0.2  # an edit, not a frame change
        bpy.context.view_layer.update()
        events = animation.take_events("viewport")
        assert "back_wall" in events.moved and events.frame is None

        bpy.ops.wm.open_mainfile(filepath=str(ANIMATED), load_ui=False)  # load_pre drops them all
        assert dropped == [1] and animation.live_session("viewport") is None
    finally:
        animation.unregister_session("viewport")
        animation.unregister_session("elsewhere")

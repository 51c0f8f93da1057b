"""Render settings and object flags a user sets, through the real `hybridgi render` command: each
either works as in Cycles (render border with and without crop, transparent film, objects hidden
from the camera, a zero scale on one axis) or is refused with a clear message (panoramic camera)."""

from __future__ import annotations

import json
import textwrap
from pathlib import Path

import numpy as np
import pytest

from hybridgi_cli import exr
from tests import cli_renders
from tests.cli_renders import QUICK, run_render

ROOT = Path(__file__).resolve().parents[1]
RES = "64x48"

pytestmark = [pytest.mark.blender, pytest.mark.slow]


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    """The Cornell box, and variants edited in a bpy subprocess (the user's files stay untouched)."""
    script = textwrap.dedent("""
        def variant(name, edit):
            bpy.ops.wm.open_mainfile(filepath=src)
            edit(bpy.data)
            bpy.ops.wm.save_as_mainfile(filepath=out + "/" + name + ".blend")
        variant("hidden_block", lambda d: setattr(d.objects["tall_block"], "visible_camera", False))
        variant("flat_block", lambda d: setattr(d.objects["tall_block"], "scale", (1.0, 1.0, 0.0)))
        variant("pano", lambda d: setattr(d.cameras[0], "type", "PANO"))
        def placed(scale, offset):
            def edit(d):
                scene = bpy.context.scene
                root = d.objects.new("root", None)
                scene.collection.objects.link(root)
                for ob in list(scene.objects):
                    if ob.parent is None and ob is not root:
                        ob.parent = root
                root.scale, root.location = (scale,) * 3, (offset, offset, 0.0)
                for light in d.lights:
                    light.energy *= scale * scale  # the same radiance from the scaled lamp
                for cam in d.cameras:
                    cam.clip_start, cam.clip_end = cam.clip_start * scale, cam.clip_end * scale
                scene.world.light_settings.distance *= scale
            return edit
        def second_layer(d):
            scene = bpy.context.scene
            block = d.objects["tall_block"]
            own = d.collections.new("block")
            scene.collection.children.link(own)
            for c in list(block.users_collection):
                c.objects.unlink(block)
            own.objects.link(block)
            scene.view_layers.new("NoBlock").layer_collection.children["block"].exclude = True
        variant("two_layers", second_layer)
        def mirrored_camera(d):
            rig = d.objects.new("rig", None)
            bpy.context.scene.collection.objects.link(rig)
            rig.scale = (-1.0, 1.0, 1.0)
            bpy.context.scene.camera.parent = rig
        variant("mirrored_camera", mirrored_camera)
        variant("centimetres", placed(0.01, 0.0))
        variant("far_away", placed(1.0, 1.0e5))
    """)
    return cli_renders.cornell_variants(tmp_path_factory.mktemp("settings_scenes"), script)


def render(blend, prefix, *extra):
    return run_render(blend, prefix, RES, *QUICK, *extra)


def rendered(blend, prefix, *extra):
    run = render(blend, prefix, *extra)
    assert run.returncode == 0, run.stderr[-3000:]
    record = json.loads(run.stdout.strip().splitlines()[-1])
    return record, exr.read_channels(record["exr"])


def layer(channels, name):
    return cli_renders.layer(channels, name, "RGBA" if name == "Combined" else "Z" if name == "Depth" else "RGB")


@pytest.fixture(scope="module")
def full(scenes, tmp_path_factory):
    return rendered(scenes / "cornell.blend", tmp_path_factory.mktemp("full") / "f")[1]


BORDER = ("--set", "render.use_border=true", "--set", "render.border_min_x=0.25", "--set", "render.border_max_x=0.75",
          "--set", "render.border_min_y=0.5", "--set", "render.border_max_y=1.0")


def test_render_border_fills_only_the_border_of_a_full_size_image(scenes, full, tmp_path):
    _record, ch = rendered(scenes / "cornell.blend", tmp_path / "b", *BORDER, "--set", "render.use_crop_to_border=false")
    combined, reference = layer(ch, "Combined"), layer(full, "Combined")
    assert combined.shape == reference.shape == (48, 64, 4)
    # EXR rows are top-down: the border's upper half of the frame is rows 0-23, columns 16-47.
    inside = np.zeros((48, 64), bool)
    inside[0:24, 16:48] = True
    assert np.all(combined[~inside] == 0)  # outside the border: nothing rendered (alpha 0), as Cycles
    np.testing.assert_allclose(combined[inside], reference[inside], atol=1e-4)


def test_render_border_with_crop_writes_the_border_alone(scenes, full, tmp_path):
    _record, ch = rendered(scenes / "cornell.blend", tmp_path / "c", *BORDER, "--set", "render.use_crop_to_border=true")
    for name in ("Combined", "Diffuse Indirect", "Depth"):
        cropped = layer(ch, name)
        assert cropped.shape[:2] == (24, 32), name
        np.testing.assert_allclose(cropped, layer(full, name)[0:24, 16:48], atol=1e-4, err_msg=name)


def test_transparent_film_hides_the_world_but_keeps_its_light(scenes, full, tmp_path):
    _record, ch = rendered(scenes / "cornell.blend", tmp_path / "t", "--set", "render.film_transparent=true")
    combined, opaque = layer(ch, "Combined"), layer(full, "Combined")
    background = layer(full, "Depth")[..., 0] > 1e9
    assert background.any() and (~background).any()
    # The pixel filter spreads a silhouette over ~2 px (filter size 1.5): compare away from it.
    near = _grown(background, 3) & _grown(~background, 3)
    assert np.all(combined[background & ~near] == 0)  # premultiplied: no world colour under alpha 0
    np.testing.assert_allclose(combined[~background & ~near][:, 3], 1.0)
    np.testing.assert_allclose(combined[~background & ~near][:, :3], opaque[~background & ~near][:, :3], atol=1e-4)
    # On the silhouette the coverage is partial and the world adds nothing to the colour.
    edge = near & (combined[..., 3] > 0.05) & (combined[..., 3] < 0.95)
    assert edge.any()
    assert np.all(combined[edge][:, :3] <= opaque[edge][:, :3] + 1e-4)


def _grown(mask, steps):
    """mask dilated by `steps` pixels (4-neighbourhood)."""
    out = mask.copy()
    for _ in range(steps):
        grown = out.copy()
        grown[1:] |= out[:-1]
        grown[:-1] |= out[1:]
        grown[:, 1:] |= out[:, :-1]
        grown[:, :-1] |= out[:, 1:]
        out = grown
    return out


def test_object_hidden_from_the_camera_still_casts_its_shadow(scenes, full, tmp_path):
    _record, ch = rendered(scenes / "hidden_block.blend", tmp_path / "h")
    depth, depth_full = layer(ch, "Depth")[..., 0], layer(full, "Depth")[..., 0]
    behind = depth > depth_full * 1.05  # pixels that saw the tall block now see what is behind it
    assert behind.mean() > 0.03
    # The floor and wall behind the block stay shadowed by it: the lamp's light does not reach them
    # more than in the render where the block is seen (a block removed from the rays would light them).
    direct = layer(ch, "Diffuse Direct")[..., :3].mean(axis=-1)
    visible_direct = layer(full, "Diffuse Direct")[..., :3].mean(axis=-1)
    unseen = ~behind & (depth < 1e9)
    np.testing.assert_allclose(direct[unseen].mean(), visible_direct[unseen].mean(), rtol=0.02)


def test_zero_scale_on_one_axis_flattens_the_object_instead_of_dropping_it(scenes, full, tmp_path):
    record, ch = rendered(scenes / "flat_block.blend", tmp_path / "z")
    _full_record, _ = rendered(scenes / "cornell.blend", tmp_path / "zf")
    # The flattened block lies on the floor (z = 0 in its own space): its top face remains.
    assert record["triangles"] >= _full_record["triangles"] - 8  # only the side faces lost their area
    assert np.isfinite(layer(ch, "Combined")).all()


def test_a_camera_under_a_mirroring_parent_renders_the_mirror_image(scenes, full, tmp_path):
    # Cycles renders the mirrored view; HybridGI's G-buffer took every triangle for a back face
    # and flipped its normal away from the camera (dark, no shadows): here Combined 0.95 off the
    # unmirrored render's mirror image, 0.03 after (the subframes' jitter is not mirrored).
    _record, ch = rendered(scenes / "mirrored_camera.blend", tmp_path / "m")
    mirrored, reference = layer(ch, "Combined")[:, ::-1, :3], layer(full, "Combined")[..., :3]
    assert np.abs(mirrored - reference).sum() / np.abs(reference).sum() < 0.06
    # World-space normals: the mirror is in the view, not the scene; they face the camera.
    normal = cli_renders.layer(ch, "Normal", "XYZ")[:, ::-1]
    assert np.abs(normal - cli_renders.layer(full, "Normal", "XYZ")).mean() < 0.05


@pytest.mark.parametrize(("name", "tolerance"), [("centimetres", 0.03), ("far_away", 0.06)])
def test_a_scene_scaled_to_centimetres_or_placed_100_km_away_renders_the_same(scenes, full, tmp_path, name, tolerance):
    """The whole box under an empty: scaled to 1/100 (a model in centimetres; the camera inherits the
    scale, which Blender's engines ignore: the image was black), or moved 100 km (georeferenced
    coordinates, 8 mm float32 steps: surfaces shadowed themselves in streaks)."""
    _record, ch = rendered(scenes / f"{name}.blend", tmp_path / name)
    for pass_name in ("Combined", "Diffuse Direct", "Ambient Occlusion"):
        got, want = layer(ch, pass_name)[..., :3], layer(full, pass_name)[..., :3]
        err = np.abs(got - want).sum() / np.abs(want).sum()
        assert err < tolerance, f"{name}: {pass_name} relative L1 {err:.4f} against the box at the origin"


def test_panoramic_camera_is_refused_with_a_clear_message(scenes, tmp_path):
    run = render(scenes / "pano.blend", tmp_path / "p")
    assert run.returncode != 0
    assert "panoramic" in run.stderr and "Traceback" not in run.stderr
    assert not list(tmp_path.glob("p_*.exr")) and not list(tmp_path.glob("p_*.png"))


def test_motion_blur_and_passes_hybridgi_does_not_write_are_warned_by_name(scenes, tmp_path):
    # Depth of field renders through the subframes' lens points: with one pixel sample it cannot.
    run = render(scenes / "cornell.blend", tmp_path / "w", "--set", "render.use_motion_blur=true",
                 "--set", "camera.data.dof.use_dof=true", "--set", "pixel_samples=1")
    assert run.returncode == 0, run.stderr[-2000:]
    assert "motion blur is not rendered" in run.stderr
    assert "depth of field of camera" in run.stderr and "needs Pixel Samples above 1" in run.stderr


def test_shadow_samples_trade_penumbra_noise_for_rays(scenes, full, tmp_path):
    """Shadow Samples sets the rays of the area lamp's penumbrae: 1 ray per pixel leaves the block's
    soft shadow noisy, the default 48 is close to a 256-ray render of the same frame."""
    many = layer(rendered(scenes / "cornell.blend", tmp_path / "s256", "--set", "shadow_samples=256")[1],
                 "Diffuse Direct")[..., :3]
    errors = {}
    for samples, channels in ((1, rendered(scenes / "cornell.blend", tmp_path / "s1", "--set", "shadow_samples=1")[1]),
                              (48, full)):
        got = layer(channels, "Diffuse Direct")[..., :3]
        errors[samples] = np.abs(got - many).sum() / np.abs(many).sum()
    assert errors[1] > 2.0 * errors[48], errors
    assert errors[48] < 0.02, errors


def test_non_square_pixels_render_as_cycles_and_the_exr_is_still_written(scenes, full, tmp_path):
    """Pixel Aspect 2:1 (anamorphic): Blender's multilayer EXR writer refuses it (for Cycles too),
    so the EXR is written with square pixels and a warning; the image is the one the camera's
    non-square pixels see, as in Cycles."""
    aspect = ("--set", "render.pixel_aspect_x=2")
    run = render(scenes / "cornell.blend", tmp_path / "a", *aspect)
    assert run.returncode == 0, run.stderr[-2000:]
    assert "Pixel Aspect 2:1" in run.stderr
    record = json.loads(run.stdout.strip().splitlines()[-1])
    depth = layer(exr.read_channels(record["exr"]), "Depth")[..., 0]
    cycles = run_render(scenes / "cornell.blend", tmp_path / "c", RES, "--engine", "CYCLES", "--samples", "1", *aspect)
    assert cycles.returncode == 0, cycles.stderr[-2000:]
    want = layer(exr.read_channels(json.loads(cycles.stdout.strip().splitlines()[-1])["exr"]), "Depth")[..., 0]
    geo = (depth < 1e9) & (want < 1e9)
    assert geo.mean() > 0.5
    assert np.median(np.abs(depth - want)[geo] / want[geo]) < 1e-3
    # The aspect changed the view: the box's side walls and floor (not the back wall, whose view
    # depth is constant) moved in the image.
    square = layer(full, "Depth")[..., 0]
    moved = np.abs(depth - square) > 1e-2 * np.minimum(depth, square)
    assert moved.mean() > 0.1, moved.mean()


def test_an_image_larger_than_the_gpu_textures_is_refused_with_a_clear_message(scenes, tmp_path):
    """65536 pixels wide (Blender's largest resolution) is beyond any GPU's texture limit: the frame
    fails before allocating anything, saying why, and writes no file."""
    run = run_render(scenes / "cornell.blend", tmp_path / "big", "65536x4", *QUICK)
    assert run.returncode != 0
    assert "textures take at most" in run.stderr and "internal error" not in run.stderr
    assert not list(tmp_path.glob("big_*"))


def test_each_view_layer_gets_its_own_render(scenes, full, tmp_path):
    """Two view layers, the second without the tall block: Blender renders each with its own
    depsgraph, and each EXR layer holds that layer's image (the second one's used to overwrite
    the first's, leaving its own layer empty)."""
    _record, ch = rendered(scenes / "two_layers.blend", tmp_path / "v")
    depth = {name: ch[f"{name}.Depth.Z"] for name in ("ViewLayer", "NoBlock")}
    np.testing.assert_allclose(depth["ViewLayer"], layer(full, "Depth")[..., 0], rtol=1e-5)
    geo = depth["NoBlock"] < 1e9
    assert geo.mean() > 0.3  # the box is there
    behind = depth["NoBlock"] > depth["ViewLayer"] * 1.05  # where the block stood, the wall behind it
    assert 0.03 < behind.mean() < 0.3


def test_stereoscopy_is_refused_by_the_cli_with_a_clear_message(scenes, tmp_path):
    """One image per frame is what `hybridgi render` writes: a stereoscopic scene (Blender would
    write one per view, and failed to save them, for Cycles too) is refused up front, no file."""
    run = render(scenes / "cornell.blend", tmp_path / "s", "--set", "render.use_multiview=true")
    assert run.returncode != 0
    assert "Stereoscopy" in run.stderr and "internal error" not in run.stderr
    assert not list(tmp_path.glob("s_*"))

"""Renders through the real HYBRIDGI engine (the `hybridgi` command in a subprocess), checked on
the pixels of the multilayer EXR it writes, and against Cycles rendered in the same test."""

from __future__ import annotations

import json
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from hybridgi_cli import blender_compat, exr

ROOT = Path(__file__).resolve().parents[1]
HYBRIDGI = Path(sys.executable).parent / "hybridgi"

pytestmark = [pytest.mark.blender, pytest.mark.slow]


@pytest.fixture(scope="module")
def cornell(tmp_path_factory):
    out = tmp_path_factory.mktemp("scenes")
    subprocess.run([sys.executable, str(ROOT / "blend_scenes" / "build.py"), "--only", "cornell", "--out", str(out)],
                   check=True, capture_output=True)
    return out / "cornell.blend"


def render(blend, prefix, *extra, res="96x72"):
    run = subprocess.run([str(HYBRIDGI), "render", str(blend), "--out", str(prefix), "--res", res, *extra],
                         capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-3000:]
    record = json.loads(run.stdout.strip().splitlines()[-1])
    return record, exr.read_channels(record["exr"])


def layer(channels, name):
    keys = sorted((k for k in channels if k.startswith(f"ViewLayer.{name}.")), key=lambda k: "RGBAXYZ".find(k[-1]))
    return np.stack([channels[k] for k in keys], axis=-1)


def blur(img, r=1):
    p = np.pad(img, ((r, r), (r, r), (0, 0)), mode="edge")
    out = np.zeros_like(img)
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            out += p[r + dy : r + dy + img.shape[0], r + dx : r + dx + img.shape[1]]
    return out / (2 * r + 1) ** 2


def rel_l1(test, ref, mask):
    return float(np.abs(test - ref)[mask].sum() / np.abs(ref)[mask].sum())


@pytest.fixture(scope="module")
def cornell_render(cornell, tmp_path_factory):
    return render(cornell, tmp_path_factory.mktemp("hg") / "cornell")


@pytest.mark.smoke
def test_all_passes_present_with_cycles_names_and_channels(cornell_render):
    record, ch = cornell_render
    expected = {
        "Combined": "RGBA", "Diffuse Direct": "RGB", "Diffuse Indirect": "RGB", "Diffuse Color": "RGB",
        "Ambient Occlusion": "RGB", "Depth": "Z", "Normal": "XYZ",
    }
    in_file = set(exr.channel_names(record["exr"]))
    for name, chans in expected.items():
        for c in chans:
            key = f"ViewLayer.{name}.{c}"
            assert key in ch, key
            assert ch[key].shape == (72, 96) and np.isfinite(ch[key]).all(), key
            # The file holds this Blender's Cycles names (DiffDir ... before 5.0).
            assert f"ViewLayer.{blender_compat.cycles_pass_name(name)}.{c}" in in_file, key
    assert record["engine"] == "HYBRIDGI" and record["rays"] > 0
    # Per-pixel rays (the default) replace the screen-space pass.
    for step in ("gbuffer", "downsample", "select", "warmup", "gather", "pixel_rays", "bilateral", "deferred"):
        assert step in record["steps_ms"], step
    # Combined = albedo x (direct + indirect) + emission, per Cycles' pass definitions.
    comb = layer(ch, "Combined")[..., :3]
    recon = layer(ch, "Diffuse Color") * (layer(ch, "Diffuse Direct") + layer(ch, "Diffuse Indirect"))
    geo = layer(ch, "Depth")[..., 0] < 1e9
    assert rel_l1(recon, comb, geo) < 1e-3


@pytest.mark.smoke
def test_cornell_red_wall_bleeds_onto_the_floor(cornell_render):
    """Floor pixels near the red (left) wall get redder indirect light than those near the green one."""
    _, ch = cornell_render
    ind = layer(ch, "Diffuse Indirect")
    normal = layer(ch, "Normal")
    floor = normal[..., 2] > 0.9
    w = floor.shape[1]
    cols = np.arange(w)[None, :].repeat(floor.shape[0], 0)
    left = floor & (cols < w * 0.4)
    right = floor & (cols > w * 0.6)
    assert left.sum() > 20 and right.sum() > 20
    red_left = ind[left, 0].mean() / ind[left, 1].mean()
    red_right = ind[right, 0].mean() / ind[right, 1].mean()
    # Measured ~2.3x at 96x72; a grey (no-bleeding) cache gives 1.
    assert red_left / red_right > 1.5, (red_left, red_right)


@pytest.mark.smoke
def test_cornell_indirect_close_to_cycles(cornell, cornell_render, tmp_path):
    """Diffuse Indirect within 0.20 relative L1 (3x3 blur, geometry pixels) of Cycles at 256 spp.

    Budget: at 96x72 HybridGI measured 0.146 against this reference; Cycles' own 256 spp noise and
    the 24x18 GI resolution of such a tiny image make up most of it (at 320x240 against 1024 spp:
    0.09). Diffuse Direct must agree much more closely: same lamps, same shadow rays.
    """
    _, ch = cornell_render
    _, ref = render(cornell, tmp_path / "cycles", "--engine", "CYCLES", "--samples", "256")
    geo = layer(ref, "Depth")[..., 0] < 1e9
    di = rel_l1(blur(layer(ch, "Diffuse Indirect")), blur(layer(ref, "Diffuse Indirect")), geo)
    dd = rel_l1(blur(layer(ch, "Diffuse Direct")), blur(layer(ref, "Diffuse Direct")), geo)
    assert di < 0.20, di
    assert dd < 0.08, dd


def _write_blend(path: Path, body: str) -> None:
    script = textwrap.dedent(
        """
        import bpy
        from hybridgi_cli import blender_compat
        bpy.ops.wm.read_homefile(use_empty=True)
        scene = bpy.context.scene
        cam = bpy.data.objects.new("cam", bpy.data.cameras.new("cam"))
        cam.location = (0, -6, 2); cam.rotation_euler = (1.3, 0, 0)
        scene.collection.objects.link(cam); scene.camera = cam
        scene.world = blender_compat.new_world(bpy, "w")
        """
    ) + textwrap.dedent(body) + f"\nbpy.ops.wm.save_as_mainfile(filepath={str(path)!r})\n"
    subprocess.run([sys.executable, "-c", script], check=True, capture_output=True, timeout=120)


def test_empty_scene_renders_the_world_only(tmp_path):
    blend = tmp_path / "empty.blend"
    _write_blend(blend, """
        scene.world.node_tree.nodes["Background"].inputs["Color"].default_value = (0.2, 0.3, 0.4, 1)
    """)
    _, ch = render(blend, tmp_path / "empty", res="32x24")
    comb = layer(ch, "Combined")
    np.testing.assert_allclose(comb[..., :3].reshape(-1, 3).mean(0), [0.2, 0.3, 0.4], rtol=1e-3)
    assert (layer(ch, "Diffuse Indirect") == 0).all()


def test_scene_without_lights_is_lit_by_the_sky_alone(tmp_path):
    blend = tmp_path / "nolights.blend"
    _write_blend(blend, """
        scene.world.node_tree.nodes["Background"].inputs["Color"].default_value = (0.5, 0.5, 0.5, 1)
        bpy.ops.mesh.primitive_plane_add(size=10)
        bpy.ops.mesh.primitive_cube_add(location=(0, 0, 1))
    """)
    _, ch = render(blend, tmp_path / "nolights", "--set", "warmup_iterations=4", res="64x48")
    geo = layer(ch, "Depth")[..., 0] < 1e9
    direct = layer(ch, "Diffuse Direct")[geo]
    assert np.isfinite(direct).all() and geo.sum() > 100
    # An open floor under a uniform sky of radiance 0.5 sees Diffuse Direct = E / pi = 0.5.
    floor = geo & (layer(ch, "Normal")[..., 2] > 0.99)
    assert abs(np.median(layer(ch, "Diffuse Direct")[floor][:, 0]) - 0.5) < 0.1


def test_scene_without_camera_fails_with_a_clear_message(tmp_path):
    blend = tmp_path / "nocam.blend"
    _write_blend(blend, """
        scene.camera = None
        bpy.ops.mesh.primitive_cube_add()
    """)
    run = subprocess.run([str(HYBRIDGI), "render", str(blend), "--out", str(tmp_path / "x"), "--res", "16x16"],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode != 0
    assert "camera" in run.stderr.lower()


def test_warm_up_progress_says_how_long_is_left(cornell, tmp_path):
    """Each warm-up update's status (Blender's status bar; logged, so the CLI prints it on stderr)
    carries an estimate of the time left."""
    run = subprocess.run([str(HYBRIDGI), "render", str(cornell), "--out", str(tmp_path / "p"), "--res", "32x24",
                          "--set", "warmup_iterations=3"], capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-3000:]
    left = [float(s) for s in re.findall(r"hybridgi: frame 1: converging cache \d/3, (\d+\.\d) s left", run.stderr)]
    assert len(left) == 3 and left[-1] == 0.0 and left[0] > 0.0, run.stderr[-3000:]

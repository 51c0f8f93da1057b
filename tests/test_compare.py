"""The Compare with Cycles operator (addon/compare.py): both renders of the Cornell box, the
errors per pass, the side-by-side heatmap image, and every scene setting restored."""

from __future__ import annotations

import importlib
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytestmark = [pytest.mark.blender, pytest.mark.slow]

REPO = Path(__file__).resolve().parents[1]
W, H = 64, 48


@pytest.fixture(scope="module")
def cornell_blend(tmp_path_factory):
    out = tmp_path_factory.mktemp("scenes")
    env = {k: v for k, v in os.environ.items() if k != "BLENDER_USER_RESOURCES"}
    run = subprocess.run([sys.executable, str(REPO / "blend_scenes" / "build.py"), "--only", "cornell", "--out", str(out)],
                         capture_output=True, text=True, timeout=120, env=env, cwd=REPO)
    assert run.returncode == 0, run.stderr[-2000:]
    return out / "cornell.blend"


@pytest.fixture
def compare(bpy_module, gpu_context, cornell_blend):
    from hybridgi_cli import dev_install  # noqa: PLC0415

    bpy_module.ops.wm.open_mainfile(filepath=str(cornell_blend))
    package = dev_install.enable()
    return importlib.import_module(f"{package.__name__}.compare")


def test_heatmap_is_black_where_equal_and_hot_where_off(compare):
    ref = np.full((2, 3, 3), 0.5, np.float32)
    test = ref.copy()
    test[0, 0] = 1.0  # 100% off
    mask = np.ones((2, 3), bool)
    heat = compare.heatmap(test, ref, mask)
    assert heat.shape == (2, 3, 3) and np.all(heat[1] == 0.0)
    np.testing.assert_allclose(heat[0, 0], compare.RAMP[-1])  # beyond full scale: the ramp's top
    assert compare.relative_l1(test, ref, mask) == pytest.approx(1.5 / 9.0)
    assert compare.side_by_side(test, ref, heat).shape == (2, 3 * 3 + 2 * compare.GAP, 4)


def test_compare_with_cycles_reports_errors_shows_heatmap_and_restores_the_scene(bpy_module, compare):
    bpy = bpy_module
    scene = bpy.context.scene
    scene.render.engine = "HYBRIDGI"
    scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage = W, H, 100
    scene.hybridgi.warmup_iterations = 4
    scene.render.image_settings.file_format = "PNG"
    layer = bpy.context.view_layer
    layer.use_pass_diffuse_indirect = False
    samples_before = scene.cycles.samples

    assert bpy.ops.hybridgi.compare_cycles(samples=64, resolution_percentage=100) == {"FINISHED"}

    result = compare.LAST[scene.name]
    assert set(result.errors) == set(compare.COMPARED) and result.samples == 64
    assert all(math.isfinite(e) for e in result.errors.values()), result.errors
    # 64x48 against 64 spp: Cycles' own noise is most of the indirect error.
    assert result.errors["Diffuse Indirect"] < 0.5 and result.errors["Diffuse Direct"] < 0.15, result.errors
    image = bpy.data.images[result.image]
    assert tuple(image.size) == (3 * W + 2 * compare.GAP, H)
    pixels = np.empty(image.size[0] * image.size[1] * 4, np.float32)
    image.pixels.foreach_get(pixels)
    pixels = pixels.reshape(H, -1, 4)
    assert pixels[..., :3].max() > 0.05 and np.isfinite(pixels).all()
    # What the operator changed is back.
    assert scene.render.engine == "HYBRIDGI" and scene.cycles.samples == samples_before
    assert scene.render.image_settings.file_format == "PNG" and not layer.use_pass_diffuse_indirect
    assert scene.render.resolution_percentage == 100

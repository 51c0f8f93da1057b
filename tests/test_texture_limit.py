"""Material textures are read at most twice the render's longer side per side (a power of two,
1024 to 4096: `sync.texture_limit`): a PBR asset's four 4k maps on a plate and a ball, 320x180,
first render 11.8 -> 4.0 s, 3.4 -> 1.1 GB, Combined against Cycles 16 spp + OIDN the same (Diffuse
Color 0.054 -> 0.055)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest


def _scene(width, height, percentage=100):
    return SimpleNamespace(render=SimpleNamespace(resolution_x=width, resolution_y=height,
                                                  resolution_percentage=percentage))


@pytest.mark.blender
def test_the_limit_follows_the_renders_longer_side(sync):
    limit = sync.texture_limit
    assert limit(_scene(320, 180)) == 1024  # 640 -> 1024 (the floor)
    assert limit(_scene(640, 360)) == 2048  # 1280 -> 2048
    assert limit(_scene(360, 640)) == 2048  # portrait: the longer side
    assert limit(_scene(1920, 1080)) == 4096  # 3840 -> 4096
    assert limit(_scene(1920, 1080, 50)) == 2048  # the resolution percentage counts
    assert limit(_scene(7680, 4320)) == 4096  # the core's own cap


@pytest.mark.blender
def test_a_large_image_is_read_at_the_limit_as_its_box_average(bpy_module, empty_scene, sync):
    """A 2048 image read at limit 512: a quarter a side, each texel the mean of its 4 x 4 block
    (a fine checker reads as its grey); under the limit it is read whole."""
    bpy = bpy_module
    image = bpy.data.images.new("fine", 2048, 2048, alpha=False, float_buffer=True)
    px = np.ones((2048, 2048, 4), np.float32)
    checker = ((np.arange(2048)[:, None] + np.arange(2048)[None, :]) % 2).astype(np.float32)
    px[..., :3] = checker[..., None]
    image.pixels.foreach_set(px.ravel())
    rgb, _alpha = sync.read_image(image, 512)
    assert rgb.shape == (512, 512, 3)
    np.testing.assert_allclose(rgb, 0.5, atol=0.02)
    whole, _ = sync.read_image(image, 4096)
    assert whole.shape == (2048, 2048, 3)
    assert sorted(np.unique(whole)) == [0.0, 1.0]


@pytest.mark.blender
@pytest.mark.parametrize("space", ["sRGB", "Non-Color"])
def test_a_large_image_file_averages_its_linear_values(bpy_module, empty_scene, sync, tmp_path, space):
    """A black and white checker saved as an 8-bit PNG, read at a quarter a side: grey 0.5 in
    linear values whatever its colour space (Blender's own scale of the sRGB bytes gave 0.21, the
    decoded mean of the encoded 0.5)."""
    bpy = bpy_module
    image = bpy.data.images.new("checker", 1024, 1024, alpha=False)
    px = np.ones((1024, 1024, 4), np.float32)
    px[..., :3] = ((np.arange(1024)[:, None] + np.arange(1024)[None, :]) % 2)[..., None]
    image.pixels.foreach_set(px.ravel())
    image.filepath_raw = str(tmp_path / "checker.png")
    image.file_format = "PNG"
    image.save()
    loaded = bpy.data.images.load(str(tmp_path / "checker.png"))
    loaded.colorspace_settings.name = space
    rgb, _ = sync.read_image(loaded, 256)
    assert rgb.shape == (256, 256, 3)
    np.testing.assert_allclose(rgb, 0.5, atol=0.01)

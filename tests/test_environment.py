"""Environment maps split into a shadowed sun and a sky (hybridgi_core/environment.py): analytic
maps with a known sun, and the sky's radiance read back in every direction."""

import numpy as np
import pytest

from hybridgi_core.environment import equirect_directions, split_environment
from hybridgi_core.snapshot import World

H, W = 128, 256


SUN_RADIUS = np.radians(0.8)


def sky_with_sun(direction, sun_radiance=2000.0, sun_radius=SUN_RADIUS, sky=0.4):
    dirs, _solid = equirect_directions(H, W)
    d = np.asarray(direction, np.float64) / np.linalg.norm(direction)
    pixels = np.full((H, W, 3), sky, np.float64)
    disc = dirs @ d > np.cos(max(sun_radius, 1.5 * np.pi / H))  # at least a pixel or two
    pixels[disc] = sun_radiance
    return pixels, disc


def test_equirect_directions_cover_the_sphere_with_blender_conventions():
    dirs, solid = equirect_directions(H, W)
    assert np.allclose(np.linalg.norm(dirs, axis=-1), 1.0)
    assert solid.sum() * W == pytest.approx(4 * np.pi, rel=1e-3)
    assert dirs[0, W // 2, 2] < -0.99 and dirs[-1, W // 2, 2] > 0.99  # row 0 is the nadir
    middle = dirs[H // 2, W // 2 - 1: W // 2 + 1].mean(axis=0)
    assert middle[0] > 0.99  # the image centre faces +X
    quarter = dirs[H // 2, W // 4]
    assert quarter[1] > 0.99  # u = 0.25 faces +Y (u grows clockwise seen from above)


def test_a_sun_becomes_a_lamp_with_its_direction_and_irradiance():
    direction = np.array([0.3, -0.5, 0.6])
    pixels, disc = sky_with_sun(direction)
    split = split_environment(pixels)
    d = direction / np.linalg.norm(direction)
    assert np.degrees(np.arccos(np.clip(split.sun_direction @ d, -1, 1))) < 1.0
    dirs, solid = equirect_directions(H, W)
    weight = np.broadcast_to(solid[:, None], disc.shape)
    expected = 2000.0 * float((weight[disc] * np.clip(dirs[disc] @ d, 0, None)).sum())
    np.testing.assert_allclose(split.sun_irradiance, expected, rtol=0.02)
    np.testing.assert_allclose(split.sky, 0.4, rtol=0.01)  # the sun's pixels filled with the sky around
    world = World(color=split.sky, sky_sh=split.sky_sh)
    up_and_down = world.radiance(np.array([[0, 0, 1.0], [0, 0, -1.0], [1.0, 0, 0]]))
    np.testing.assert_allclose(up_and_down, 0.4, rtol=0.03)  # a uniform sky is uniform in SH too


def test_a_studio_maps_softboxes_each_become_a_shadowed_lamp():
    """Three compact bright regions over a dim sky (a studio map's softboxes): each is split off
    with its direction and irradiance, brightest first, and the sky keeps only the dim rest. One
    sun alone left the others in the sky map, where a pixel's cosine rays meet them rarely: the
    studio.exr scene (160x90 against Cycles 256 spp) Combined 0.152, Diffuse Direct 0.195; now
    0.040 and 0.022 (interior.exr 0.066 -> 0.023, night.exr 0.106 -> 0.060)."""
    boxes = [(np.array([0.8, 0.2, 0.5]), 900.0, np.radians(4.0)), (np.array([-0.6, 0.5, 0.4]), 600.0, np.radians(5.0)),
             (np.array([0.1, -0.9, 0.3]), 400.0, np.radians(3.0))]
    dirs, solid = equirect_directions(H, W)
    pixels = np.full((H, W, 3), 0.05, np.float64)
    discs = []
    for d, radiance, radius in boxes:
        d = d / np.linalg.norm(d)
        disc = dirs @ d > np.cos(radius)
        pixels[disc] = radiance
        discs.append((d, radiance, disc))
    split = split_environment(pixels)
    found = [(split.sun_direction, split.sun_irradiance)] + [(d, e) for d, e, _a in split.more_suns]
    assert len(found) == 3
    weight = np.broadcast_to(solid[:, None], (H, W))
    for (d, radiance, disc), (direction, irradiance) in zip(discs, found, strict=True):
        assert np.degrees(np.arccos(np.clip(direction @ d, -1, 1))) < 1.0
        expected = radiance * float((weight[disc] * np.clip(dirs[disc] @ d, 0, None)).sum())
        np.testing.assert_allclose(irradiance, expected, rtol=0.03)
    np.testing.assert_allclose(split.sky, 0.05, rtol=0.05)


def test_a_broad_bright_patch_stays_in_the_sky_map():
    """After the sun, only compact regions are split off (`MAX_MORE_SUN_ANGLE`): a 25-degree bright
    patch (forest.exr's sky through the trees) lights better from the map than as a disc."""
    pixels, _ = sky_with_sun([0.3, -0.5, 0.6])
    dirs, _solid = equirect_directions(H, W)
    patch = dirs @ (np.array([-0.5, 0.5, 0.5]) / np.sqrt(0.75)) > np.cos(np.radians(12.5))
    pixels[patch] = 20.0
    split = split_environment(pixels)
    assert split.sun_direction is not None and split.more_suns == ()


def test_a_rotation_turns_the_sun_with_the_map():
    pixels, _ = sky_with_sun([1.0, 0.0, 0.3])
    quarter = np.array([[0, -1.0, 0], [1.0, 0, 0], [0, 0, 1.0]])  # +90 degrees about Z
    split = split_environment(pixels, to_world=quarter)
    expected = quarter @ (np.array([1.0, 0, 0.3]) / np.linalg.norm([1.0, 0, 0.3]))
    assert split.sun_direction @ expected > np.cos(np.radians(1.0))


def test_an_overcast_map_has_no_sun_and_keeps_its_gradient_in_the_sky():
    dirs, _ = equirect_directions(H, W)
    pixels = (0.2 + 0.8 * np.clip(dirs[..., 2], 0, None))[..., None].repeat(3, axis=-1)  # brighter overhead
    split = split_environment(pixels)
    assert split.sun_direction is None and not split.sun_irradiance.any()
    world = World(color=split.sky, sky_sh=split.sky_sh)
    zenith, horizon, nadir = world.radiance(np.array([[0, 0, 1.0], [1.0, 0, 0], [0, 0, -1.0]]))[:, 0]
    assert zenith > horizon > 0.1 and nadir < horizon + 0.05
    # The uniform colour is what a surface facing up receives, / pi.
    up = np.clip(dirs[..., 2], 0, None) * np.cos(np.arcsin(dirs[..., 2]))
    np.testing.assert_allclose(split.sky[0], (pixels[..., 0] * up).sum() / up.sum(), rtol=1e-3)


def test_non_finite_pixels_do_not_reach_the_lamp_or_the_sky():
    pixels, _ = sky_with_sun([0, 0.5, 0.8])
    pixels[10, 20] = np.nan
    pixels[11, 20] = np.inf
    split = split_environment(pixels)
    assert np.isfinite(split.sun_irradiance).all() and np.isfinite(split.sky).all() and np.isfinite(split.sky_sh).all()


def test_the_camera_sees_the_whole_map_its_sun_included():
    """What the camera sees of an HDRI world (`EnvironmentSplit.background`, `BackgroundMap`): the
    map itself, sun disc and all, read along each direction as the sky map is (the light's split
    fills the disc and keeps a coarse copy; the background is neither)."""
    from hybridgi_core.environment import BackgroundMap, SkyMap

    direction = np.array([0.3, -0.5, 0.6])
    pixels, disc = sky_with_sun(direction, sun_radiance=900.0)
    split = split_environment(pixels)
    assert split.background.dtype == np.float16 and split.background.shape == (H, W, 3)
    np.testing.assert_allclose(split.background.astype(np.float64), pixels, rtol=1e-3)
    quarter = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])  # texture -> world
    seen = BackgroundMap(split.background, strength=0.5, to_world=quarter)
    dirs = np.random.default_rng(1).normal(size=(500, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    want = SkyMap(pixels.astype(np.float32), quarter).radiance(dirs) * 0.5
    np.testing.assert_allclose(seen.radiance(dirs), want, rtol=2e-3, atol=1e-4)
    d = quarter @ (direction / np.linalg.norm(direction))  # the sun, in world directions
    assert seen.radiance(d[None])[0, 0] > 0.5 * 900.0 * 0.5  # the disc itself, not the filled sky


def test_a_wide_background_map_is_halved_until_it_fits_and_stays_finite():
    from hybridgi_core.environment import background_pixels

    rng = np.random.default_rng(2)
    pixels = rng.uniform(0.0, 4.0, (64, 256, 3))
    pixels[3, 5] = (np.nan, np.inf, -2.0)
    pixels[7, 9] = 1e7  # its 4 x 4 block's mean beyond half-float range: clamped, not infinite
    out = background_pixels(pixels, max_width=64)
    assert out.shape == (16, 64, 3) and out.dtype == np.float16 and np.isfinite(out).all()
    clean = np.nan_to_num(pixels, nan=0.0, posinf=0.0, neginf=0.0).clip(min=0.0)
    means = clean.reshape(16, 4, 64, 4, 3).mean(axis=(1, 3))
    keep = np.ones((16, 64), bool)
    keep[1, 2] = False  # that block, clamped at 65504
    np.testing.assert_allclose(out.astype(np.float64)[keep], means[keep], rtol=2e-3)
    assert out[1, 2, 0] == np.float16(np.finfo(np.float16).max)
    assert background_pixels(pixels, max_width=256).shape == (64, 256, 3)  # small enough: as it is


def test_a_large_map_splits_on_a_filtered_copy_with_its_sun_at_full_resolution():
    """A map wider than SPLIT_WIDTH (a 4K HDRI): the sun is measured at the map's own resolution
    (in the rows it can reach), the sky it leaves from a box-filtered copy. Both as an exact
    full-resolution split gives them: the sun's direction, irradiance and size, the sky's SH, its
    uniform mean, and no sun left in the map the rays read."""
    from hybridgi_core.environment import SPLIT_WIDTH

    h, w = 2 * SPLIT_WIDTH // 2, 2 * SPLIT_WIDTH  # one halving
    dirs, solid = equirect_directions(h, w)
    direction = np.array([-0.4, 0.7, 0.35]) / np.linalg.norm([-0.4, 0.7, 0.35])
    sky = 0.3 + 0.2 * np.clip(dirs[..., 2:3], 0.0, None) * np.array([0.8, 1.0, 1.3])  # a gradient
    disc = dirs @ direction > np.cos(np.radians(0.6))
    pixels = np.where(disc[..., None], 3000.0, sky).astype(np.float32)
    quarter = np.array([[0, -1.0, 0], [1.0, 0, 0], [0, 0, 1.0]])
    split = split_environment(pixels, to_world=quarter)
    weight = np.broadcast_to(solid[:, None], disc.shape)
    d_world = quarter @ direction
    assert np.degrees(np.arccos(np.clip(split.sun_direction @ d_world, -1, 1))) < 0.05
    expected = 3000.0 * float((weight[disc] * np.clip(dirs[disc] @ direction, 0, None)).sum())
    np.testing.assert_allclose(split.sun_irradiance, expected, rtol=0.01)
    np.testing.assert_allclose(split.sun_angle, 2 * np.sqrt(weight[disc].sum() / np.pi), rtol=1e-6)
    # The sky: the gradient, as the full-resolution projections of the map without its sun give it.
    world_dirs = dirs @ quarter.T
    from hybridgi_core.sh import basis

    want_sh = basis(world_dirs.reshape(-1, 3), 2).T @ (sky.reshape(-1, 3) * weight.reshape(-1, 1))
    np.testing.assert_allclose(split.sky_sh, want_sh, rtol=2e-3, atol=2e-3 * np.abs(want_sh).max())
    assert split.sky_map.max() < 0.6  # the sun is the lamp's, none of it left where rays escape
    assert split.background.shape == (h, w, 3) and split.background.max() > 2000  # the camera sees it


def test_a_split_kept_as_arrays_reads_back_the_same():
    """`split_arrays` / `split_from_arrays` (the add-on keeps splits on disk with them): every
    field back as it was, a map without a sun and one with more suns alike."""
    import io

    from hybridgi_core.environment import split_arrays, split_from_arrays

    boxes, _ = sky_with_sun((0.3, 0.2, 0.9))
    extra, _ = sky_with_sun((-0.7, 0.4, 0.3), sun_radiance=900.0, sun_radius=np.radians(4.0))
    for pixels, to_world in ((boxes, None), (np.maximum(boxes, extra), np.eye(3)), (np.full((H, W, 3), 0.3), None)):
        split = split_environment(pixels, to_world)
        buffer = io.BytesIO()
        np.savez(buffer, **split_arrays(split))
        buffer.seek(0)
        back = split_from_arrays(np.load(buffer, allow_pickle=False))
        for name in ("sun_direction", "sun_irradiance", "sky", "sky_sh", "sky_map", "to_world", "background"):
            mine, theirs = getattr(split, name), getattr(back, name)
            assert (mine is None) == (theirs is None), name
            if mine is not None:
                np.testing.assert_array_equal(np.asarray(theirs), np.asarray(mine))
                assert np.asarray(theirs).dtype == np.asarray(mine).dtype, name
        assert back.sun_angle == split.sun_angle and len(back.more_suns) == len(split.more_suns)
        for (d0, e0, a0), (d1, e1, a1) in zip(split.more_suns, back.more_suns, strict=True):
            np.testing.assert_array_equal(d1, d0)
            np.testing.assert_array_equal(e1, e0)
            assert a1 == a0

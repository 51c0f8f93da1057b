"""The pixel filter's sample pattern and accumulation (`hybridgi_core/raster/subpixel.py`): bpy-free."""

from __future__ import annotations

import functools

import numpy as np
import pytest

from hybridgi_core.raster.subpixel import (
    FilmAccumulator,
    blackman_harris,
    blackman_harris_cdf,
    filter_image,
    filter_offsets,
    filter_support,
    jittered_projection,
    reconstruction_taps,
    subframe_rays,
    subpixel_offsets,
    surface_edges,
)


def test_the_cdf_is_the_integral_of_cycles_window():
    # Cycles' filter_func_blackman_harris(v, width) with its table's width *= 2, integrated numerically.
    size = 1.5
    v = np.linspace(-size, size, 200001)
    width = 2.0 * size
    x = 2.0 * np.pi * (v / width + 0.5)
    w = 0.35875 - 0.48829 * np.cos(x) + 0.14128 * np.cos(2 * x) - 0.01168 * np.cos(3 * x)
    assert np.allclose(blackman_harris(v, size), w)
    integral = np.concatenate([[0.0], np.cumsum((w[1:] + w[:-1]) * 0.5 * np.diff(v))])
    assert np.abs(blackman_harris_cdf(v, size) - integral / integral[-1]).max() < 1e-6
    assert blackman_harris(np.array([-1.6, 1.6]), size).tolist() == [0.0, 0.0]


@pytest.mark.parametrize("size", [0.5, 1.5, 3.0])
def test_offsets_are_distributed_as_the_filter(size):
    """Uniform draws through the inverse CDF: their histogram is the Blackman-Harris window's mass
    per bin (chi-square small), inside [-size, size] and symmetric."""
    rng = np.random.default_rng(1)
    n = 200_000
    d = filter_offsets(rng.random(n), size)
    assert np.abs(d).max() <= size
    edges = np.linspace(-size, size, 31)
    counts = np.histogram(d, edges)[0]
    expected = n * np.diff(blackman_harris_cdf(edges, size))
    keep = expected > 20
    chi2 = float(((counts[keep] - expected[keep]) ** 2 / expected[keep]).sum())
    assert chi2 < 2.0 * keep.sum(), chi2
    # The second moment matches the window's (numerically integrated).
    v = np.linspace(-size, size, 100001)
    w = blackman_harris(v, size)
    var = float((w * v * v).sum() / w.sum())
    assert abs(float((d * d).mean()) - var) < 0.02 * var


@pytest.mark.parametrize("kind, width, sigma", [("GAUSSIAN", 1.5, 0.375), ("BOX", 1.0, None)])
def test_cycles_other_filters_are_sampled_too(kind, width, sigma):
    """Gaussian: Cycles' exp(-2 (6 v / 3w)^2) is sigma = w / 4, cut at 1.5 w; box: uniform over w."""
    d = filter_offsets(np.random.default_rng(2).random(100_000), width, kind)
    reach = filter_support(kind, width)
    assert np.abs(d).max() <= reach
    if sigma is None:
        assert np.histogram(d, np.linspace(-reach, reach, 11))[0].std() < 0.05 * 10_000
    else:
        assert float(d.std()) == pytest.approx(sigma, rel=0.02)
    with pytest.raises(ValueError):
        filter_offsets(0.5, 1.0, "MITCHELL")


def test_the_pattern_is_stratified_through_the_filter():
    """K offsets: one per quantile stratum of the filter on each axis (Hammersley), deterministic,
    mean zero; K = 1 is the pixel centre; a larger Filter Size spreads them proportionally."""
    assert subpixel_offsets(1, 1.5).tolist() == [[0.0, 0.0]]
    for k in (4, 8, 16):
        off = subpixel_offsets(k, 1.5)
        assert off.shape == (k, 2)
        for axis in (0, 1):
            strata = np.floor(blackman_harris_cdf(off[:, axis], 1.5) * k + 1e-9).astype(int)
            assert sorted(strata.tolist()) == list(range(k))
        assert np.abs(off.mean(axis=0)).max() < 0.1
        assert np.array_equal(off, subpixel_offsets(k, 1.5))
    assert np.allclose(subpixel_offsets(8, 3.0), 2.0 * subpixel_offsets(8, 1.5))
    assert not subpixel_offsets(4, 0.0).any()
    with pytest.raises(ValueError):
        subpixel_offsets(0, 1.5)


@pytest.mark.parametrize("ortho", [False, True])
def test_the_jittered_projection_moves_the_image_by_the_offset(ortho):
    w, h = 64, 32
    if ortho:
        proj = np.diag([0.5, 1.0, -0.1, 1.0]).astype(np.float32)
    else:
        proj = np.array([[1.2, 0, 0, 0], [0, 2.4, 0, 0], [0, 0, -1.0, -0.2], [0, 0, -1.0, 0]], np.float32)
    p = np.array([0.3, -0.2, -4.0, 1.0])

    def pixel(m):
        c = m.astype(np.float64) @ p
        return (c[0] / c[3] * 0.5 + 0.5) * w, (c[1] / c[3] * 0.5 + 0.5) * h

    x0, y0 = pixel(proj)
    x1, y1 = pixel(jittered_projection(proj, (0.25, -0.5), w, h))
    # Sampling at centre + d: what lay at d lands on the centre, so the image moves by -d.
    assert x1 - x0 == pytest.approx(-0.25, abs=1e-4)
    assert y1 - y0 == pytest.approx(0.5, abs=1e-4)


@pytest.mark.parametrize("ortho", [False, True])
def test_subframe_rays_pass_where_each_subframe_samples_the_pixel(ortho):
    """The ray `subframe_rays` gives pixel p and offset o starts on the near plane, and every
    point along it lands on p's centre under the subframe's projection (`jittered_projection`):
    what that subframe's raster sees at p is what the ray meets first."""
    w, h = 64, 48
    if ortho:
        proj = np.diag([0.25, 1.0 / 3.0, -0.1, 1.0])
    else:
        f = 1.0 / np.tan(0.4)
        proj = np.array([[f * h / w, 0, 0, 0], [0, f, 0, 0], [0, 0, -1.002, -0.2002], [0, 0, -1.0, 0]])
    view = np.eye(4)
    view[:3, :3] = np.array([[1, 0, 0], [0, 0.8, -0.6], [0, 0.6, 0.8]])  # tilted about x
    view[:3, 3] = (0.3, -0.2, -1.0)
    pix = np.array([5 + 7 * w, 30 + 20 * w, 63 + 47 * w])
    offsets = np.array([[0.3, -0.2], [-0.45, 0.4], [0.0, 0.0]])
    origins, dirs = subframe_rays(pix, w, h, view, proj, offsets)
    assert origins.shape == dirs.shape == (3, 3, 3) and dirs.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=2), 1.0, atol=1e-6)
    for k, offset in enumerate(offsets):
        m = jittered_projection(proj, offset, w, h).astype(np.float64) @ view
        for t in (0.0, 2.0, 7.5):
            clip = np.c_[origins[k].astype(np.float64) + t * dirs[k], np.ones(3)] @ m.T
            xy = (clip[:, :2] / clip[:, 3:] * 0.5 + 0.5) * (w, h) - 0.5
            np.testing.assert_allclose(xy, np.c_[pix % w, pix // w], atol=2e-3)
            if t == 0.0:
                np.testing.assert_allclose(clip[:, 2] / clip[:, 3], -1.0, atol=1e-4)  # the near plane


def test_surface_edges_mark_both_sides_of_a_crease_a_step_and_a_silhouette():
    """A floor (z = 0, normal +z) meeting a wall (x = 5, normal -x) between columns 4 and 5, a
    step up at row 3 of the floor, the background at column 7: the pixels either side of each
    are edges, the flat floor and wall inside are not; a gently curved surface is none."""
    h, w = 6, 8
    pos = np.zeros((h, w, 4), np.float32)
    nrm = np.zeros((h, w, 4), np.float32)
    xs, ys = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    floor = xs <= 4
    pos[..., 0], pos[..., 1], pos[..., 3] = xs, ys, 1.0
    pos[..., 2] = np.where(floor, np.where(ys >= 3, 0.5, 0.0), xs - 4)
    nrm[..., 2] = np.where(floor, 1.0, 0.0)
    nrm[..., 0] = np.where(floor, 0.0, -1.0)
    pos[:, 7, 3] = 0.0  # background
    depth = np.full((h, w), 10.0, np.float32)
    edge = surface_edges(pos, nrm, depth)
    assert edge[:, 4].all() and edge[:, 5].all()  # the crease
    assert edge[2, :4].all() and edge[3, :4].all()  # the step (0.5 at depth 10: off the plane)
    assert edge[:, 6].all() and edge[:, 7].all()  # the silhouette, both sides
    assert not edge[[0, 1, 4, 5], :4].any()
    # A sphere-like bulge: normals turn by 2 degrees a pixel, points stay on each other's planes.
    angle = np.radians(2.0) * xs
    curved_pos = np.stack([np.sin(angle) * 20, ys, 20 - np.cos(angle) * 20, np.ones_like(xs)], axis=-1)
    curved_nrm = np.stack([-np.sin(angle), np.zeros_like(xs), np.cos(angle), np.zeros_like(xs)], axis=-1)
    assert not surface_edges(curved_pos.astype(np.float32), curved_nrm.astype(np.float32), depth * 100).any()


def test_the_film_averages_passes_and_keeps_one_depth():
    acc = FilmAccumulator()
    geo = np.ones((1, 2, 4), np.float32) * np.array([0.8, 0.4, 0.2, 1.0], np.float32)
    bg = np.array([[[0.1, 0.1, 0.1, 0.0], [0.8, 0.4, 0.2, 1.0]]], np.float32)
    ones = np.ones((1, 2, 4), np.float32)
    for combined, depth in ((geo, np.full((1, 2, 1), 2.0, np.float32)),
                            (bg, np.array([[[1e10], [2.0]]], np.float32))):
        acc.add({"combined": combined, "diffuse_direct": ones, "diffuse_indirect": ones,
                 "diffuse_color": combined, "ao": ones[..., :1], "normal": ones[..., :3], "depth": depth})
    acc.set_depth(np.full((1, 2, 1), 2.0, np.float32))
    c = acc.read("combined")
    # Half the samples saw the background (world 0.1, alpha 0): an edge pixel mixes both.
    assert np.allclose(c[0, 0], [0.45, 0.25, 0.15, 0.5])
    assert np.allclose(acc.read("combined_premultiplied")[0, 0], [0.4, 0.2, 0.1, 0.5])
    assert np.allclose(acc.read("normal")[0, 0], 0.5) and np.allclose(acc.read("normal")[0, 1], 1.0)
    assert acc.read("depth").tolist() == [[[2.0], [2.0]]]
    with pytest.raises(KeyError):
        FilmAccumulator().read("combined")


def test_refracting_glass_takes_its_share_of_a_pixel_over_the_raster():
    """`set_refraction`: a pixel half covered by glass is half the raster's see-through light and
    half the glass paths'; its Diffuse and Glossy Color keep the half that missed, the light
    passes divided by them are unchanged, and a transparent film's Combined takes the glass as
    opaque (its alpha grows by the glass's share)."""
    acc = FilmAccumulator()
    bg = np.array([[[0.1, 0.1, 0.1, 0.0], [0.8, 0.4, 0.2, 1.0]]], np.float32)
    ones = np.ones((1, 2, 4), np.float32)
    acc.add({"combined": bg, "diffuse_direct": ones, "diffuse_indirect": ones, "diffuse_color": bg,
             "ao": ones[..., :1], "normal": ones[..., :3], "depth": np.full((1, 2, 1), 2.0, np.float32)})
    acc.set_depth(np.full((1, 2, 1), 2.0, np.float32))
    acc.set_glossy(None, None, 1, 2)
    before = {name: acc.read(name).copy() for name in ("diffuse_color", "diffuse_direct", "combined_premultiplied")}
    acc.set_refraction(np.array([[0.0, 0.5]], np.float32), np.full((1, 2, 3), 2.0, np.float32))
    np.testing.assert_allclose(acc.read("combined")[0, 0], [0.1, 0.1, 0.1, 0.0])  # no glass: as it was
    np.testing.assert_allclose(acc.read("combined")[0, 1], [1.4, 1.2, 1.1, 1.0])
    np.testing.assert_allclose(acc.read("diffuse_color")[0, 1, :3], 0.5 * before["diffuse_color"][0, 1, :3])
    np.testing.assert_array_equal(acc.read("diffuse_direct"), before["diffuse_direct"])
    np.testing.assert_allclose(acc.read("combined_premultiplied")[0, 0], before["combined_premultiplied"][0, 0])
    np.testing.assert_allclose(acc.read("combined_premultiplied")[0, 1, 3], 1.0)
    # A pixel wholly behind glass: no sample saw a diffuse colour, so its light passes read 0 as
    # Cycles' do (they had kept the see-through surface's light).
    acc.set_refraction(np.array([[0.0, 1.0]], np.float32), np.full((1, 2, 3), 2.0, np.float32))
    np.testing.assert_array_equal(acc.read("diffuse_color")[0, 1, :3], 0.0)
    for name in ("diffuse_direct", "diffuse_indirect"):
        np.testing.assert_array_equal(acc.read(name)[0, 1, :3], 0.0)
        np.testing.assert_array_equal(acc.read(name)[0, 0], before["diffuse_direct"][0, 0])


def test_one_sample_per_pixel_takes_the_filters_share_of_each_neighbour():
    """The taps of a one-subframe frame are Cycles' filter integrated over each pixel's footprint
    (here by quadrature of the window itself), K subframes keep 1 / K of the neighbours' share,
    and a box of one pixel (or a filter width 0) leaves the pixels alone."""
    v = np.linspace(-1.5, 1.5, 300001)
    w = blackman_harris(v, 1.5)
    side = w[(v >= 0.5)].sum() / w.sum()
    one = reconstruction_taps(1, 1.5)
    assert one.shape == (3,) and one.sum() == pytest.approx(1.0)
    assert one[0] == pytest.approx(side, abs=1e-4) and one[2] == pytest.approx(side, abs=1e-4)
    assert 0.11 < side < 0.13
    four = reconstruction_taps(4, 1.5)
    assert four[0] == pytest.approx(side / 4, abs=1e-4) and four.sum() == pytest.approx(1.0)
    assert reconstruction_taps(1, 1.0, "BOX").tolist() == [1.0]
    assert reconstruction_taps(1, 0.0).tolist() == [1.0]
    wide = reconstruction_taps(1, 3.0)  # a 3 px Blackman-Harris reaches two pixels and more
    assert wide.size == 7 and wide[3] < 0.5 and wide.sum() == pytest.approx(1.0)


def test_the_film_filters_its_sums_as_cycles_filters_its_samples():
    """A lone bright pixel spreads by the taps along both axes, a flat image stays flat, Depth
    stays a point sample, and a colour-divided pass is its filtered light over its filtered colour."""
    acc = FilmAccumulator()
    taps = reconstruction_taps(1, 1.5)
    acc.set_filter(taps)
    combined = np.zeros((5, 5, 4), np.float32)
    combined[2, 2] = 1.0
    colour = np.full((5, 5, 4), 0.5, np.float32)
    colour[:, :2, :3] = 0.1  # a dark left side: Cycles weighs each sample's light by its colour
    light = np.ones((5, 5, 4), np.float32)
    light[:, :2, :3] = 4.0
    acc.add({"combined": combined, "diffuse_direct": light, "diffuse_indirect": np.ones_like(light),
             "diffuse_color": colour, "ao": np.ones((5, 5, 1), np.float32), "normal": np.ones((5, 5, 3), np.float32),
             "depth": np.full((5, 5, 1), 2.0, np.float32)})
    acc.set_depth(np.arange(25, dtype=np.float32).reshape(5, 5, 1))
    np.testing.assert_allclose(acc.read("combined")[..., 0], np.outer(np.pad(taps, 1), np.pad(taps, 1)), atol=1e-6)
    np.testing.assert_allclose(acc.read("ao"), 1.0, atol=1e-6)
    np.testing.assert_allclose(acc.read("diffuse_indirect")[..., :3], 1.0, atol=1e-6)
    assert acc.read("depth")[..., 0].tolist() == np.arange(25).reshape(5, 5).tolist()
    # Column 2 (bright side, next to the dark one): light x colour filtered over colour filtered.
    mixed = (taps[0] * 0.1 * 4.0 + (taps[1] + taps[2]) * 0.5 * 1.0) / (taps[0] * 0.1 + (taps[1] + taps[2]) * 0.5)
    assert acc.read("diffuse_direct")[2, 2, 0] == pytest.approx(mixed, rel=1e-5)
    np.testing.assert_array_equal(filter_image(combined, np.ones(1)), combined)


def test_diffuse_light_is_divided_by_the_accumulated_colour_as_cycles_does():
    """An edge pixel half red wall (E = 2), half white floor (E = 4): Cycles' Diffuse Direct is
    sum(colour x E) / sum(colour) per channel, so Combined = Direct x Color holds for the filtered
    pixel; a channel without colour takes the other channels' ratio (safe_divide_even_color)."""
    acc = FilmAccumulator()
    red, white = np.array([1.0, 0.0, 0.0, 1.0]), np.array([1.0, 1.0, 1.0, 1.0])
    for color, e in ((red, 2.0), (white, 4.0)):
        c = np.array(color, np.float32).reshape(1, 1, 4)
        light = np.full((1, 1, 4), e, np.float32)
        light[..., 3] = 1.0
        acc.add({"combined": c * e, "diffuse_direct": light, "diffuse_indirect": np.zeros_like(light),
                 "diffuse_color": c, "ao": np.ones((1, 1, 1), np.float32), "normal": np.ones((1, 1, 3), np.float32),
                 "depth": np.ones((1, 1, 1), np.float32)})
    direct, color, combined = acc.read("diffuse_direct")[0, 0], acc.read("diffuse_color")[0, 0], acc.read("combined")[0, 0]
    assert np.allclose(direct[:3], [3.0, 4.0, 4.0])
    assert np.allclose(direct[:3] * color[:3], combined[:3])
    black = FilmAccumulator()
    zero = np.zeros((1, 1, 4), np.float32)
    black.add({"combined": zero, "diffuse_direct": zero + 1, "diffuse_indirect": zero, "diffuse_color": zero,
               "ao": zero[..., :1], "normal": zero[..., :3], "depth": zero[..., :1]})
    assert black.read("diffuse_direct")[0, 0, :3].tolist() == [0.0, 0.0, 0.0]


def test_a_subframe_traces_shadow_rays_only_where_it_sees_another_surface():
    """Same plane, slightly shifted point: the centre's light (its full sample count) is reused;
    a point on a surface behind (silhouette) or turned away (crease) is traced with the
    subframe's share of the samples; background stays 0."""
    from hybridgi_core.raster.subpixel import subframe_direct

    class System:
        def __init__(self):
            self.calls = []

        def direct(self, points, normals, frame, samples):
            self.calls.append((points.shape[0], frame, samples))
            return np.full((points.shape[0], 3), 7.0, np.float32)

    centre, position0, normal0 = _three_plane_pixels_and_sky()
    position = position0.copy()
    position[0, 0, 0] += 0.01  # same plane, a sub-pixel step along it
    position[0, 1, 2] = -7.0  # a surface 2 m behind
    normal = normal0.copy()
    normal[0, 2] = (1.0, 0.0, 0.0, 0.0)  # the other side of a crease
    system = System()
    got = subframe_direct(system, centre, position, normal, seed_frame=3, samples=4)
    assert got[0].tolist() == [1.0, 2.0, 3.0, 1.0]
    assert got[1, :3].tolist() == [7.0] * 3 and got[2, :3].tolist() == [7.0] * 3
    assert not got[3].any()
    assert system.calls == [(2, 3, 4)]



def test_a_subframe_of_many_lamps_traces_them_in_groups_that_sum_to_all_of_them():
    """Over LAMP_GROUP lamps a subframe's fresh pixels take their lamps in groups (a job each on
    the pool, lamp group g0 seeded seed_frame + g0 x LAMP_SEED_STRIDE): the groups' sum is every
    lamp's light, where one job of every lamp ran on one core."""
    from types import SimpleNamespace

    from hybridgi_core.penumbra import LAMP_GROUP, LAMP_SEED_STRIDE
    from hybridgi_core.raster.subpixel import subframe_direct

    count = LAMP_GROUP + 4

    class System:
        scene = SimpleNamespace(lights=[object()] * count)

        def __init__(self):
            self.calls = []

        def direct(self, points, normals, frame, samples, lights=None):
            lights = list(range(count)) if lights is None else lights
            self.calls.append((points.shape[0], frame, tuple(lights)))
            return np.full((points.shape[0], 3), float(sum(j + 1 for j in lights)), np.float32)

    centre, position0, normal0 = _three_plane_pixels_and_sky()
    position = position0.copy()
    position[0, 1, 2] = -7.0  # a surface 2 m behind: fresh
    system = System()
    got = subframe_direct(system, centre, position, normal0.copy(), seed_frame=3, samples=4)
    every = float(sum(range(1, count + 1)))
    assert got[1, :3].tolist() == [every] * 3  # the groups' sum
    assert got[0].tolist() == [1.0, 2.0, 3.0, 1.0] and not got[3].any()
    assert sorted(system.calls) == [(1, 3, tuple(range(LAMP_GROUP))),
                                    (1, 3 + LAMP_GROUP * LAMP_SEED_STRIDE, tuple(range(LAMP_GROUP, count)))]


def _three_plane_pixels_and_sky():
    """(CentreSample, position, normal read-backs) of a 1 x 4 centre raster: three pixels of the
    plane z = -5 facing the camera, their direct light (1, 2, 3), and the background."""
    from hybridgi_core.raster.subpixel import CentreSample

    h, w = 1, 4
    position0 = np.array([[[0, 0, -5, 1], [1, 0, -5, 1], [2, 0, -5, 1], [0, 0, 0, 0]]], np.float32)
    normal0 = np.tile(np.array([0, 0, 1, 0], np.float32), (h, w, 1))
    depth0 = np.array([[[5.0], [5.0], [5.0], [1e10]]], np.float32)
    direct0 = np.tile(np.array([1.0, 2.0, 3.0, 1.0], np.float32), (h * w, 1))
    return CentreSample.from_gbuffer(direct0, position0, normal0, depth0), position0, normal0


def _plane_row(w):
    """(position, normal, depth) read-backs of a 1 x w centre raster of the plane z = -5 facing
    the camera, one metre a pixel."""
    position = np.zeros((1, w, 4), np.float32)
    position[0, :, 0] = np.arange(w)
    position[0, :, 2] = -5.0
    position[..., 3] = 1.0
    return position, np.tile(np.array([0, 0, 1, 0], np.float32), (1, w, 1)), np.full((1, w, 1), 5.0, np.float32)

def test_a_shadow_boundary_on_one_surface_is_traced_again_in_every_subframe():
    """A sun's shadow edge across one plane: the pixels on both sides of the step are light edges
    and get their own shadow rays in a subframe; pixels away from it reuse the centre's light."""
    from hybridgi_core.raster.subpixel import CentreSample, light_edges, subframe_direct

    class System:
        def direct(self, points, normals, frame, samples):
            return np.full((points.shape[0], 3), 0.5, np.float32)

    h, w = 1, 6
    position0, normal0, depth0 = _plane_row(w)
    lit = np.array([1.0, 1.0, 1.0, 0.0, 0.0, 0.0], np.float32)  # the shadow starts at pixel 3
    direct0 = np.zeros((h * w, 4), np.float32)
    direct0[:, :3] = lit[:, None]
    assert light_edges(lit.reshape(h, w)).ravel().tolist() == [False, False, True, True, False, False]
    centre = CentreSample.from_gbuffer(direct0, position0, normal0, depth0)
    got = subframe_direct(System(), centre, position0.copy(), normal0.copy(), seed_frame=1, samples=4)
    assert got[:, 0].tolist() == [1.0, 1.0, 0.5, 0.5, 0.0, 0.0]


def _row_of_surfaces(lum, depth_of, normals=None):
    """A 1 x n centre raster on the plane z = -depth (or the given depths), all facing the camera,
    with indirect light of luminance `lum` per pixel."""
    from hybridgi_core.raster.subpixel import CentreSample

    n = len(lum)
    position = np.zeros((1, n, 4), np.float32)
    position[0, :, 0] = np.arange(n) * 0.01
    position[0, :, 2] = -np.asarray(depth_of, np.float32)
    position[..., 3] = 1.0
    normal = np.tile(np.array([0, 0, 1, 0], np.float32), (1, n, 1)) if normals is None else normals
    depth = np.asarray(depth_of, np.float32).reshape(1, n, 1)
    indirect = np.zeros((n, 4), np.float32)
    indirect[:, :3] = np.asarray(lum, np.float32)[:, None]
    return CentreSample.from_gbuffer(np.zeros((n, 4), np.float32), position, normal, depth), indirect


def test_gi_edges_mark_neighbours_on_other_surfaces_of_far_other_bounce_light():
    """`gi_edges`: a bar (pixel 2, 1 m in front of the ground) whose bounce light is 20 x the
    ground's marks itself and both neighbours; a bar of similar light does not, nor does a
    10 x step of light on one surface (a shadow's edge: `light_edges` handles those)."""
    from hybridgi_core.raster.subpixel import gi_edges

    centre, indirect = _row_of_surfaces([1, 1, 20, 1, 1, 1], [5, 5, 4, 5, 5, 5])
    assert gi_edges(centre, indirect, 1, 6).tolist() == [False, True, True, True, False, False]
    centre, indirect = _row_of_surfaces([1, 1, 1.5, 1, 1, 1], [5, 5, 4, 5, 5, 5])
    assert not gi_edges(centre, indirect, 1, 6).any()
    centre, indirect = _row_of_surfaces([1, 1, 1, 20, 20, 20], [5] * 6)
    assert not gi_edges(centre, indirect, 1, 6).any()


def test_a_frame_takes_extra_subframes_only_when_gi_edges_are_a_share_of_the_image():
    from hybridgi_core.raster.subpixel import EXTRA_MIN_SHARE, worth_extra

    edges = np.zeros(10000, bool)
    assert not worth_extra(edges)
    edges[: int(np.ceil(EXTRA_MIN_SHARE * 10000)) - 1] = True  # the odd silhouette of a bundled scene
    assert not worth_extra(edges)
    edges[: int(np.ceil(EXTRA_MIN_SHARE * 10000))] = True
    assert worth_extra(edges)


def test_a_normal_maps_bends_are_one_surface_to_gi_edges_and_subframes():
    """Ridges of a normal map: shading normals bent +-50 degrees pixel by pixel over one flat
    plane, whose indirect light differs 12 x between the two flanks. Compared by their shading
    normals every pixel is a GI edge (the ridged planes' frame took 32 subframes instead of 8);
    by the smooth surface (the G-buffer's `surface`, `CentreSample.surface`) none is. A
    subframe's pixel still counts as the centre's surface, to reuse its light, only where the
    bend agrees too."""
    from hybridgi_core.raster.subpixel import CentreSample, gi_edges, subframe_surfaces

    n = 8
    bend = np.radians(50.0)
    normal = np.zeros((1, n, 4), np.float32)
    normal[0, :, 0] = np.where(np.arange(n) % 2 == 0, np.sin(bend), -np.sin(bend))
    normal[0, :, 2] = np.cos(bend)
    flat = np.tile(np.array([0, 0, 1, 1], np.float32), (1, n, 1))
    position = np.zeros((1, n, 4), np.float32)
    position[0, :, 0] = np.arange(n) * 0.01
    position[0, :, 2] = -5.0
    position[..., 3] = 1.0
    depth = np.full((1, n, 1), 5.0, np.float32)
    indirect = np.zeros((n, 4), np.float32)
    indirect[:, :3] = np.where(np.arange(n) % 2 == 0, 12.0, 1.0)[:, None]
    direct = np.zeros((n, 4), np.float32)
    by_bend = CentreSample.from_gbuffer(direct, position, normal, depth)
    assert gi_edges(by_bend, indirect, 1, n).all()
    by_surface = CentreSample.from_gbuffer(direct, position, normal, depth, surface=flat)
    assert not gi_edges(by_surface, indirect, 1, n).any()
    # A subframe: the same bends except pixel 3's, on the same plane.
    turned = normal.copy()
    turned[0, 3, 0] *= -1.0
    hit, same = subframe_surfaces(by_surface, position, turned, flat)
    assert hit.all() and same.tolist() == [True, True, True, False, True, True, True, True]


def test_a_step_of_faint_light_is_no_light_edge():
    """`light_edges`' floor: a relative step far below the frame's light (a wall's grazing sliver
    of a high sun, noisy from pixel to pixel) is not traced again in the subframes; the same step
    between lit pixels is. `CentreSample.from_gbuffer` sets the floor from the frame's light."""
    from hybridgi_core.raster.subpixel import LIGHT_EDGE_FLOOR, CentreSample, edge_floor, light_edges

    lit = np.array([[30.0, 30.0, 30.0, 0.03, 0.02, 0.03, 0.02, 30.0, 15.0]], np.float32)
    floor = edge_floor(lit)
    assert np.isclose(floor, LIGHT_EDGE_FLOOR * lit[lit > 0].mean())
    assert light_edges(lit).ravel().tolist() == [False, False, True, True, True, True, True, True, True]
    # With the floor: the faint pixels' steps among themselves go; the steps to and from the lit
    # pixels (30 -> 0.03, 0.02 -> 30) and between lit ones (30 -> 15) stay.
    assert light_edges(lit, floor=floor).ravel().tolist() == [False, False, True, True, False, False, True,
                                                              True, True]
    position, normal, depth = _plane_row(lit.shape[1])
    direct = np.zeros((lit.size, 4), np.float32)
    direct[:, :3] = lit.reshape(-1, 1)
    centre = CentreSample.from_gbuffer(direct, position, normal, depth)
    assert centre.light_edge.tolist() == light_edges(lit, floor=floor).ravel().tolist()


def test_a_light_edge_is_traced_again_only_for_the_lamp_that_makes_it():
    """Two lamps over one plane, a shadow edge of lamp 0 only: its light-edge pixels take lamp 0's
    light from the subframe's own rays and keep the centre's share of lamp 1; pixels away from
    the edge keep both; a weak lamp's step too small against the total light is no edge."""
    from hybridgi_core.raster.subpixel import CentreSample, lamp_edges, subframe_direct

    class System:
        def __init__(self):
            self.calls = []

        def direct(self, points, normals, frame, samples, lights=None):
            self.calls.append((points.shape[0], lights))
            return np.full((points.shape[0], 3), 0.5, np.float32)

    h, w = 1, 6
    position0, normal0, depth0 = _plane_row(w)
    shares = np.zeros((h * w, 3, 3), np.float32)
    shares[:, 0] = np.array([1.0, 1.0, 1.0, 0.0, 0.0, 0.0])[:, None]  # lamp 0's shadow starts at pixel 3
    shares[:, 1] = 2.0  # lamp 1 lights the whole plane
    shares[:, 2] = np.array([0.1, 0.1, 0.1, 0.1, 0.0, 0.0])[:, None]  # lamp 2: 0.1 of 3, no edge
    direct0 = np.zeros((h * w, 4), np.float32)
    direct0[:, :3] = shares.sum(axis=1)
    edges = lamp_edges(shares, direct0[:, :3].sum(axis=1).reshape(h, w))
    assert edges[:, 0].tolist() == [False, False, True, True, False, False]
    assert not edges[:, 1:].any()
    centre = CentreSample.from_gbuffer(direct0, position0, normal0, depth0, lamp_light=shares)
    assert centre.light_edge.tolist() == edges[:, 0].tolist()
    system = System()
    got = subframe_direct(system, centre, position0.copy(), normal0.copy(), seed_frame=1, samples=4)
    assert system.calls == [(2, [0])]
    np.testing.assert_allclose(got[:, 0], [3.1, 3.1, 2.6, 2.6, 2.0, 2.0], rtol=1e-6)


def test_extra_subframes_share_the_shadow_ray_floor_of_the_frames_own():
    """A subframe lights its fresh pixels with the shadow samples split over the subframes, at
    least SUBFRAME_MIN_SAMPLES over the Pixel Samples' own subframes; extra subframes (GI edges,
    lens points) spread that floor's total instead of each keeping it."""
    from hybridgi_core.raster.frame import SUBFRAME_MIN_SAMPLES, subframe_shadow_samples  # noqa: PLC0415

    assert subframe_shadow_samples(48, 8, 8) == SUBFRAME_MIN_SAMPLES  # the frame's own: unchanged
    assert subframe_shadow_samples(96, 8, 8) == 12  # the split where it is above the floor
    assert subframe_shadow_samples(48, 1, 1) == 48
    # 8 + 24 GI-edge subframes: the floor's 64 rays over 32; 2 + 24: 16 over 26 (at least 1);
    # 16 lens points over 8 Pixel Samples: 64 over 16.
    assert subframe_shadow_samples(48, 8, 32) == 2
    assert subframe_shadow_samples(24, 2, 26) == 1
    assert subframe_shadow_samples(24, 8, 16) == 4
    assert subframe_shadow_samples(4, 8, 32) == 1


def test_extra_subframes_grow_with_the_frames_own():
    """A frame whose GI edges pass the share adds at most EXTRA_PER_SUBFRAME extra subframes per
    subframe of its own, EXTRA_SUBFRAMES at most: 2 Pixel Samples take 2 + 6, 8 take 8 + 24."""
    from types import SimpleNamespace

    from hybridgi_core.raster import frame as frame_mod
    from hybridgi_core.raster.subpixel import CentreSample

    h, w = 4, 8
    # Alternate columns: a near plane and a far plane, their indirect light 20 x apart.
    position = np.zeros((h, w, 4), np.float32)
    position[..., 0] = np.arange(w) * 0.01
    position[..., 2] = np.where(np.arange(w) % 2 == 0, -5.0, -9.0)
    position[..., 3] = 1.0
    normal = np.tile(np.array([0, 0, 1, 0], np.float32), (h, w, 1))
    depth = -position[..., 2].reshape(-1)
    centre = CentreSample(np.zeros((h * w, 4), np.float32), position.reshape(-1, 4), normal.reshape(-1, 4), depth)
    indirect = np.zeros((h * w, 4), np.float32)
    indirect[:, :3] = np.where(np.arange(w) % 2 == 0, 1.0, 0.05)[None, :].repeat(h, 0).reshape(-1, 1)
    pipe = SimpleNamespace(extra_subframes=frame_mod.EXTRA_SUBFRAMES, subframes=8, height=h, width=w)
    stats = SimpleNamespace(extra_pixels=0)
    count = functools.partial(frame_mod.FramePipeline._subframe_count, pipe, centre, SimpleNamespace(indirect=indirect),
                              stats)
    assert count(2) == 2 + 2 * frame_mod.EXTRA_PER_SUBFRAME
    assert count(8) == 8 + frame_mod.EXTRA_SUBFRAMES
    assert count(16) == 16 + frame_mod.EXTRA_SUBFRAMES
    assert stats.extra_pixels == h * w

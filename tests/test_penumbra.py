"""Penumbra-adaptive shadow rays (hybridgi_core/penumbra.py): the full sample count where a
shadow is soft, few rays elsewhere, and the same light as the full count everywhere."""

from __future__ import annotations

import numpy as np

from hybridgi_core.lights import RATIO_MIN_SAMPLES, direct_irradiance, one_sample_exact, rough_lights
from hybridgi_core.penumbra import (
    COARSE_MIN_PIXELS,
    FIRST_SAMPLES,
    MAX_SHARE,
    MIN_SHARE,
    TIERS,
    WEAK_SHARE,
    adaptive_direct,
    dilate,
    filter_emitter_light,
    sample_counts,
)
from tests.test_lights import TriangleTracer, area_light, point_light, quad, sun_light, translation

# A floor image of 48 x 48 pixels over [-4, 4]^2, a 1 m square lamp 2 m up, a blocker that
# shadows the middle: a hard core with soft rims (penumbrae) and open floor around them.
H = W = 48


def _floor():
    ys, xs = np.meshgrid(np.linspace(-4, 4, H), np.linspace(-4, 4, W), indexing="ij")
    pts = np.column_stack([xs.ravel(), ys.ravel(), np.zeros(H * W)]).astype(np.float32)
    return pts, np.tile(np.float32([0, 0, 1]), (H * W, 1))


def _direct(lights, tracer, seed=0):
    """`GISystem.direct`'s signature over `lights` (lights= picks some of them by index)."""
    def direct(points, normals, frame, samples=1, partial=None, unshadowed=None, exact=None, per_lamp=None,
               lights=None):
        rng = np.random.default_rng([seed, frame])
        shaded = lamps if lights is None else [lamps[i] for i in lights]
        return direct_irradiance(shaded, points, normals, tracer, rng, samples=samples,
                                 partial=partial, unshadowed=unshadowed, exact=exact, per_lamp=per_lamp)
    lamps = lights
    return direct


def test_dilate_grows_by_the_radius_without_wrapping():
    mask = np.zeros((7, 9), bool)
    mask[0, 0] = mask[4, 5] = True
    grown = dilate(mask, 2)
    assert grown.sum() == 9 + 25
    assert grown[2, 2] and grown[3, 3] and not grown[3, 2] and grown[6, 7] and not grown[6, 8]
    assert not grown[:, -1].any() and not grown[-1, :3].any()  # no wrap-around to the far side


def test_partial_marks_penumbrae_only():
    lamp = area_light(translation(0.0, 0.0, 2.0), power=200.0)
    tracer = TriangleTracer(quad((0.0, 0.0, 1.0), (0.4, 0, 0), (0, 0.4, 0)))
    pts, nrm = _floor()
    partial = np.zeros(H * W, bool)
    direct_irradiance([lamp], pts, nrm, tracer, np.random.default_rng(0), samples=16, partial=partial)
    v = direct_irradiance([lamp], pts, nrm, tracer, np.random.default_rng(1), samples=1024) / np.maximum(
        direct_irradiance([lamp], pts, nrm, None, np.random.default_rng(1), samples=1024), 1e-9)
    v = v[:, 0]
    assert partial.any() and not partial[v > 0.999].any() and not partial[v < 0.001].any()
    assert partial[(v > 0.2) & (v < 0.8)].mean() > 0.95
    # Hard shadows (one ray per receiver) have no penumbra; the flag is cleared, not accumulated.
    partial[:] = True
    direct_irradiance([point_light((0, 0, 2))], pts, nrm, tracer, np.random.default_rng(0), samples=16, partial=partial)
    assert not partial.any()


def test_unshadowed_output_is_the_same_samples_without_shadows():
    """direct_irradiance's unshadowed output: what the same call without a tracer returns, for
    every lamp kind (the penumbra filter's visibility is the ratio of the two)."""
    lamps = [area_light(translation(0.0, 0.0, 2.0), power=200.0), sun_light((0.3, 0.2, -1.0), strength=2.0, angle=0.1),
             sun_light((-0.2, 0.1, -1.0), strength=1.0), point_light((1.0, 0.5, 1.5), radius=0.2)]
    tracer = TriangleTracer(quad((0.0, 0.0, 1.0), (0.4, 0, 0), (0, 0.4, 0)))
    pts, nrm = _floor()
    for samples in (1, 16):
        opened = np.full((H * W, 3), np.nan, np.float32)
        shadowed = direct_irradiance(lamps, pts, nrm, tracer, np.random.default_rng(5), samples=samples,
                                     unshadowed=opened)
        free = direct_irradiance(lamps, pts, nrm, None, np.random.default_rng(5), samples=samples)
        np.testing.assert_array_equal(opened, free)
        assert (shadowed <= opened + 1e-6).all() and (shadowed < opened - 1e-3).any()


def test_adaptive_direct_matches_the_full_count_with_fewer_rays():
    lamp = area_light(translation(0.0, 0.0, 2.0), power=200.0)
    sun = sun_light((0.3, 0.2, -1.0), strength=2.0, angle=0.1)
    tracer = TriangleTracer(quad((0.0, 0.0, 1.0), (0.4, 0, 0), (0, 0.4, 0)))
    pts, nrm = _floor()
    pix = np.arange(H * W)
    ref = direct_irradiance([lamp, sun], pts, nrm, tracer, np.random.default_rng(7), samples=1024)
    tracer.rays = 0
    light, full = adaptive_direct(_direct([lamp, sun], tracer), pts, nrm, pix, (H, W), frame=3, samples=16)
    adaptive_rays = tracer.rays
    tracer.rays = 0
    plain = _direct([lamp, sun], tracer)(pts, nrm, 3, samples=16)
    plain_rays = tracer.rays
    # Far fewer rays: open floor and the umbra's core get FIRST_SAMPLES only.
    assert 0.05 < full.mean() < 0.6
    assert adaptive_rays < 0.75 * plain_rays
    # As close to the converged light as 16 rays everywhere, and exact on the open floor.
    err_adaptive = np.abs(light - ref).sum() / ref.sum()
    err_plain = np.abs(plain - ref).sum() / ref.sum()
    assert err_adaptive < 1.1 * err_plain, (err_adaptive, err_plain)
    # Pixels left at the first count saw their lamps wholly or not at all.
    open_floor = ~full
    assert np.abs(light[open_floor] - ref[open_floor]).max() < 0.1 * ref.max()


def test_few_samples_skip_the_second_pass():
    lamp = area_light(translation(0.0, 0.0, 2.0), power=200.0)
    tracer = TriangleTracer(quad((0.0, 0.0, 1.0), (0.4, 0, 0), (0, 0.4, 0)))
    pts, nrm = _floor()
    light, full = adaptive_direct(_direct([lamp], tracer), pts, nrm, np.arange(H * W), (H, W), frame=0,
                                  samples=FIRST_SAMPLES)
    assert full.all()
    np.testing.assert_array_equal(light, _direct([lamp], tracer)(pts, nrm, 0, samples=FIRST_SAMPLES))


def test_filtered_penumbra_is_closer_to_the_converged_light_and_keeps_open_floor_exact():
    """The penumbra pixels' visibility averaged on their surface (camera given): less noise than
    24 rays alone where the penumbra spans many pixels (3 cm pixels here, as a render's are
    against an area lamp's soft shadow), and the wholly lit floor is untouched."""
    lamp = area_light(translation(0.0, 0.0, 2.0), power=200.0)
    tracer = TriangleTracer(quad((0.0, 0.0, 1.0), (0.4, 0, 0), (0, 0.4, 0)))
    n = 96
    ys, xs = np.meshgrid(np.linspace(-1.5, 1.5, n), np.linspace(-1.5, 1.5, n), indexing="ij")
    pts = np.column_stack([xs.ravel(), ys.ravel(), np.zeros(n * n)]).astype(np.float32)
    nrm = np.tile(np.float32([0, 0, 1]), (n * n, 1))
    pix = np.arange(n * n)
    ref = direct_irradiance([lamp], pts, nrm, tracer, np.random.default_rng(7), samples=1024)
    camera = np.array([0.0, 0.0, 5.0])
    raw, full = adaptive_direct(_direct([lamp], tracer), pts, nrm, pix, (n, n), frame=3, samples=16)
    smooth, full_f = adaptive_direct(_direct([lamp], tracer), pts, nrm, pix, (n, n), frame=3, samples=16,
                                     camera=camera)
    np.testing.assert_array_equal(full, full_f)
    err = lambda e: np.abs(e - ref)[full].sum() / ref[full].sum()  # noqa: E731
    assert err(smooth) < 0.8 * err(raw), (err(smooth), err(raw))
    np.testing.assert_array_equal(smooth[~full], raw[~full])


def test_exact_light_is_reused_and_the_same():
    """direct_irradiance's exact= in/out: the area lamp's exact unshadowed light, filled where
    the ratio estimator used it and read back by a later call (the penumbra pass), which gives
    the same light as computing it again; adaptive_direct with lamps= gives the same bits."""
    lamps = [sun_light((0.3, 0.2, -1.0), strength=2.0, angle=0.1), area_light(translation(0.0, 0.0, 2.0), power=200.0)]
    tracer = TriangleTracer(quad((0.0, 0.0, 1.0), (0.4, 0, 0), (0, 0.4, 0)))
    pts, nrm = _floor()
    exact = np.full((H * W, 2), np.nan)
    plain = direct_irradiance(lamps, pts, nrm, tracer, np.random.default_rng(3), samples=8)
    kept = direct_irradiance(lamps, pts, nrm, tracer, np.random.default_rng(3), samples=8, exact=exact)
    np.testing.assert_array_equal(kept, plain)
    assert np.isnan(exact[:, 0]).all()  # the sun has no closed form here
    lit = ~np.isnan(exact[:, 1])
    assert lit.mean() > 0.5 and not lit.all()  # wholly shadowed receivers need none
    again = direct_irradiance(lamps, pts, nrm, tracer, np.random.default_rng(3), samples=8, exact=exact.copy())
    np.testing.assert_array_equal(again, plain)
    wrong = exact.copy()
    wrong[lit, 1] *= 2.0  # read, not recomputed: the lit receivers' light changes
    doubled = direct_irradiance(lamps, pts, nrm, tracer, np.random.default_rng(3), samples=8, exact=wrong)
    assert (doubled[lit] > kept[lit]).any()
    pix = np.arange(H * W)
    for camera in (None, np.array([0.0, -3.0, 4.0])):
        a = adaptive_direct(_direct(lamps[1:], tracer), pts, nrm, pix, (H, W), frame=2, samples=24, camera=camera)
        b = adaptive_direct(_direct(lamps[1:], tracer), pts, nrm, pix, (H, W), frame=2, samples=24, camera=camera,
                            lamps=1)
        np.testing.assert_array_equal(a[0], b[0])
        np.testing.assert_array_equal(a[1], b[1])


def test_per_lamp_outputs_split_the_light_and_the_penumbrae():
    """direct_irradiance's per_lamp shares sum to its result, and a per-lamp partial (n, lamps)
    marks each lamp's own penumbra: their union is the one-column mark of the same samples."""
    lamps = [area_light(translation(0.0, 0.0, 2.0), power=200.0), sun_light((0.3, 0.2, -1.0), strength=2.0, angle=0.1),
             point_light((1.0, 0.5, 1.5), radius=0.2), sun_light((-0.2, 0.1, -1.0), strength=1.0)]
    tracer = TriangleTracer(quad((0.0, 0.0, 1.0), (0.4, 0, 0), (0, 0.4, 0)))
    pts, nrm = _floor()
    union = np.zeros(H * W, bool)
    plain = direct_irradiance(lamps, pts, nrm, tracer, np.random.default_rng(4), samples=8, partial=union)
    each = np.zeros((H * W, len(lamps)), bool)
    share = np.zeros((H * W, len(lamps), 3), np.float32)
    split = direct_irradiance(lamps, pts, nrm, tracer, np.random.default_rng(4), samples=8, partial=each,
                              per_lamp=share)
    np.testing.assert_array_equal(split, plain)
    np.testing.assert_allclose(share.sum(axis=1), plain, rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(each.any(axis=1), union)
    assert each[:, 0].any() and each[:, 1].any() and not each[:, 3].any()  # the axial sun is hard
    assert (each[:, 0] != each[:, 1]).any()  # their penumbrae lie apart
    for j, lamp in enumerate(lamps):
        alone = direct_irradiance([lamp], pts, nrm, tracer, np.random.default_rng(9), samples=256)
        assert np.abs(share[:, j] - alone).sum() <= 0.1 * max(alone.sum(), 1e-9) + 1e-6, j


def test_per_lamp_penumbrae_trace_fewer_rays_for_the_same_light():
    """Two soft lamps whose penumbrae lie in different places: re-sampling each lamp only in its
    own penumbra (lamps=2) traces fewer rays than re-sampling both wherever either is soft, and
    is as close to the converged light."""
    lamps = [area_light(translation(0.0, 0.0, 2.0), power=200.0), point_light((2.5, -2.0, 1.5), radius=0.3)]
    tracer = TriangleTracer(quad((0.0, 0.0, 1.0), (0.4, 0, 0), (0, 0.4, 0)))
    pts, nrm = _floor()
    pix = np.arange(H * W)
    ref = direct_irradiance(lamps, pts, nrm, tracer, np.random.default_rng(7), samples=2048)
    errors, rays = [], []
    for count in (0, len(lamps)):
        tracer.rays = 0
        light, full = adaptive_direct(_direct(lamps, tracer), pts, nrm, pix, (H, W), frame=3, samples=32,
                                      lamps=count)
        rays.append(tracer.rays)
        errors.append(np.abs(light - ref).sum() / ref.sum())
        assert (light >= 0).all()
    assert rays[1] < 0.8 * rays[0], rays
    assert errors[1] < 1.15 * errors[0], errors


def test_per_lamp_shares_of_adaptive_direct_add_up_to_its_light():
    """adaptive_direct(per_lamp=) hands each lamp's share after its own penumbra pass (what the
    subframes' per-lamp light edges read): the shares add up to the light, and each is that lamp's
    light alone (a lamp's shadow is not in the other's share)."""
    lamps = [area_light(translation(0.0, 0.0, 2.0), power=200.0), point_light((2.5, -2.0, 1.5), radius=0.3)]
    tracer = TriangleTracer(quad((0.0, 0.0, 1.0), (0.4, 0, 0), (0, 0.4, 0)))
    pts, nrm = _floor()
    pix = np.arange(H * W)
    shares = np.zeros((pts.shape[0], 2, 3), np.float32)
    light, _full = adaptive_direct(_direct(lamps, tracer), pts, nrm, pix, (H, W), frame=3, samples=32, lamps=2,
                                   per_lamp=shares)
    np.testing.assert_allclose(shares.sum(axis=1), light, rtol=1e-5, atol=1e-6)
    for k, lamp in enumerate(lamps):
        alone = direct_irradiance([lamp], pts, nrm, tracer, np.random.default_rng(7), samples=512)
        assert np.abs(shares[:, k] - alone).sum() < 0.05 * alone.sum(), k


def test_weak_lamps_trace_one_ray_and_the_strong_lamp_its_one_lamp_rays():
    """adaptive_direct(rough=): a dim soft lamp beside a strong one traces one shadow ray where
    its rough light is under WEAK_SHARE of the pixel's, and no penumbra pass there: fewer rays
    than without rough=, the light as close to the converged light, and the strong lamp's share,
    strong everywhere, the very light of a frame with that lamp alone."""
    strong = area_light(translation(0.0, 0.0, 2.0), power=2000.0)
    lamps = [strong, point_light((2.5, -2.0, 1.5), radius=0.3, power=50.0)]
    tracer = TriangleTracer(quad((0.0, 0.0, 1.0), (0.4, 0, 0), (0, 0.4, 0)))
    pts, nrm = _floor()
    pix = np.arange(H * W)
    rough = rough_lights(lamps, pts, nrm)
    weak = rough[:, 1] < WEAK_SHARE * rough.sum(axis=1)
    assert 0.5 < weak.mean() < 1.0  # weak over most of the floor, not under the dim lamp
    ref = direct_irradiance(lamps, pts, nrm, tracer, np.random.default_rng(7), samples=2048)
    errors, rays = [], []
    for given in (None, rough):
        tracer.rays = 0
        shares = np.zeros((pts.shape[0], 2, 3), np.float32)
        light, _ = adaptive_direct(_direct(lamps, tracer), pts, nrm, pix, (H, W), frame=3, samples=32, lamps=2,
                                   per_lamp=shares, rough=given)
        rays.append(tracer.rays)
        errors.append(np.abs(light - ref).sum() / ref.sum())
        np.testing.assert_allclose(shares.sum(axis=1), light, rtol=1e-5, atol=1e-6)
    assert rays[1] < 0.75 * rays[0], rays
    assert errors[1] < 1.05 * errors[0] + 1e-4, errors
    alone, _ = adaptive_direct(_direct([strong], tracer), pts, nrm, pix, (H, W), frame=3, samples=32, lamps=1,
                               rough=rough[:, :1])
    np.testing.assert_array_equal(shares[:, 0], alone)


def _direct_with_ratio(lights, tracer, seed=0):
    """`_direct` with `direct_irradiance`'s ratio_samples= too (the probes' one-sample check)."""
    def direct(points, normals, frame, samples=1, partial=None, unshadowed=None, exact=None, per_lamp=None,
               lights=None, ratio_samples=RATIO_MIN_SAMPLES):
        rng = np.random.default_rng([seed, frame])
        shaded = lamps if lights is None else [lamps[i] for i in lights]
        return direct_irradiance(shaded, points, normals, tracer, rng, samples=samples, partial=partial,
                                 unshadowed=unshadowed, exact=exact, per_lamp=per_lamp, ratio_samples=ratio_samples)
    lamps = lights
    return direct


def _large_floor(n=144):
    """n x n floor pixels over [-4, 4]^2 (enough for the probes: n^2 >= COARSE_MIN_PIXELS)."""
    ys, xs = np.meshgrid(np.linspace(-4, 4, n), np.linspace(-4, 4, n), indexing="ij")
    pts = np.column_stack([xs.ravel(), ys.ravel(), np.zeros(n * n)]).astype(np.float32)
    return pts, np.tile(np.float32([0, 0, 1]), (n * n, 1)), n


def test_probes_find_the_penumbrae_with_fewer_rays_and_the_same_light():
    """The first pass on probes (`_coarse_first_pass`): a soft lamp's penumbra and a hard lamp's
    thin shadow, a one-pixel line between probes that saw the lamp, come out as the full first
    pass gives them, for far fewer rays."""
    assert _large_floor()[2] ** 2 >= COARSE_MIN_PIXELS
    area = area_light(translation(0.0, 0.0, 2.0), power=200.0, size=0.3)
    point = point_light((5.0, 0.5, 3.0), power=600.0)
    # A square blocker (a soft shadow of the area lamp, its penumbra a few pixels wide) and a thin
    # bar: its hard shadow under the point lamp is one pixel column wide, an odd one (x = -1.93 m),
    # which no probe sees, far from its soft shadow under the area lamp (x = -1.26 m): only the
    # pixels' own check rays find it.
    blockers = quad((0.0, 0.0, 0.6), (0.4, 0, 0), (0, 0.4, 0)) + quad((-1.0062, 0.0, 0.4), (0.02, 0, 0), (0, 1.5, 0))
    pts, nrm, n = _large_floor()
    pix = np.arange(n * n)
    lamps = [area, point]
    line = pts[:, 0][(np.arange(n * n) % n) == 37][0]  # the bar's shadow, an odd pixel column

    class LineTracer(TriangleTracer):
        """Counts the rays leaving that column too."""
        line_rays = 0

        def occluded(self, origins, directions, tfar=np.inf, trusted=False):
            self.line_rays += int((np.abs(origins[:, 0] - line) < 1e-3).sum())
            return super().occluded(origins, directions, tfar, trusted)

    tracer = LineTracer(blockers)
    ref = direct_irradiance(lamps, pts, nrm, tracer, np.random.default_rng(7), samples=512)
    runs = {}
    for name, exact_lamps in (("plain", None), ("probes", np.array([one_sample_exact(lt) for lt in lamps]))):
        tracer.rays = tracer.line_rays = 0
        shares = np.zeros((n * n, 2, 3), np.float32)
        light, full = adaptive_direct(_direct_with_ratio(lamps, tracer), pts, nrm, pix, (n, n), frame=3,
                                      samples=16, lamps=2, per_lamp=shares, exact_lamps=exact_lamps)
        runs[name] = (light, full, shares, tracer.rays)
    runs["line_rays"] = tracer.line_rays
    (light_p, full_p, share_p, rays_p), (light_c, full_c, share_c, rays_c) = runs["plain"], runs["probes"]
    assert rays_c < 0.6 * rays_p, (rays_c, rays_p)
    err = lambda e: np.abs(e - ref).sum() / ref.sum()  # noqa: E731
    assert err(light_c) < 1.1 * err(light_p) + 1e-3, (err(light_c), err(light_p))
    # The hard lamp's light is one ray's either way: the same at every pixel, its thin shadow too.
    bar_shadow = (share_p[:, 1, 0] == 0) & (np.abs(pts[:, 0] + 1.93) < 0.2)
    assert 0 < bar_shadow.sum() < 0.02 * n * n
    assert (np.flatnonzero(bar_shadow) % n % 2 == 1).all()  # between the probes' columns
    np.testing.assert_allclose(share_c[:, 1], share_p[:, 1], rtol=1e-5, atol=1e-6)
    # The line's pixels agreed with no probe's view of the point lamp (their check rays were
    # blocked): they traced the full first pass, FIRST_SAMPLES rays to the area lamp, not one.
    assert runs["line_rays"] >= bar_shadow.sum() * (FIRST_SAMPLES + 1), (runs["line_rays"], bar_shadow.sum())
    # The soft penumbra is found (re-sampled) where the full first pass finds it.
    assert full_c[full_p].mean() > 0.95


def test_one_sample_exact_lamps():
    assert one_sample_exact(point_light((0, 0, 2)))
    assert one_sample_exact(point_light((0, 0, 2), radius=0.3))
    assert one_sample_exact(area_light(translation(0, 0, 2)))
    assert one_sample_exact(area_light(translation(0, 0, 2), shape="DISK"))
    assert one_sample_exact(sun_light((0, 0, -1), angle=0.02))
    assert not one_sample_exact(sun_light((0, 0, -1), angle=0.2))  # one direction's cosine is not the disc's
    sheared = translation(0, 0, 2)
    sheared[:3, 1] = (0.5, 1.0, 0.0)
    assert not one_sample_exact(area_light(sheared))
    spread = area_light(translation(0, 0, 2))
    spread.spread = 0.5
    assert not one_sample_exact(spread)


def test_sun_disc_is_exact_where_nothing_shadows_it():
    """A sampled sun disc takes the ratio estimator: an open floor gets strength x cos exactly,
    not each sample direction's cosine (1.7% noise under a 2 degree sun at 45 degrees)."""
    sun = sun_light((1.0, 0.0, -1.0), strength=3.0, angle=np.radians(2.0))
    tracer = TriangleTracer(quad((0.0, 0.0, 1.0), (0.4, 0, 0), (0, 0.4, 0)))
    pts, nrm = _floor()
    partial = np.zeros(H * W, bool)
    light = direct_irradiance([sun], pts, nrm, tracer, np.random.default_rng(0), samples=8, partial=partial)
    unblocked = direct_irradiance([sun], pts, nrm, None, np.random.default_rng(0), samples=8)
    exact = 3.0 * np.cos(np.pi / 4)
    np.testing.assert_allclose(unblocked[:, 0], exact, rtol=1e-5)
    lit = (light[:, 0] > 0) & ~partial
    assert lit.mean() > 0.5
    np.testing.assert_allclose(light[lit, 0], exact, rtol=1e-5)
    # Below ratio_samples, each sample's own cosine (the plain estimate): not all equal.
    plain = direct_irradiance([sun], pts, nrm, None, np.random.default_rng(0), samples=2)
    assert np.ptp(plain[:, 0]) > 1e-3 * exact


def test_sample_counts_spend_the_rays_where_the_lamp_is_bright_for_the_same_expected_error():
    """sample_counts: rays ~ the rough light^(2/3) on the tiers, within MIN_SHARE..MAX_SHARE of
    `samples`, fewer in all for the expected error (sum e / sqrt(first + n)) of `samples` each;
    a lamp whose light is even over the penumbra, none known or none at all: `samples` each."""
    first, samples = FIRST_SAMPLES, 48
    e = np.geomspace(0.01, 10.0, 500)[np.random.default_rng(0).permutation(500)]
    n = sample_counts(e, first, samples)
    order = np.argsort(e)
    assert (np.diff(n[order]) >= 0).all()  # brighter never fewer
    tiers = set(np.rint(samples * np.asarray(TIERS)).astype(int))
    assert set(n.tolist()) <= tiers and MIN_SHARE * samples <= n.min() and n.max() <= MAX_SHARE * samples
    uniform = (e / np.sqrt(first + samples)).sum()
    assert (e / np.sqrt(first + n)).sum() < 1.03 * uniform  # the tiers' rounding
    assert n.sum() < 0.85 * samples * e.size
    for even in (np.full(100, 3.0), None, np.zeros(100), np.full(100, np.nan)):
        n = sample_counts(even, first, samples)
        assert n.size == (0 if even is None else 100) and (n == samples).all()


def test_a_penumbra_falling_off_from_its_lamp_takes_fewer_rays_for_the_same_light():
    """A 1 m area lamp 1 m above a floor and a blocker beside it: the penumbra runs from under the
    lamp to metres away, where the lamp's light is a fraction of it. adaptive_direct(rough=)
    traces fewer shadow rays there and is as close to the converged light (six frames)."""
    lamp = area_light(translation(-2.0, 0.0, 1.0), power=300.0)
    tracer = TriangleTracer(quad((-1.2, 0.0, 0.6), (0.5, 0, 0), (0, 2.0, 0)))
    pts, nrm = _floor()
    pix = np.arange(H * W)
    ref = direct_irradiance([lamp], pts, nrm, tracer, np.random.default_rng(7), samples=4096)
    rough = rough_lights([lamp], pts, nrm)
    rays, errors = [], []
    for given in (None, rough):
        tracer.rays, err = 0, 0.0
        for frame in range(6):
            light, full = adaptive_direct(_direct([lamp], tracer), pts, nrm, pix, (H, W), frame=frame, samples=32,
                                          lamps=1, rough=given)
            err += np.abs(light - ref).sum() / ref.sum()
        assert 0.2 < full.mean() < 0.8
        rays.append(tracer.rays)
        errors.append(err / 6)
    assert rays[1] < 0.85 * rays[0], rays
    assert errors[1] < 1.05 * errors[0], errors


def test_emitters_sampled_by_power_are_denoised_apart_from_their_shadows_and_cones():
    """`filter_emitter_light`: a panel of 32 triangles over a floor with a blocker, 16 samples per
    pixel by power (`MeshLights._block`): closer to 512 samples than the raw samples, the core
    of the shadow still dark, and a compact emitter's cone light (handed over apart) added back
    as it was."""
    from hybridgi_core.emitters import MeshLights

    quads = [quad((x, y, 2.0), (0.125, 0.0, 0.0), (0.0, 0.125, 0.0))
             for x in (-0.375, -0.125, 0.125, 0.375) for y in (-0.375, -0.125, 0.125, 0.375)]
    tris = np.asarray([t for q in quads for t in q], np.float32)
    lights = MeshLights.from_triangles(tris.reshape(-1, 3), np.arange(3 * len(tris)).reshape(-1, 3),
                                       np.tile(np.float32([4.0, 3.0, 2.0]), (len(tris), 1)))
    assert not lights.ratio
    tracer = TriangleTracer(np.concatenate([tris, np.asarray(quad((0.0, 0.0, 1.0), (0.3, 0, 0), (0, 0.3, 0)),
                                                             np.float32)]))
    n = 40
    ys, xs = np.meshgrid(np.linspace(-1.2, 1.2, n), np.linspace(-1.2, 1.2, n), indexing="ij")
    pts = np.column_stack([xs.ravel(), ys.ravel(), np.zeros(n * n)]).astype(np.float32)
    nrm = np.tile(np.float32([0, 0, 1]), (n * n, 1))
    ref = lights.irradiance(pts, nrm, tracer, np.random.default_rng(1), 512, 1e-4)
    open_light, cones = np.zeros_like(ref), np.zeros_like(ref)
    raw = lights.irradiance(pts, nrm, tracer, np.random.default_rng(2), 16, 1e-4, unshadowed=open_light, cones=cones)
    assert (open_light >= raw - 1e-6).all() and not cones.any()
    camera = np.array([0.0, 0.0, 5.0])
    out = filter_emitter_light(raw, open_light, cones, pts, nrm, np.arange(n * n), (n, n), camera)
    err = lambda e: float(np.abs(e - ref).sum() / ref.sum())  # noqa: E731
    assert err(out) < 0.6 * err(raw), (err(out), err(raw))
    core = np.linalg.norm(pts[:, :2], axis=1) < 0.05
    assert out[core].max() < 0.2 * ref.max()
    glow = np.full_like(raw, 0.5)
    np.testing.assert_allclose(filter_emitter_light(raw + glow, open_light, glow, pts, nrm, np.arange(n * n), (n, n),
                                                    camera), out + glow, rtol=1e-5, atol=1e-6)

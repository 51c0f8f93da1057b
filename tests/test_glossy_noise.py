"""More glossy lamp samples where the highlight is noisy (`glossy_noise`), and the variance
`glossy.glossy_direct` reports for it: bpy-free, on a floor half rough, half polished, under a
small area lamp."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from hybridgi_core import glossy
from hybridgi_core import specular as sp
from hybridgi_core.glossy_noise import FIRST_SAMPLES, LUMA, adaptive_lamp_glossy
from hybridgi_core.sampling import frame_rng
from hybridgi_core.snapshot import Light, Material

SIDE = 24  # the image: SIDE x SIDE pixels of floor


def _lamp() -> Light:
    matrix = np.eye(4)
    matrix[:3, 3] = (0.0, 0.0, 2.0)
    return Light(kind="AREA", color=np.ones(3, np.float32), power=200.0, matrix=matrix, size=0.6)


def _floor():
    """Points of a 4 m floor (one per pixel), their normals and directions to an eye above its
    front edge; the left half rough (material 0), the right half polished (material 1)."""
    xs = np.linspace(-2.0, 2.0, SIDE, dtype=np.float32)
    x, y = np.meshgrid(xs, xs)
    points = np.stack([x.ravel(), y.ravel(), np.zeros(SIDE * SIDE, np.float32)], axis=1)
    normals = np.tile(np.array([[0.0, 0.0, 1.0]], np.float32), (SIDE * SIDE, 1))
    eye = np.array([0.0, -4.0, 3.0], np.float32)
    to_eye = eye - points
    to_eye /= np.linalg.norm(to_eye, axis=1, keepdims=True)
    rows = (points[:, 0] > 0).astype(np.int32)
    mats = glossy.GlossyMaterials.from_materials([Material(specular=sp.SpecularLayer(roughness=0.8)),
                                                  Material(specular=sp.SpecularLayer(roughness=0.15))])
    return points, normals, to_eye, rows, mats


class _System:
    """What `reflection.lamp_glossy_without` asks of a GISystem: its lamps and `glossy`, here
    without shadow rays."""

    def __init__(self, lights, mats):
        self.scene = SimpleNamespace(lights=lights)
        self.glossy_materials = mats
        self.settings = SimpleNamespace(seed=0)
        self.calls = []

    def glossy(self, points, normals, to_eye, rows, frame, samples=None, lights=None, variance=None, widen=None):
        self.calls.append((len(points), samples))
        return glossy.glossy_direct(self.scene.lights if lights is None else lights, points, normals, to_eye, rows,
                                    self.glossy_materials, None, frame_rng(7, frame), samples, variance=variance,
                                    widen=widen)


def test_the_reported_variance_is_the_spread_of_the_estimates():
    """Over many independent estimates of 4 samples each, the luminance's variance is what each
    estimate's own samples said it was (on average, per receiver; polished and rough alike)."""
    points, normals, to_eye, rows, mats = _floor()
    pick = np.array([SIDE * SIDE // 2 + SIDE // 2 + 1, SIDE * SIDE // 2 + 2, SIDE * 3 + SIDE - 3, SIDE * 3 + 2])
    lum, reported = [], []
    for seed in range(400):
        var = np.zeros(pick.size, np.float32)
        out = glossy.glossy_direct([_lamp()], points[pick], normals[pick], to_eye[pick], rows[pick], mats, None,
                                   np.random.default_rng(seed), samples=4, variance=var)
        lum.append(out @ LUMA)
        reported.append(var)
    empirical = np.var(np.array(lum), axis=0)
    predicted = np.mean(np.array(reported), axis=0)
    assert (empirical > 0).all(), empirical
    # The report treats the samples as independent; the stratified ones spread less (4-5x here):
    # it may be high, never low.
    assert np.all(predicted > 0.8 * empirical), (predicted, empirical)
    assert np.all(predicted < 8.0 * empirical), (predicted, empirical)


def test_noisy_highlights_take_the_samples_and_the_estimate_stays_unbiased():
    points, normals, to_eye, rows, mats = _floor()
    lamp = _lamp()
    pix = np.arange(SIDE * SIDE)
    skip = np.zeros((pix.size, 1), bool)
    level = np.zeros(pix.size, np.float32)
    converged = glossy.glossy_direct([lamp], points, normals, to_eye, rows, mats, None, np.random.default_rng(99),
                                     samples=4096) @ LUMA
    estimates, chosen, spent = [], [], []
    for frame in range(24):
        system = _System([lamp], mats)
        light, more = adaptive_lamp_glossy(system, points, normals, to_eye, rows, pix, (SIDE, SIDE), frame, 64,
                                           skip, level)
        estimates.append(light @ LUMA)
        chosen.append(more)
        spent.append(sum(n * s for n, s in system.calls))
    estimates, chosen = np.array(estimates), np.array(chosen)
    polished = rows == 1
    lit = converged > 1e-3 * converged.max()
    # The polished half's highlight is where the samples went; the rough half needs few.
    assert chosen[:, polished & lit].mean() > 3.0 * chosen[:, ~polished & lit].mean(), chosen.mean(axis=0)
    assert np.mean(spent) < 0.6 * 64 * pix.size, np.mean(spent)
    # Unbiased: the mean over frames is the converged light (within its own noise), pixel by
    # pixel in the highlight and over each half.
    mean = estimates.mean(axis=0)
    for half in (polished & lit, ~polished & lit):
        assert abs(mean[half].sum() / converged[half].sum() - 1.0) < 0.02
    # And quieter than the first pass alone where it sampled again.
    first = []
    for frame in range(24):
        first.append(_System([lamp], mats).glossy(points, normals, to_eye, rows, frame, FIRST_SAMPLES) @ LUMA)
    err_adaptive = np.abs(estimates - converged)[:, polished & lit].mean()
    err_first = np.abs(np.array(first) - converged)[:, polished & lit].mean()
    assert err_adaptive < 0.6 * err_first, (err_adaptive, err_first)


def _faint(x: float, power: float) -> Light:
    matrix = np.eye(4)
    matrix[:3, 3] = (x, 1.0, 1.5)
    return Light(kind="POINT", color=np.ones(3, np.float32), power=power, matrix=matrix, radius=0.3)


def _weak_lamps_over_frames(faint: list, frames: int, check_calls) -> None:
    """The mean over frames of `adaptive_lamp_glossy` at the floor beside the area lamp (skipped,
    as the reflection rays' or the closed form's lamps are, so that its own noise stays out)
    with the dim lamps `faint`, each frame's calls to `glossy` checked by check_calls: within 3%
    of the dim lamps' light."""
    points, normals, to_eye, rows, mats = _floor()
    system = _System([_lamp(), *faint], mats)
    pix = np.arange(SIDE * SIDE)
    skip = np.zeros((pix.size, 1 + len(faint)), bool)
    skip[:, 0] = True
    level = np.zeros(pix.size, np.float32)
    total = np.zeros((pix.size, 3))
    for f in range(frames):
        system.calls.clear()
        light, _ = adaptive_lamp_glossy(system, points, normals, to_eye, rows, pix, (SIDE, SIDE), f, 32, skip, level)
        total += light
        check_calls(system.calls, pix.size)
    expected = glossy.glossy_direct(faint, points, normals, to_eye, rows, mats, None, frame_rng(3, 0), 4096) @ LUMA
    got = (total / frames) @ LUMA
    assert expected.sum() > 0
    assert abs(got.sum() / expected.sum() - 1.0) < 0.03


def test_a_weak_lamp_takes_one_unbiased_sample_and_is_never_resampled():
    """A dim round lamp beside the area lamp (under `penumbra.WEAK_SHARE` of their light at every
    receiver) takes one sample per receiver, in a call of its own, never in the noisy pixels'
    second pass; the mean over frames is its light all the same."""
    def one_call(calls, n):
        assert calls == [(n, 1)]  # one sample at every receiver, no other pass

    _weak_lamps_over_frames([_faint(1.0, 0.5)], 400, one_call)


def test_several_weak_lamps_take_one_sample_of_one_of_them():
    """Two dim round lamps beside the area lamp: each receiver samples one of them once (drawn by
    its rough light, weighted by 1 / its chance), in one call per drawn lamp that together cover
    every receiver once; the mean over frames is both lamps' light."""
    def one_per_lamp(calls, n):
        assert len(calls) == 2 and sum(c[0] for c in calls) == n
        assert all(c[1] == 1 for c in calls)

    _weak_lamps_over_frames([_faint(1.0, 0.5), _faint(-1.0, 0.3)], 600, one_per_lamp)


def test_a_lamp_whose_edge_alone_rises_above_the_horizon_is_not_dropped_as_weak():
    """Receivers tilted away from a 1 m area lamp's centre (cosine -0.15 to it) still see its near
    edge, beside a sun: the lamp's rough light, the weight weak lamps are drawn by, must not be 0
    there (`lights._reach_margin`), or its glossy light is dropped. (A 10 cm lamp 6 cm from the
    dragon's scales, beside a sun: a quarter of the image's Glossy Direct was missing, 0.938
    against Cycles' 1.259; 1.248 since.)"""
    theta = np.radians(35.0)
    n = 64
    points = np.tile(np.array([[0.6, 0.0, 0.0]], np.float32), (n, 1))
    normals = np.tile(np.array([[np.sin(theta), 0.0, np.cos(theta)]], np.float32), (n, 1))
    to_eye = np.tile(np.array([[0.6, 0.0, 0.8]], np.float32), (n, 1))
    rows = np.zeros(n, np.int32)
    mats = _floor()[4]
    area = np.eye(4)
    area[:3, 3] = (0.0, 0.0, 0.3)
    lamp = Light(kind="AREA", color=np.ones(3, np.float32), power=100.0, matrix=area, size=1.0)
    sun = Light(kind="SUN", color=np.ones(3, np.float32), power=1.0, matrix=np.eye(4))  # straight down
    centre = (area[:3, 3] - points[0]) / np.linalg.norm(area[:3, 3] - points[0])
    assert normals[0] @ centre < -0.1  # the lamp's centre is below the horizon
    system = _System([lamp, sun], mats)
    skip = np.zeros((n, 2), bool)
    pix = np.arange(n)
    total = np.zeros((n, 3))
    frames = 32
    for f in range(frames):
        total += adaptive_lamp_glossy(system, points, normals, to_eye, rows, pix, (8, 8), f, 16, skip,
                                      np.zeros(n, np.float32))[0]
    expected = glossy.glossy_direct([lamp, sun], points, normals, to_eye, rows, mats, None, frame_rng(3, 0), 4096)
    alone = glossy.glossy_direct([sun], points, normals, to_eye, rows, mats, None, frame_rng(3, 0), 64)
    assert expected.mean() > 1.5 * alone.mean()  # the lamp's edge gives most of the light
    np.testing.assert_allclose((total / frames).mean(), expected.mean(), rtol=0.03)

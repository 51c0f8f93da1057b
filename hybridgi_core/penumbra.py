"""Shadow rays where a shadow is uncertain: the full-resolution lamp light of a frame.

Why: the deferred pass's lamp light traces `samples` (48) shadow rays per pixel and soft lamp,
~11 M rays at 640x360 for the Cornell box's one area lamp, yet most pixels see a lamp wholly or
not at all, and there one ray says what 48 say (the ratio estimator of `polygon_light` makes a
wholly lit pixel exact). So a first pass traces FIRST_SAMPLES rays per pixel and lamp and marks
the pixels whose rays disagreed (`lights.direct_irradiance(partial=)`). The penumbra is the
region around them, dilated by DILATE pixels: a pixel in a penumbra whose few rays happened to
agree is found through a neighbour whose rays did not. Only there are `samples` more rays traced;
the two estimates are averaged by their sample counts. Hard lamps (one ray, no penumbra) and
images without any soft shadow cost the first pass only. In full frames the first pass itself
runs on probes, a pixel in four (`_coarse_first_pass`): the pixels between probes that all saw
a lamp wholly (or not at all) take one checked ray per lamp, the exact light times its
visibility, and the rest the full first pass.

In a penumbra a pixel's error is its lamp's unshadowed light times the visibility's noise: with
the lamp's rough light at the pixels (`lights.rough_lights`), the penumbra pass spends its rays
where they buy the most absolute error (`sample_counts`), for the expected error of `samples`
rays everywhere.

numpy only (no bpy); `direct` is `GISystem.direct`.
"""

from __future__ import annotations

import numpy as np

from .pixel_gather import filter_at_pixels
from .rows import rows_above

#: Shadow rays per pixel and lamp of the first pass, which finds the penumbrae (>= the ratio
#: estimator's minimum, so that wholly lit pixels are exact).
FIRST_SAMPLES = 8
#: Pixels around a disagreeing pixel that get the full sample count too.
DILATE = 2
#: Added to the frame number of the second pass's samples: a stream of its own.
SEED_OFFSET = 1 << 20
#: A-trous passes over the penumbra pixels' visibility (`filter_penumbra`); 0 = none.
FILTER_PASSES = 1
#: Lamps whose first pass runs in one call (`_per_lamp` keeps their shares: (n, LAMP_GROUP, 3)).
LAMP_GROUP = 8
#: Lamp j's penumbra pass adds j times this to its frame number (and group g0's first pass g0 times).
LAMP_SEED_STRIDE = 1 << 12
#: With several lamps, a lamp whose rough light at a pixel (`lights.rough_lights`) is under this
#: share of all the lamps' there is weak at it: one shadow ray instead of FIRST_SAMPLES, and no
#: penumbra pass (unbiased; its noise is at most this share of the pixel's light, less after the
#: subframes). Why: a room lit through a window by a strong lamp with a few dim ones beside it
#: traced FIRST_SAMPLES rays per pixel to every dim lamp (morse_apartment: 4 point lamps of 100 W
#: with a 1 m radius beside a 28 kW area lamp, 40 rays per pixel for ~0.2% of its light).
WEAK_SHARE = 1.0 / 64.0
#: Added to a weak lamp's frame number (after its own LAMP_SEED_STRIDE): a stream of its own.
WEAK_SEED_OFFSET = 1 << 21
#: Probes (`_coarse_first_pass`): with at least COARSE_MIN_PIXELS pixels, the first pass traces
#: its FIRST_SAMPLES rays per lamp at the pixels of every COARSE_STEP-th row and column only. A
#: pixel whose probes within COARSE_REACH probe steps all saw each lamp wholly (or none of it)
#: takes one sample per lamp instead, the lamp's exact light times that ray's visibility
#: (`lights.one_sample_exact`), and keeps it if the ray agrees with its probes; the others trace
#: the full first pass. Why: most pixels see a lamp wholly or not at all, and there the first
#: pass's FIRST_SAMPLES rays and their sampling cost 3/4 of its time (spheres: 2 soft lamps over
#: 200k pixels, ~0.6 s of the frame's CPU) for the light one ray gives.
COARSE_MIN_PIXELS = 16384
COARSE_STEP = 2
COARSE_REACH = 2
#: More lamps in a group (`_per_lamp`) than this take the full first pass: a pixel is a candidate
#: only where every lamp agrees, and each lamp's weak pixels split the calls further, so with many
#: lamps the probes cost more than they save (640x360, lamp light: 3 lamps 1.20 -> 1.14 s; the
#: five-lamp apartment equal; 8 lamps 2.56 -> 2.74 s).
COARSE_MAX_LAMPS = 4
#: Added to the frame number of the probes' checked pixels' samples and of the other pixels'.
CHECK_SEED_OFFSET = 1 << 22
REST_SEED_OFFSET = 1 << 23
#: Penumbra pixels' shadow rays by the light they can miss (`sample_counts`): a pixel's count
#: lies between MIN_SHARE and MAX_SHARE of `samples`, on the TIERS (shares of `samples`, one
#: `direct` call each; tier i adds i x TIER_SEED_OFFSET to the frame number).
MIN_SHARE = 0.5
MAX_SHARE = 2.0
TIERS = (0.25, 0.375, 0.5, 0.75, 1.0, 1.5, 2.0)
TIER_SEED_OFFSET = 1 << 24


def filter_camera(lights, eye) -> np.ndarray | None:
    """The eye (3,) to hand `adaptive_direct` as `camera` (its penumbrae filtered), or None: an
    orthographic view (eye[3] = 0), or a scene with a sun disc, whose penumbra is a pixel or two
    wide (a filter over 5 x 5 pixels would blur it: car Diffuse Direct 0.0028 -> 0.0029, atrium
    0.0185 -> 0.0189); area lamps' are wide. eye : `gbuffer.camera_eye`'s (x, y, z, w)."""
    eye = np.asarray(eye, np.float64)
    if eye[3] <= 0.5 or any(lt.kind == "SUN" and float(lt.angle) > 0 for lt in lights):
        return None
    return eye[:3]


def dilate(mask: np.ndarray, radius: int) -> np.ndarray:
    """(h, w) bool: mask grown by `radius` pixels (a square neighbourhood), no wrap-around."""
    out = mask.copy()
    for axis in (0, 1):
        grown = out.copy()
        for r in range(1, radius + 1):
            a = [slice(None), slice(None)]
            b = [slice(None), slice(None)]
            a[axis], b[axis] = slice(r, None), slice(None, -r)
            grown[tuple(a)] |= out[tuple(b)]
            grown[tuple(b)] |= out[tuple(a)]
        out = grown
    return out


def adaptive_direct(direct, points: np.ndarray, normals: np.ndarray, pix: np.ndarray, shape: tuple[int, int],
                    frame: int, samples: int, camera=None, pool=None, lamps: int = 0,
                    smooth: np.ndarray | None = None,
                    per_lamp: np.ndarray | None = None,
                    rough: np.ndarray | None = None,
                    exact_lamps: np.ndarray | None = None,
                    exact_out: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Lamp irradiance (n, 3) at the pixels `pix` (flat indices into an image of `shape` (h, w))
    with `samples` shadow rays per lamp in penumbrae and FIRST_SAMPLES elsewhere, and the (n,)
    bool mask of the pixels that got the full count (for some lamp).

    direct(points, normals, frame, samples=, partial=, unshadowed=) -> (n, 3): `GISystem.direct`.
    camera : (3,) the eye; given, the penumbra pixels' visibility (their light over the
    unshadowed light) is filtered edge-aware on their surfaces (`filter_penumbra`).
    lamps : the scene's lamp count; given (> 0), `direct` takes exact= too and the area lamps'
    exact unshadowed irradiance of the first pass is reused by the second (the same values, not
    computed twice: ~1 us per receiver and lamp). With more than one lamp `direct` also takes
    per_lamp= and lights= (lamp indices), and each lamp's penumbra is re-sampled for that lamp
    alone (`_per_lamp`). smooth : (n, 3) the smooth surface normals under the points where a
    normal map bends `normals` (the G-buffer's `surface` target): handed to `direct` (its bump
    shadowing term) and the guide of the penumbra filter's surfaces; None: `normals`. per_lamp :
    an optional (n, lamps, 3) output, each lamp's share of the light (with more than one lamp).
    rough : (n, lamps) each lamp's rough unshadowed light at the points (`lights.rough_lights`)
    or None: with several lamps, the lamps weak at a point (`weak_lamps`); the penumbra pass's
    rays per pixel (`sample_counts`; None: `samples` each).
    exact_lamps : (lamps,) bool, the lamps one sample gives exactly (`lights.one_sample_exact`);
    given, the first pass of the lamps that are all such runs on probes (`_coarse_first_pass`).
    exact_out : an optional (n, lamps) float64 output (NaN-filled by the caller), the area lamps'
    exact unshadowed irradiance wherever the first pass computed it (without colour: `direct`'s
    exact=): with each lamp's light, the visibility the glossy lobes' closed-form lamp light is
    shadowed by (`glossy_ltc`)."""
    guide = normals if smooth is None else smooth
    first = min(FIRST_SAMPLES, samples)
    if samples <= first:
        kwargs = {} if per_lamp is None or lamps <= 1 else {"per_lamp": per_lamp}
        return (direct(points, normals, frame, samples=samples, **kwargs, **_smooth(smooth)),
                np.ones(points.shape[0], bool))
    if lamps > 1:
        return _per_lamp(direct, points, normals, pix, shape, frame, samples, first, camera, pool, lamps, smooth,
                         per_lamp, rough, exact_lamps, exact_out)
    partial = np.zeros(points.shape[0], bool)
    reuse = {"exact": np.full((points.shape[0], lamps), np.nan)} if lamps > 0 else {}
    if lamps == 1 and _coarse(exact_lamps, [0], points.shape[0]):
        grid = np.zeros((points.shape[0], 1), bool)
        light = _coarse_first_pass(direct, points, normals, pix, shape, frame, first, [0], None, grid,
                                   reuse["exact"], np.zeros((points.shape[0], 1, 3), np.float32), smooth)
        partial = grid[:, 0]
    else:
        light = direct(points, normals, frame, samples=first, partial=partial, **reuse, **_smooth(smooth))
    if exact_out is not None and lamps == 1:
        exact_out[:] = reuse["exact"]
    if not partial.any():
        return light, partial
    full = _grown(partial, pix, shape)
    redo = np.flatnonzero(full)
    again = {k: v[redo] for k, v in reuse.items()}
    light[redo] = _resample(direct, points, normals, guide, pix, shape, redo, light[redo], frame + SEED_OFFSET,
                            samples, first, camera, pool,
                            rough=None if rough is None else np.asarray(rough).reshape(points.shape[0], -1)[redo].sum(1),
                            **again, **_smooth(smooth, redo))
    if exact_out is not None and lamps == 1:
        exact_out[redo] = again["exact"]  # those the first pass's rays all missed, computed now
    return light, full


def sample_counts(rough: np.ndarray | None, first: int, samples: int) -> np.ndarray:
    """(r,) int shadow rays per lamp of r penumbra pixels whose lamp has the rough unshadowed
    light `rough` (r,) there (`lights.rough_lights`; None: `samples` each), after `first` rays.

    Why: a penumbra pixel's absolute error is its unshadowed light e times the visibility's
    noise, ~ e / sqrt(first + n) with n rays, and the image's relative L1 sums it over the
    pixels. For a budget of rays the sum is least with n ~ e^(2/3) (Lagrange); the counts are
    that, scaled to the sum `samples` rays everywhere expects, kept within MIN_SHARE..MAX_SHARE
    of `samples` (a dim penumbra keeps some rays: its noise shows after tone mapping) and
    rounded to the nearest TIER. Where the lamp's light varies little over the penumbra (a
    lamp far from its shadow) the counts are `samples` as before; where it falls off (a large
    lamp over the floor it shadows) fewer rays reach the same expected error. 640x360, the
    penumbra pass's rays: bunny_npm 0.74, spheres 0.79 / 0.83 (its two lamps), dragon_npm 0.59
    of before; Combined at the r32 x32 p32 s4 rung the same to 0.1% on the bundled scenes,
    bunny_npm and morse_apartment, dragon_npm 0.0493 -> 0.0496 (its lamp, 10 cm wide, sits
    among the scales it shadows: the bright pixels' error did not fall with their rays there).
    A floor of 0.25 instead of MIN_SHARE: bunny 0.69, dragon 0.41 of the rays, dragon 0.0500."""
    r = 0 if rough is None else rough.shape[0]
    counts = np.full(r if rough is not None else 0, samples, np.int64)
    e = None if rough is None else np.nan_to_num(np.asarray(rough, np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    if r < 2 or e.max() <= 0.0 or MAX_SHARE <= MIN_SHARE:
        return counts
    np.maximum(e, 0.0, out=e)
    lo, hi = samples * MIN_SHARE, samples * MAX_SHARE
    target = e.sum() / np.sqrt(first + samples)
    w = np.cbrt(e * e)
    lit = w > 0
    # n(lam) = clip(lam w, lo, hi): the expected error falls as lam grows; bisect on log lam.
    a, b = np.log(lo / w[lit].max()), np.log(hi / w[lit].min())
    for _ in range(40):
        mid = 0.5 * (a + b)
        n = np.clip(np.exp(mid) * w, lo, hi)
        if (e / np.sqrt(first + n)).sum() <= target:
            b = mid
        else:
            a = mid
    n = np.clip(np.exp(b) * w, lo, hi)
    tiers = samples * np.asarray(TIERS, np.float64)
    pick = np.abs(np.log(n)[:, None] - np.log(tiers)[None, :]).argmin(axis=1)
    return np.maximum(np.rint(tiers[pick]).astype(np.int64), 1)


def _resample(direct, points, normals, guide, pix, shape, redo, was, frame, samples, first, camera, pool,
              rough: np.ndarray | None = None, **kwargs) -> np.ndarray:
    """(r, 3) the light of the penumbra pixels `redo` (r,): more shadow rays per lamp
    (`direct(..., frame, **kwargs)`; `samples` each, or by `sample_counts` of the lamps' rough
    light `rough` (r,) there) averaged with the first pass's `was` (r, 3) by their counts, its
    visibility filtered on the pixels' surfaces (`guide` normals) when `camera` is given. The
    same samples' unshadowed light comes with them (exact where the ratio estimator applies): no
    second sampling pass for the filter's visibility. kwargs' exact= is written back as `direct`
    writes it."""
    open_light = np.zeros((redo.size, 3), np.float32)
    counts = sample_counts(rough, first, samples)
    if counts.size == 0 or (counts == samples).all():
        more = direct(points[redo], normals[redo], frame, samples=samples, unshadowed=open_light, **kwargs)
        mixed = (first * was + samples * more) / np.float32(first + samples)
    else:
        more = np.zeros((redo.size, 3), np.float32)
        for t, count in enumerate(np.unique(counts)):
            rows = np.flatnonzero(counts == count)
            part = {k: v[rows] if isinstance(v, np.ndarray) else v for k, v in kwargs.items()}
            got = np.zeros((rows.size, 3), np.float32)
            more[rows] = direct(points[redo[rows]], normals[redo[rows]], frame + t * TIER_SEED_OFFSET,
                                samples=int(count), unshadowed=got, **part)
            open_light[rows] = got
            if isinstance(kwargs.get("exact"), np.ndarray):
                kwargs["exact"][rows] = part["exact"]
        n = counts.astype(np.float32)[:, None]
        mixed = (first * was + n * more) / (np.float32(first) + n)
    if camera is not None and FILTER_PASSES > 0:
        mixed = filter_penumbra(mixed, open_light, points[redo], guide[redo], pix[redo], shape, camera, pool)
    return mixed


def _smooth(smooth: np.ndarray | None, rows: np.ndarray | None = None) -> dict:
    """`direct`'s smooth= keyword for the points of `rows` (None: all), or none without."""
    if smooth is None:
        return {}
    return {"smooth": smooth if rows is None else smooth[rows]}


def weak_lamps(rough: np.ndarray | None) -> np.ndarray | None:
    """(n, lamps) bool: the lamps under WEAK_SHARE of all the lamps' rough light at each point
    (non-finite rough light counts 0: a NaN-power lamp is weak everywhere), or None for none."""
    if rough is None:
        return None
    r = np.nan_to_num(np.asarray(rough, np.float32), nan=0.0, posinf=np.float32(1e30), neginf=0.0)
    np.maximum(r, 0.0, out=r)
    weak = r < np.float32(WEAK_SHARE) * r.sum(axis=1, keepdims=True)
    return weak if weak.any() else None


def _first_pass(direct, points, normals, frame, first, group, weak, partial, exact, share, smooth=None):
    """The first pass of the lamps `group` at every point -> (n, 3), filling partial (n, g),
    exact (n, g) and share (n, g, 3): one call for the group, or, where some of them are weak at
    some points (`weak` (n, g) bool), per lamp: FIRST_SAMPLES rays where it is not (seeded
    frame + j x LAMP_SEED_STRIDE: a lamp strong everywhere draws what a one-lamp frame draws) and
    one ray where it is (never a penumbra)."""
    if weak is None or not weak.any():
        return direct(points, normals, frame + group[0] * LAMP_SEED_STRIDE, samples=first, partial=partial,
                      exact=exact, per_lamp=share, lights=group, **_smooth(smooth))
    light = np.zeros((points.shape[0], 3), np.float32)
    for k, j in enumerate(group):
        strong = ~weak[:, k]
        seed = frame + j * LAMP_SEED_STRIDE
        for rows, count in ((np.flatnonzero(strong), first), (np.flatnonzero(~strong), 1)):
            if rows.size == 0:
                continue
            got = np.zeros((rows.size, 1), bool)
            known = exact[rows, k : k + 1]
            e = direct(points[rows], normals[rows], seed if count > 1 else seed + WEAK_SEED_OFFSET, samples=count,
                       partial=got, exact=known, lights=[j], **_smooth(smooth, rows))
            light[rows] += e
            share[rows, k] = e
            if count > 1:
                partial[rows, k] = got[:, 0]
                exact[rows, k] = known[:, 0]
    return light


def _per_lamp(direct, points, normals, pix, shape, frame, samples, first, camera, pool, lamps, smooth=None,
              per_lamp=None, rough=None, exact_lamps=None, exact_out=None):
    """`adaptive_direct` of several lamps, each lamp's penumbra on its own: a pixel re-samples
    only the lamps whose rays disagreed around it. Why: a room lit by several soft lamps (an
    area lamp and ceiling lamps with a radius) has some lamp's penumbra over most of the image,
    and re-sampling every lamp there costs `samples` rays per lamp where one or two are soft.
    The first pass shades LAMP_GROUP lamps per call (each lamp's share kept for the blend); lamp
    j's penumbra pass draws from frame + SEED_OFFSET + j * LAMP_SEED_STRIDE; each penumbra's
    visibility is filtered against its own lamp's unshadowed light. smooth, per_lamp : as
    `adaptive_direct`'s."""
    n = points.shape[0]
    guide = normals if smooth is None else smooth
    weak = weak_lamps(rough)
    light = np.zeros((n, 3), np.float32)
    full = np.zeros(n, bool)
    for g0 in range(0, lamps, LAMP_GROUP):
        group = list(range(g0, min(g0 + LAMP_GROUP, lamps)))
        partial = np.zeros((n, len(group)), bool)
        exact = np.full((n, len(group)), np.nan)
        share = np.zeros((n, len(group), 3), np.float32)
        group_weak = None if weak is None else weak[:, g0 : g0 + len(group)]
        if _coarse(exact_lamps, group, n):
            light += _coarse_first_pass(direct, points, normals, pix, shape, frame, first, group, group_weak,
                                        partial, exact, share, smooth)
        else:
            light += _first_pass(direct, points, normals, frame, first, group, group_weak, partial, exact, share,
                                 smooth)
        for k, j in enumerate(group):
            if not partial[:, k].any():
                continue
            grown = _grown(partial[:, k], pix, shape)
            if weak is not None:
                grown &= ~weak[:, j]  # their one ray is no first pass of FIRST_SAMPLES to average with
            full |= grown
            redo = np.flatnonzero(grown)
            was = share[redo, k]
            known = exact[redo, k : k + 1]
            mixed = _resample(direct, points, normals, guide, pix, shape, redo, was,
                              frame + SEED_OFFSET + j * LAMP_SEED_STRIDE, samples, first, camera, pool,
                              rough=None if rough is None else rough[redo, j],
                              exact=known, lights=[j], **_smooth(smooth, redo))
            exact[redo, k] = known[:, 0]
            light[redo] += mixed - was
            share[redo, k] = mixed
        if per_lamp is not None:
            per_lamp[:, g0 : g0 + len(group)] = share
        if exact_out is not None:
            exact_out[:, g0 : g0 + len(group)] = exact
    np.maximum(light, 0.0, out=light)  # the differences' rounding must not leave a dark pixel below 0
    return light, full


def _coarse(exact_lamps: np.ndarray | None, group: list[int], n: int) -> bool:
    """Whether the first pass of the lamps `group` over n pixels runs on probes."""
    return (exact_lamps is not None and n >= COARSE_MIN_PIXELS and len(group) <= COARSE_MAX_LAMPS
            and bool(np.all(np.asarray(exact_lamps)[group])))


def _coarse_first_pass(direct, points, normals, pix, shape, frame, first, group, weak, partial, exact, share,
                       smooth=None) -> np.ndarray:
    """`_first_pass` of the lamps `group` (all `lights.one_sample_exact`) over pixels `pix` of an
    image of `shape`, found from probes (COARSE_STEP): -> (n, 3), filling partial (n, g), exact
    (n, g) and share (n, g, 3) as it does.

    1. The probes (every COARSE_STEP-th pixel of every COARSE_STEP-th row) trace the first pass.
    2. Each lamp's probes that saw it wholly (light, no disagreeing ray) or not at all are eroded
       by COARSE_REACH probe steps: a pixel all of whose probes around it agree is a candidate
       (a probe missing there, background or another surface's edge, or in a penumbra, makes it
       none); a lamp weak at the pixel (`weak_lamps`) agrees with anything.
    3. Candidates take one sample per lamp (`direct(ratio_samples=1)`: the exact light times its
       ray's visibility) and keep it where every lamp's ray agrees with its probes (seen where
       they saw the lamp, unseen where they did not); a ray that disagrees (a thin shadow or gap
       between probes, a sample outside a round lamp) sends the pixel to the full first pass.
    4. The rest trace the full first pass. Penumbrae are then found as before, from `partial`."""
    n, g = points.shape[0], len(group)
    h, w = shape
    y, x = np.divmod(np.asarray(pix, np.int64), w)
    is_probe = (y % COARSE_STEP == 0) & (x % COARSE_STEP == 0)
    light = np.zeros((n, 3), np.float32)

    def full_pass(rows: np.ndarray, seed: int) -> None:
        if rows.size == 0:
            return
        got, known, part = partial[rows], exact[rows], share[rows]
        light[rows] = _first_pass(direct, points[rows], normals[rows], seed, first, group,
                                  None if weak is None else weak[rows], got, known, part,
                                  None if smooth is None else smooth[rows])
        partial[rows], exact[rows], share[rows] = got, known, part

    probes = np.flatnonzero(is_probe)
    full_pass(probes, frame)
    # Each lamp's agreeing probes on the probe grid, eroded: +1 all saw it, -1 none did, 0 neither.
    gh, gw = -(-h // COARSE_STEP), -(-w // COARSE_STEP)
    gy, gx = y // COARSE_STEP, x // COARSE_STEP
    verdict = np.zeros((n, g), np.int8)
    for k in range(g):
        seen = rows_above(share[probes, k], 0.0)
        calm = ~partial[probes, k]
        for sign, mask in ((1, calm & seen), (-1, calm & ~seen)):
            grid = np.zeros((gh, gw), bool)
            grid[gy[probes[mask]], gx[probes[mask]]] = True
            agreed = ~dilate(~grid, COARSE_REACH)
            verdict[agreed[gy, gx], k] = sign
    if weak is not None:
        verdict[weak & (verdict == 0)] = 2  # one ray whatever it sees (`_first_pass`)
    candidates = np.flatnonzero(~is_probe & (verdict != 0).all(axis=1))
    kept = np.zeros(n, bool)
    if candidates.size:
        known = exact[candidates]
        part = np.zeros((candidates.size, g, 3), np.float32)
        one = direct(points[candidates], normals[candidates], frame + CHECK_SEED_OFFSET, samples=1,
                     exact=known, per_lamp=part, lights=group, ratio_samples=1, **_smooth(smooth, candidates))
        saw = rows_above(part.reshape(-1, 3), 0.0).reshape(part.shape[:2])
        v = verdict[candidates]
        agree = np.where(v == 1, saw, np.where(v == -1, ~saw, True)).all(axis=1)
        good = candidates[agree]
        kept[good] = True
        light[good] = one[agree]
        share[good] = part[agree]
        exact[good] = known[agree]
        partial[good] = False
    full_pass(np.flatnonzero(~is_probe & ~kept), frame + REST_SEED_OFFSET)
    return light


def _grown(partial: np.ndarray, pix: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(n,) bool: the pixels `pix` within DILATE pixels of a `partial` one (in an image of `shape`)."""
    h, w = shape
    image = np.zeros(h * w, bool)
    image[pix[partial]] = True
    return dilate(image.reshape(h, w), DILATE).reshape(-1)[pix]


#: A-trous passes over the light of emitters sampled by power before their shadows
#: (`filter_emitter_light`), taps 1, 2, 4 pixels apart.
EMITTER_OPEN_PASSES = 1


def filter_emitter_light(light: np.ndarray, open_light: np.ndarray, cones: np.ndarray, points: np.ndarray,
                         normals: np.ndarray, pix: np.ndarray, shape: tuple[int, int], camera,
                         pool=None) -> np.ndarray:
    """(n, 3) the light of emitters sampled by power (`emitters.MeshLights._block`: many
    triangles, no closed form) at the pixels `pix`, denoised: the samples' light without their
    shadows (open_light (n, 3), a smooth function of the receiver's place and normal) averaged
    over EMITTER_OPEN_PASSES a-trous passes on the same surfaces, times the samples' visibility
    (light over open_light) averaged as a penumbra's (`filter_penumbra`), plus the compact
    emitters' cone light (cones (n, 3), part of light; kept per pixel).

    Why: 16 samples per pixel of a sign in 98 triangles left its wall and floor grainy (320x180
    against Cycles 1024 spp, Diffuse Direct rel L1 0.39; Cycles 16 spp + OIDN denoises its
    own). Splitting visibility from the unshadowed light keeps the shadows' edges where the
    filter reaches far. camera None (an orthographic view: no eye to scale the planes' distances
    by): the samples' light as it is."""
    if camera is None:
        return np.asarray(light, np.float32)
    sampled = np.maximum(light - cones, 0.0)
    return filter_penumbra(sampled, open_light, points, normals, pix, shape, camera, pool,
                           open_passes=EMITTER_OPEN_PASSES) + cones


def filter_penumbra(light: np.ndarray, open_light: np.ndarray, points: np.ndarray, normals: np.ndarray,
                    pix: np.ndarray, shape: tuple[int, int], camera, pool=None, open_passes: int = 0) -> np.ndarray:
    """(n, 3) the penumbra pixels' light with its visibility (light / the unshadowed light)
    averaged over their neighbours on the same surface (`pixel_gather.filter_at_pixels`: plane and
    normal guided a-trous passes), times their own unshadowed light: 24 shadow rays leave a
    large lamp's soft shadow grainy (Cycles' image is denoised); the shading's own detail (the
    unshadowed term) is kept per pixel. open_passes > 0: the unshadowed light is itself an
    estimate (`filter_emitter_light`), averaged that many passes on its surfaces first."""
    seen = open_light.max(axis=1) > 0
    visibility = np.where(seen[:, None], light / np.maximum(open_light, np.float32(1e-30)), 0.0).astype(np.float32)
    out = filter_at_pixels(visibility, seen, points, normals, pix, shape, camera, FILTER_PASSES, pool)
    if open_passes > 0:
        open_light = filter_at_pixels(np.asarray(open_light, np.float32), seen, points, normals, pix, shape, camera,
                                      open_passes, pool)
    return np.where(seen[:, None], open_light * np.clip(out, 0.0, 1.0), light).astype(np.float32)

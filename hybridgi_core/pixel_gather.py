"""Per-pixel final-gather rays at the GI resolution: the first bounce exact per pixel.

The cache gather (`evaluate.gather`) interpolates cells of ~1/48 of the scene, so light that
varies within a cell (contacts, thin posts, under eaves) is smeared, and the screen-space pass
that stood in for the missing near field sees only what the screen shows. Here every GI pixel
traces `rays` cosine-distributed rays of its own (stratified: Hammersley with a per-pixel
Cranley-Patterson rotation, deterministic per frame). Hits are shaded as probe-ray hits are
(`update.py`): lamp light through shadow rays, the cache read at the hit for the further bounces
(`evaluate.HitLookup`), emission; misses read the world (`World.radiance`). So sky light and
emitters (Cycles' Diffuse Direct) get the pixel's own visibility, the first bounce is exact per
pixel, and AO is Cycles' definition (cosine-weighted share of rays unblocked within the World's
AO distance).

Noise: the cache gather's radiance SH at the pixel is a control variate. With cosine sampling,
E = pi/N sum L(w_i) estimates irradiance, and the same sum over the cache's band-limited SH
radiance L_c estimates exactly the cache's own irradiance E_c (the clamped-cosine convolution of
an L2 function is exact in L2). So

    E_hat = E_c + pi/N sum (L(w_i) - L_c(w_i))

is unbiased for the ray-traced irradiance whatever the cache holds, and its noise is only that of
the difference: small where the cache is right (open, smooth light), where the rays add nothing,
and the signal itself where the cache is wrong (a contact's occluder, a post's shadow). The
residual E_hat - E_c is then filtered edge-aware at the GI resolution (`filter_residual`:
a-trous passes guided by the pixels' planes and normals), so the cache's smooth part is never
blurred and the correction stays on the surface it belongs to.

numpy + embreex only (bpy-free; the raster pipeline uploads the result, `raster/frame.py`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from . import sh
from .evaluate import HitLookup, corner_weights
from .lights import _onb, concentric_disk, direct_irradiance, stratified_uv
from .sampling import frame_rng
from .settings import AO_ONLY, MULTI_BOUNCE

#: Rec.709 luminance weights (the colour channels' filter guide).
LUMA = np.array([0.2126, 0.7152, 0.0722], np.float32)

#: Rays per work item (pixels x rays): fixed, so the result does not depend on the thread count.
CHUNK_RAYS = 65536
#: Seed offset of the pixel rays' stream (the cache uses seed, the direct light seed + 1).
SEED_OFFSET = 2
#: Standard deviations of the noise within which a filter tap counts as the same signal.
NOISE_SIGMA = 2.0
#: B3-spline taps of one a-trous pass (5 x 5, Dammertz et al. 2010).
_B3 = np.array([1.0, 4.0, 6.0, 4.0, 1.0], np.float32) / 16.0
#: Fewest rows of own pixels a band must add to its halos for the filter to split the image.
BAND_MIN_ROWS = 32


@dataclass
class PixelGI:
    """Irradiance (W/m^2) at n GI pixels from their own rays.

    direct (n, 3): sky and emitters seen straight (Cycles' Diffuse Direct, less lamps);
    indirect (n, 3): light reflected by surfaces (all bounces; further ones from the cache);
    ao (n,): cosine-weighted share of rays unblocked within the AO distance.
    cache_* : the cache gather at the same points (the control variate's own value).
    """

    direct: np.ndarray
    indirect: np.ndarray
    ao: np.ndarray
    cache_direct: np.ndarray
    cache_indirect: np.ndarray
    cache_ao: np.ndarray
    variance: np.ndarray | None = None  # (n, 2) of the means of luminance (direct + indirect) and AO
    rays: int = 0
    steps_ms: dict[str, float] = field(default_factory=dict)

    def channels(self) -> tuple[np.ndarray, np.ndarray]:
        """((n, 7) estimate, (n, 7) cache) as direct rgb | indirect rgb | ao columns."""
        est = np.concatenate([self.direct, self.indirect, self.ao[:, None]], axis=1)
        cache = np.concatenate([self.cache_direct, self.cache_indirect, self.cache_ao[:, None]], axis=1)
        return est, cache


def cosine_directions(normals: np.ndarray, rays: int, rng: np.random.Generator) -> np.ndarray:
    """(n, rays, 3) float32 cosine-distributed unit directions around unit normals (n, 3).

    Each pixel's set is a Hammersley set shifted by its own random offset (`lights.stratified_uv`),
    mapped to the disc area-preserving (`concentric_disk`) and lifted to the hemisphere (Malley).
    """
    n = normals.shape[0]
    u, v = stratified_uv(rng, n, rays)
    a, b = concentric_disk(u, v)
    c = np.sqrt(np.maximum(np.float32(1.0) - a * a - b * b, np.float32(0.0)))
    nx, ny, nz = (np.asarray(normals[:, k], np.float32)[:, None] for k in range(3))
    t1, t2 = _onb(nx, ny, nz)
    d = np.empty((n, rays, 3), np.float32)
    for k in range(3):
        d[..., k] = a * t1[k] + b * t2[k] + c * (nx, ny, nz)[k]
    return d


def cache_sh_at(cache, points: np.ndarray, normals: np.ndarray, corner_visible: np.ndarray | None):
    """The cache gather's blended radiance SH at points: (direct (n, K, 3), indirect (n, K, 3),
    ao (n, K), covered (n,) bool), with the gather's own weights (`evaluate.corner_weights`)."""
    flats, w = corner_weights(cache, points, normals, True, corner_visible)
    n, k = flats.shape[0], cache.settings.sh_coeffs
    wr = w[:, None, :]  # (n, 1, 8) @ (n, 8, .): batched GEMMs, far faster than einsum's loops
    sh_d = np.matmul(wr, cache.sh_direct[flats].reshape(n, 8, k * 3)).reshape(n, k, 3)
    sh_i = np.matmul(wr, cache.sh_indirect[flats].reshape(n, 8, k * 3)).reshape(n, k, 3)
    sh_a = np.matmul(wr, cache.ao_sh[flats]).reshape(n, k)
    return sh_d, sh_i, sh_a, w.sum(axis=1) > 0


def trace_pixels(system, points: np.ndarray, normals: np.ndarray, rays: int, frame: int,
                 corner_visible: np.ndarray | None = None) -> PixelGI:
    """Per-pixel gather at points (n, 3) with unit normals (n, 3) of `system` (a GISystem):
    `rays` rays each, the cache's SH as control variate (module docstring). corner_visible :
    (n, 8) bool occlusion of the 8 neighbour cells (`GISystem.corner_visibility`), as the image
    gather reads the cache."""
    cache, s = system.cache, system.settings
    points = np.ascontiguousarray(points, np.float32)
    normals = np.array(normals, np.float32).reshape(-1, 3)
    # Rays are built from the normal without checks (`trusted`): a pixel without a usable normal
    # (a degenerate triangle's zero) gathers around +Z rather than sending zero directions.
    length = np.linalg.norm(normals, axis=1)
    bad = ~(np.abs(length - 1.0) < 0.1)
    if bad.any():
        normals[bad] = (0.0, 0.0, 1.0)
    n = points.shape[0]
    steps: dict[str, float] = {}
    # Columns: residual direct rgb, indirect rgb, AO | luminance and AO variances | the cache's
    # direct rgb, indirect rgb, AO. Everything per chunk of pixels on the worker pool, so no
    # per-pixel (n, 8, K, 3) temporaries exist for the whole image at once.
    out = np.zeros((n, 16), np.float32)
    if n:
        lookup = HitLookup(cache, bounced=s.indirect_quality == MULTI_BOUNCE) if rays > 0 else None
        per = max(1, CHUNK_RAYS // max(rays, 8))
        starts = range(0, n, per)
        vis = (lambda a: None) if corner_visible is None else (lambda a: corner_visible[a:a + per])
        jobs = [system.updater.pool.submit(_chunk, system, lookup, points[a:a + per], normals[a:a + per], vis(a),
                                           rays, frame_rng(s.seed + SEED_OFFSET, frame * 7919 + i))
                for i, a in enumerate(starts)]
        for a, job in zip(starts, jobs, strict=True):
            values, times = job.result()
            out[a:a + per] = values
            for k, v in times.items():
                steps[k] = steps.get(k, 0.0) + v
    # Residual means (estimate - the cache along the same rays) plus the cache's exact integrals.
    cd, ci, ca = out[:, 9:12], out[:, 12:15], out[:, 15]
    return PixelGI(out[:, 0:3] + cd, out[:, 3:6] + ci, out[:, 6] + ca, cd, ci, ca, variance=out[:, 7:9],
                   rays=n * rays, steps_ms=steps)


def _chunk(system, lookup: HitLookup | None, p, nrm, corner_visible, rays, rng):
    """Worker: (m, 16) of m pixels: mean residuals pi/N sum (L - L_cache) (direct rgb, indirect
    rgb, AO as 1/N sum (v - V_cache)), the variances of the luminance and AO means, and the
    cache gather's direct rgb, indirect rgb and AO; and step times."""
    times = {}
    s = system.settings
    tic = time.perf_counter()
    m = p.shape[0]
    res = np.zeros((m, 16), np.float32)
    sh_d, sh_i, sh_a, covered = cache_sh_at(system.cache, p, nrm, corner_visible)
    # The cache's own irradiance at the pixels, what the GPU gather reads (unclamped here: the
    # control variate must be the exact integral of the SH used below).
    res[:, 9:12] = sh.irradiance(sh_d, nrm)
    res[:, 12:15] = sh.irradiance(sh_i, nrm)
    res[:, 15] = np.where(covered, sh.irradiance(sh_a[..., None], nrm)[:, 0] / np.float32(np.pi), np.float32(1.0))
    times["cache_sh"] = (time.perf_counter() - tic) * 1e3
    if rays <= 0:
        return res, times
    scene = system.updater.scene
    tracer = system.tracer
    eps = np.float32(tracer.epsilon)
    tic = time.perf_counter()
    dirs = cosine_directions(nrm, rays, rng).reshape(-1, 3)
    origins = np.repeat(p + nrm * eps, rays, axis=0)
    tfar = np.float32(s.ray_length) if s.ray_length > 0 else np.float32(np.inf)
    hits = tracer.intersect(origins, dirs, tfar, trusted=True)
    times["trace"] = (time.perf_counter() - tic) * 1e3

    tic = time.perf_counter()
    k = sh_d.shape[1]
    hit = np.flatnonzero(hits.prim >= 0)
    radiance = np.zeros((m * rays, 6), np.float32)  # direct rgb (sky, emitters) | reflected rgb
    world = scene.world
    if s.indirect_quality != AO_ONLY:
        if world.any:
            radiance[:, 0:3] = world.radiance(dirs)
        if hit.size:
            surf = scene.surfaces.probe_hits(hits.prim[hit], hits.u[hit], hits.v[hit], dirs[hit])
            radiance[hit, 0:3] = surf.emission
            position = dirs[hit] * hits.t[hit, None]
            position += origins[hit]
            ts = time.perf_counter()
            e_in = direct_irradiance(scene.lights, position, surf.normal, tracer, rng,
                                     samples=s.light_samples, epsilon=float(eps), sun_disc=False)
            times["shadow"] = (time.perf_counter() - ts) * 1e3
            # Further bounces read the cache at the hit, as probe-ray hits do.
            e_in += lookup.irradiance(position, surf.normal).T
            radiance[hit, 3:6] = e_in * surf.brdf
    visible = (hits.t > s.ao_distance).astype(np.float32)
    # Control variate: the cache's radiance SH along the same rays. Linear in the SH, so its mean
    # over a pixel's rays is the SH of the pixel's mean basis vector (no per-ray products).
    y = sh.basis(dirs, 2 if k == 9 else 1).reshape(m, rays, k)
    y_mean = y.mean(axis=1)  # (m, K)
    cv_d = np.einsum("mk,mkc->mc", y_mean, sh_d)
    cv_i = np.einsum("mk,mkc->mc", y_mean, sh_i)
    cv_a = np.where(covered, np.einsum("mk,mk->m", y_mean, sh_a), np.float32(1.0))  # uncovered: ao_c = 1
    r = radiance.reshape(m, rays, 6)
    res[:, 0:3] = (r[..., 0:3].mean(axis=1) - cv_d) * np.float32(np.pi)
    res[:, 3:6] = (r[..., 3:6].mean(axis=1) - cv_i) * np.float32(np.pi)
    res[:, 6] = visible.reshape(m, rays).mean(axis=1) - cv_a
    # Variance of the two filter guides' means (luminance of all light, AO), from the rays' own
    # spread around their control variate: what the filter may average away as noise.
    luma = LUMA.astype(np.float32)
    lum = (r[..., 0:3] + r[..., 3:6]) @ luma - np.matmul(y, ((sh_d + sh_i) @ luma)[..., None])[..., 0]
    ao = visible.reshape(m, rays) - np.where(covered[:, None], np.matmul(y, sh_a[..., None])[..., 0], np.float32(1.0))
    of_mean = np.float32(1.0 / max(rays - 1, 1))  # sample variance / N
    res[:, 7] = lum.var(axis=1) * np.float32(np.pi**2) * of_mean
    res[:, 8] = ao.var(axis=1) * of_mean
    times["shade"] = (time.perf_counter() - tic) * 1e3 - times.get("shadow", 0.0)
    return res, times


def filter_residual(residual: np.ndarray, position: np.ndarray, normal: np.ndarray, valid: np.ndarray,
                    camera: np.ndarray, passes: int = 3, plane_sigma: float = 0.02,
                    normal_power: float = 8.0, variance: np.ndarray | None = None,
                    noise_sigma: float = NOISE_SIGMA, pool=None) -> np.ndarray:
    """Edge-aware a-trous filter of an (h, w, 7) image of residuals (direct rgb, indirect rgb, AO)
    at the GI resolution.

    position (h, w, 3) world, normal (h, w, 3) unit, valid (h, w) bool (background pixels are
    neither read nor written), camera (3,) the eye (plane distances are measured as a share of
    the view distance, as the bilateral upsampling does). Pass i uses taps 2^i pixels apart;
    a tap's weight is the B3 spline x exp(-(plane distance / (plane_sigma x view distance))^2)
    x max(0, n_p . n_q)^normal_power: a tap on another surface, or on the same surface's other
    side of a crease, does not count.

    variance : (h, w, 2) variances of the pixels' luminance (of direct + indirect) and AO, or
    None. Given, taps also stop where the residual differs by more than noise_sigma standard
    deviations of the noise (SVGF, Schied et al. 2017; the variance filtered along with the
    image): a contact's correction on a plane stays at the contact instead of spreading over
    the plane, while the noise around it averages out.

    pool : an executor; given, bands of rows are filtered on it side by side (each with a halo
    of the rows the passes reach, so the result is the same as in one piece).
    """
    h, w = valid.shape
    halo = 2 * ((1 << max(passes, 0)) - 1)
    if pool is not None and passes > 0 and h >= 4 * halo + BAND_MIN_ROWS:
        return _filter_in_bands(pool, halo, residual, position, normal, valid, camera, passes, plane_sigma,
                                normal_power, variance, noise_sigma)
    out = np.where(valid[..., None], residual, 0.0).astype(np.float32)
    if passes <= 0:
        return out
    # Channel-first planes: every tap is a few whole-image multiply-adds on contiguous rows.
    pos = np.ascontiguousarray(np.moveaxis(np.asarray(position, np.float32), -1, 0))
    nrm = np.ascontiguousarray(np.moveaxis(np.asarray(normal, np.float32), -1, 0))
    img = np.ascontiguousarray(np.moveaxis(out, -1, 0))
    var = None
    if variance is not None:
        var = np.ascontiguousarray(np.moveaxis(np.where(valid[..., None], variance, 0.0), -1, 0), np.float32)
    dist = np.sqrt(sum((pos[k] - np.float32(camera[k])) ** 2 for k in range(3)))
    inv_sigma = np.where(valid, 1.0 / np.maximum(plane_sigma * dist, 1e-12), 0.0).astype(np.float32)
    # p . n_p once: the plane distance of a tap q is q . n_p - p . n_p.
    own = pos[0] * nrm[0] + pos[1] * nrm[1] + pos[2] * nrm[2]
    vf = valid.astype(np.float32)
    k2 = np.float32(noise_sigma**2)
    for i in range(passes):
        step = 1 << i
        pad = 2 * step
        widths = ((0, 0), (pad, pad), (pad, pad))
        pr, pp, pn = (np.pad(a, widths) for a in (img, pos, nrm))
        pv = np.pad(vf, pad)
        acc = np.zeros_like(img)
        wsum = np.zeros((2, h, w), np.float32)
        if var is not None:
            guide = np.stack([(img[0:3] + img[3:6]).transpose(1, 2, 0) @ LUMA, img[6]])
            pg, pvar = np.pad(guide, widths), np.pad(var, widths)
            acc_var = np.zeros_like(var)
        for dy in range(5):
            for dx in range(5):
                ys = slice(pad + (dy - 2) * step, pad + (dy - 2) * step + h)
                xs = slice(pad + (dx - 2) * step, pad + (dx - 2) * step + w)
                qp, qn = pp[:, ys, xs], pn[:, ys, xs]
                plane = (qp[0] * nrm[0] + qp[1] * nrm[1] + qp[2] * nrm[2] - own) * inv_sigma
                cos = np.maximum(qn[0] * nrm[0] + qn[1] * nrm[1] + qn[2] * nrm[2], 0.0)
                wt = _power(cos, normal_power)
                wt *= pv[ys, xs] * np.float32(_B3[dy] * _B3[dx])
                if var is None:
                    wt *= np.exp(-plane * plane)
                    acc += wt * pr[:, ys, xs]
                    wsum += wt
                    continue
                # One weight for the colour channels (luminance guide), one for AO; the plane
                # and range terms share one exp.
                diff = pg[:, ys, xs] - guide
                wt2 = wt * np.exp(-(diff * diff) / (k2 * (var + pvar[:, ys, xs]) + np.float32(1e-12)) - plane * plane)
                acc[0:6] += wt2[0] * pr[0:6, ys, xs]
                acc[6] += wt2[1] * pr[6, ys, xs]
                acc_var += wt2 * wt2 * pvar[:, ys, xs]
                wsum += wt2
        total = np.maximum(wsum, np.float32(1e-12))
        img[0:6] = acc[0:6] / total[0]
        img[6] = acc[6] / total[1]
        img *= vf
        if var is not None:
            var = acc_var / (total * total) * vf
    return np.ascontiguousarray(np.moveaxis(img, 0, -1))


def _power(x: np.ndarray, exponent: float) -> np.ndarray:
    """x ** exponent, by squarings when the exponent is a power of two (the default 8: three
    multiplies instead of a transcendental pow per tap)."""
    e = float(exponent)
    if e >= 1 and e == int(e) and int(e) & (int(e) - 1) == 0:
        y = x
        for _ in range(int(e).bit_length() - 1):
            y = y * y
        return y
    return x**e


def _filter_in_bands(pool, halo, residual, position, normal, valid, camera, passes, plane_sigma, normal_power,
                     variance, noise_sigma):
    """`filter_residual` over two bands of rows on the pool, each with `halo` extra rows."""
    h = valid.shape[0]
    cuts = [0, h // 2, h]
    jobs = []
    for a, b in zip(cuts[:-1], cuts[1:], strict=True):
        lo, hi = max(a - halo, 0), min(b + halo, h)
        rows = slice(lo, hi)
        jobs.append((a - lo, b - lo, pool.submit(
            filter_residual, residual[rows], position[rows], normal[rows], valid[rows], camera, passes,
            plane_sigma, normal_power, None if variance is None else variance[rows], noise_sigma)))
    return np.concatenate([job.result()[i:j] for i, j, job in jobs], axis=0)


def gi_images(system, position_lo: np.ndarray, normal_lo: np.ndarray, pix: np.ndarray, points: np.ndarray,
              normals: np.ndarray, corner_visible: np.ndarray, view: np.ndarray, frame: int, rays: int,
              passes: int = 3, plane_sigma: float = 0.02, normal_power: float = 8.0):
    """The GI resolution's textures from pixel rays: (gi_indirect (h, w, 4) rgb indirect + a AO,
    gi_direct (h, w, 4) rgb sky/emitter irradiance, PixelGI), rows as the read-back's (pix indexes
    its flattened pixels), background as the GPU gather writes it (indirect 0 with AO 1)."""
    h, w = position_lo.shape[:2]
    gi = trace_pixels(system, points, normals, rays, frame, corner_visible)
    tic = time.perf_counter()
    est, cache = gi.channels()
    valid = np.zeros(h * w, bool)
    valid[pix] = True
    res = np.zeros((h * w, 7), np.float32)
    res[pix] = est - cache
    pos = np.zeros((h * w, 3), np.float32)
    pos[pix] = points
    nrm = np.zeros((h * w, 3), np.float32)
    nrm[pix] = normals
    camera = np.linalg.inv(np.asarray(view, np.float64))[:3, 3].astype(np.float32)
    var = np.zeros((h * w, 2), np.float32)
    var[pix] = gi.variance
    filtered = filter_residual(res.reshape(h, w, 7), pos.reshape(h, w, 3), nrm.reshape(h, w, 3),
                               valid.reshape(h, w), camera, passes, plane_sigma, normal_power,
                               variance=var.reshape(h, w, 2), pool=system.updater.pool).reshape(h * w, 7)
    gi.steps_ms["filter"] = (time.perf_counter() - tic) * 1e3
    value = np.zeros((h * w, 7), np.float32)
    value[pix] = cache + filtered[pix]
    indirect = np.zeros((h * w, 4), np.float32)
    indirect[:, 3] = 1.0
    indirect[pix, 0:3] = np.maximum(value[pix, 3:6], 0.0)
    indirect[pix, 3] = np.clip(value[pix, 6], 0.0, 1.0)
    direct = np.zeros((h * w, 4), np.float32)
    direct[pix, 0:3] = np.maximum(value[pix, 0:3], 0.0)
    return indirect.reshape(h, w, 4), direct.reshape(h, w, 4), gi

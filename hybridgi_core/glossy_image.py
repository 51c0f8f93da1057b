"""The glossy light of an image's pixels in two parts, as final renders compute it
(`FramePipeline._glossy`: the same `GISystem.glossy`, `glossy_color` and `cache_reflection` calls).

Final renders compute a frame's glossy light once at the centre raster's pixels (`frame_glossy`:
the lamps' light sampled where it is noisy and filtered, traced reflections at every roughness,
the cache's split-sum estimate only where a pixel's rays found nothing). The viewport's worker computes the two parts
at its GI pixels while a view is new and refreshes each on its own clock: the lamps' part
(`lamp_glossy`, shadow rays, noisy: averaged over passes while the view holds still, traced again
at once after a lamp edit) and the cache's split-sum part (`cache_glossy`, no rays: read again
when the cache changes); once a still view has its pixel rays it takes `frame_glossy` at every
pixel too, so its settled image is the final render's.

Pure numpy (no bpy, no gpu): the worker thread calls it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import glossy, glossy_ltc
from .evaluate import HitLookup
from .glossy import cache_reflection, glossy_color
from .glossy_noise import adaptive_lamp_glossy
from .pixel_gather import LUMA
from .reflection import bsdf_lamps, filter_lamp_glossy, filter_reflections, traced_reflection, traced_share
from .rows import rows_above
from .settings import MULTI_BOUNCE
from .specular_aa import RAY_WIDEN_SHARE, footprint_alpha2, widened_roughness

#: Glossy colour below which a channel's lamp light is filtered as it is (`finish_glossy`).
DEMODULATE_FLOOR = 1e-4


def has_glossy(system) -> bool:
    """Whether any material's glossy lobes reflect anything (`GlossyMaterials.reflects`; else nothing to compute)."""
    return hasattr(system, "glossy") and bool(system.glossy_materials.reflects.any())


def material_rows(material: np.ndarray, mats=None) -> np.ndarray:
    """(n,) int64 glossy rows from G-buffer `material` texels (index + 1, 0 = background; a
    material with a Metallic texture adds half its texel's metallic; one with a Roughness texture
    adds (variant + 0.5) / variants, its metallic step x `glossy.ROUGHNESS_STEPS` + its roughness
    step: `raster/gbuffer_frag.glsl`). With `mats` (`glossy.GlossyMaterials`), such a pixel's row
    is its material's variant nearest its texels; without, the material's own row. With `mats`,
    a texel of a material it does not know (a G-buffer drawn from another material list than the
    system's: the viewport's worker may still hold the one before an edit) gets -1, as the
    background: it reflects nothing."""
    r = np.asarray(material, np.float32).reshape(-1)
    whole = np.floor(r)
    rows = whole.astype(np.int64) - 1
    if mats is None:
        return rows
    rows = np.where((rows >= 0) & (rows < len(mats.layers)), rows, -1)
    variants = getattr(mats, "variants", None)
    if variants is None or not (variants >= 0).any():
        return rows
    known = (rows >= 0) & (rows < variants.shape[0])
    first = np.where(known, variants[np.clip(rows, 0, variants.shape[0] - 1)], -1)
    mapped = first >= 0
    frac = r - whole
    steps = glossy.METALLIC_STEPS - 1
    step = np.clip(np.rint(frac * 2.0 * steps), 0, steps).astype(np.int64)
    counts = getattr(mats, "variant_steps", None)
    if counts is not None:
        count = counts[np.clip(rows, 0, counts.shape[0] - 1)]
        rough = mapped & (count[:, 1] > 1)
        if rough.any():
            total = count[rough, 0] * count[rough, 1]
            step[rough] = np.clip(np.floor(frac[rough] * total), 0, total - 1).astype(np.int64)
    rows[mapped] = first[mapped] + step[mapped]
    return rows


def directions_to_eye(points: np.ndarray, eye) -> np.ndarray:
    """(n, 3) unit directions from points to the camera; eye = `gbuffer.camera_eye` (w = 1: a
    position, w = 0: an orthographic camera's direction)."""
    eye = np.asarray(eye, np.float64)
    points = np.asarray(points).reshape(-1, 3)
    to_eye = eye[:3] - points * eye[3] if eye[3] > 0.5 else np.broadcast_to(eye[:3], points.shape)
    return to_eye / np.maximum(np.linalg.norm(to_eye, axis=1, keepdims=True), 1e-30)


@dataclass
class GlossyLight:
    """Glossy light at n receivers, each (n, 3) float32: `direct` the lamps', sky's and emitters'
    reflection (Glossy Direct, colour applied; the cache's split sum: the sky's and emitters'
    alone), `colour` Glossy Color at the view angle, `bounced` other surfaces' light before its
    colour (Glossy Indirect / Glossy Color)."""

    direct: np.ndarray
    colour: np.ndarray
    bounced: np.ndarray

    @property
    def radiance(self) -> np.ndarray:
        """(n, 3) what the deferred pass adds to Combined: direct + colour x bounced."""
        return self.direct + self.colour * self.bounced


def lamp_glossy(system, points, normals, to_eye, rows, frame: int, samples: int) -> np.ndarray:
    """(n, 3) float32 lamp radiance the glossy lobes reflect to the eye (`GISystem.glossy`)."""
    return system.glossy(points, normals, to_eye, rows, frame, samples=samples)


def cache_glossy(system, points, normals, to_eye, rows) -> GlossyLight:
    """The cache's split-sum `GlossyLight` at the receivers: Glossy Color and
    `glossy.cache_reflection` of the cache as it is now (receivers without a glossy colour read no
    cache)."""
    n = np.asarray(points).reshape(-1, 3).shape[0]
    normals = np.asarray(normals).reshape(-1, 3)
    mu = np.clip(np.einsum("ij,ij->i", normals, to_eye), 0.0, 1.0)
    colour = glossy_color(system.glossy_materials, rows, mu)
    sky = np.zeros((n, 3), np.float32)
    bounced = np.zeros((n, 3), np.float32)
    lit = np.flatnonzero(rows_above(colour, 0.0))
    if lit.size:
        rough = system.glossy_materials.rough[rows[lit]]
        s, b = cache_reflection(system.cache, np.asarray(points).reshape(-1, 3)[lit], normals[lit], to_eye[lit], rough)
        sky[lit] = colour[lit] * s
        bounced[lit] = b
    return GlossyLight(sky, colour, bounced)


def frame_glossy(system, points, normals, pix, shape: tuple[int, int], material, albedo, irradiance, view, eye,
                 frame: int, samples: int, reflection_rays: int, lookup: HitLookup | None = None,
                 pool=None, between=None, tint: np.ndarray | None = None,
                 visibility: np.ndarray | None = None, screen=None) -> GlossyLight:
    """The glossy light of an image's receivers as final renders compute it: the lamps' light
    (`glossy_noise.adaptive_lamp_glossy`: `samples` per lamp only where a first pass is noisy
    against the receiver's diffuse lamp light, then `reflection.filter_lamp_glossy`) and the light
    the lobes reflect (`reflection.traced_reflection`, `reflection_rays` per receiver, filtered
    edge-aware over the image, at every roughness (`reflection.TRACE_ROUGHNESS`; the cache's
    split-sum estimate `glossy.cache_reflection` where the rays found nothing); area lamps in lobes much
    narrower than they are are left to those rays, `reflection.bsdf_lamps`).

    points, normals : (n, 3) receivers (unit normals), pix : (n,) their flat pixels in an image of
    `shape` (h, w); material : (n,) G-buffer material texels (`material_rows`); albedo : (n, 3)
    diffuse colour and irradiance : (n, 3) diffuse lamp irradiance (their product is the noise
    scale of the lamp samples); view : the camera's 4x4 view matrix; eye : `gbuffer.camera_eye`'s
    (x, y, z, w); lookup : the cache's HitLookup to reuse (None: built here when rays are traced);
    between : called between its steps (the viewport's worker raises there when an edit or a
    newer view waits); tint : (n, 2) the textured metals' texel coordinates per receiver (the
    G-buffer albedo and emission targets' alphas: `glossy.metal_tint_basis`), or None: the
    metallic lobes' share of the light takes the texel's colour over the mean's. visibility :
    (n, L) each lamp's visibility at the receivers (`glossy_ltc.visibility`) or None: given, the
    area lamps' light of the lobes `glossy_ltc` covers is its closed form, shadowed by it, and
    lamp sampling takes the rest. screen : the frame's `screen_light.ScreenLight` or None (the
    reflection rays' hits the image shows read their lamp light there). Pure numpy: the final
    render's pipeline and the viewport's worker both call it. `begin_glossy` and `finish_glossy`
    in one: a final render runs the first on its stage thread and the second, whose filters are
    GPU passes there, on its own."""
    return finish_glossy(begin_glossy(system, points, normals, pix, shape, material, albedo, irradiance, view, eye,
                                      frame, samples, reflection_rays, lookup, pool, between, tint, visibility,
                                      screen))


@dataclass
class GlossyDraft:
    """`begin_glossy`'s unfiltered glossy light, what `finish_glossy` filters and blends.

    direct : (n, 3) the lamps' sampled light (filtered at `lamp_rows`, whose roughness is
    `lamp_rough`), colour : (n, 3) Glossy Color, exact : (n, 3) the closed forms' lamp light;
    lit : the receivers whose lobes reflect, traced : (t,) the rows of lit whose reflection rays'
    light (t, 3) x 2 `ray_direct`, `ray_indirect` (`ray_total` (t,) found some) is filtered, with
    their weight `share` (t,) against the cache's sky and bounced light (lit's, (l, 3) each) and
    the area lamps the rays met `lamp` (l, 3)."""

    direct: np.ndarray
    colour: np.ndarray
    exact: np.ndarray
    lit: np.ndarray
    lamp_rows: np.ndarray
    lamp_rough: np.ndarray
    traced: np.ndarray
    ray_direct: np.ndarray
    ray_indirect: np.ndarray
    ray_total: np.ndarray
    share: np.ndarray
    sky: np.ndarray
    bounced: np.ndarray
    lamp: np.ndarray
    points: np.ndarray
    normals: np.ndarray
    pix: np.ndarray
    shape: tuple
    view: np.ndarray
    pool: object
    between: object
    tint: tuple | None  # (mats, material texels, rows, (n, 2) coordinates, (n,) view cosines) of textured metals
    #: (len(lamp_rows), 3) their lobes' Glossy Color at normal incidence: the light is filtered
    #: over it (`finish_glossy`); None: as it is.
    lamp_f0: np.ndarray | None = None
    #: (t,) the roughness of the traced receivers' lobes: how far their filter reaches (`filter_reflections`).
    ray_rough: np.ndarray | None = None


def begin_glossy(system, points, normals, pix, shape: tuple[int, int], material, albedo, irradiance, view, eye,
                 frame: int, samples: int, reflection_rays: int, lookup: HitLookup | None = None,
                 pool=None, between=None, tint: np.ndarray | None = None,
                 visibility: np.ndarray | None = None, screen=None) -> GlossyDraft:
    """`frame_glossy`'s rays and samples (arguments as its), before its filters: numpy, any thread.
    screen : the frame's `screen_light.ScreenLight` or None: the reflection rays' hits that the
    image shows take their lamp light from it, as the pixel rays' do, instead of shadow rays."""
    between = between or (lambda: None)
    points = np.asarray(points).reshape(-1, 3)
    normals = np.asarray(normals).reshape(-1, 3)
    n = points.shape[0]
    mats = system.glossy_materials
    rows = material_rows(np.asarray(material).reshape(-1), mats)
    to_eye = directions_to_eye(points, eye)
    mu = np.clip(np.einsum("ij,ij->i", normals, to_eye), 0.0, 1.0)
    colour = np.zeros((n, 3), np.float32)
    colour[:] = glossy_color(mats, rows, mu)
    lit = np.flatnonzero(rows_above(colour, 0.0))
    rough = mats.rough[rows[lit]]
    # The lamps' highlights through lobes widened by the spread of their pixels' normals (one
    # sample stands for the pixel); the reflection rays' lobes by half as much (`RAY_WIDEN_SHARE`).
    widen = footprint_alpha2(normals, pix, shape)
    ray_rough = widened_roughness(rough, RAY_WIDEN_SHARE * widen[lit])
    # Area lamps in closed form first (`glossy_ltc`: noise-free where the lamp is wholly seen);
    # of the rest, those in lobes much narrower than they are: the reflection rays estimate them.
    skip = np.zeros((n, len(system.scene.lights)), bool)
    level = (np.asarray(albedo, np.float32).reshape(-1, 3) * irradiance) @ LUMA / np.float32(np.pi)
    exact, closed = glossy_ltc.closed_form(system.scene.lights, mats, points, normals, to_eye, rows, visibility, skip,
                                           level, pool)
    if reflection_rays > 0 and lit.size:
        skip[lit] = (bsdf_lamps(system.scene.lights, points[lit], normals[lit], rough, to_eye[lit])
                     & (traced_share(rough) > 0)[:, None] & ~closed[lit])
    level = level + exact @ LUMA
    direct = np.zeros((n, 3), np.float32)
    direct[:] = adaptive_lamp_glossy(system, points, normals, to_eye, rows, pix, shape, frame, samples,
                                     skip | closed, level, widen)[0]
    # Only the sampled part is noisy: receivers whose every lamp the closed form gives skip the filter.
    sampled = np.flatnonzero((~(skip[lit] | closed[lit])).any(axis=1))
    between()  # (an edit that waits stops the viewport's worker before the reflection rays)
    parts = _traced_reflections(system, points[lit], normals[lit], to_eye[lit], ray_rough, frame, pix[lit], shape,
                                skip[lit], reflection_rays, lookup, between, screen, rows[lit])
    metals = None
    if tint is not None and getattr(mats, "tint_bases", None):
        metals = (mats, np.asarray(material).reshape(-1), rows, np.asarray(tint, np.float32).reshape(-1, 2), mu)
    return GlossyDraft(direct, colour, exact, lit, lit[sampled], rough[sampled], *parts, points, normals, pix, shape,
                       view, pool, between, metals, mats.color_table[rows[lit[sampled]], -1], ray_rough[parts[0]])


def finish_glossy(draft: GlossyDraft, filter=None) -> GlossyLight:
    """The GlossyLight of a `begin_glossy` draft: its filters (`reflection.filter_lamp_glossy`,
    `filter_reflections`) and the blends that follow them. filter : a callable with
    `pixel_gather.filter_residual`'s signature for their whole-image passes (a final render's GPU
    pass, `raster.atrous.AtrousPass`); None: numpy."""
    d = draft
    direct = d.direct.copy()
    bounced = np.zeros_like(direct)
    lit = d.lit
    if lit.size:
        d.between()
        if d.lamp_rows.size:
            # Filtered as light over the lobes' colour at normal incidence (demodulated):
            # neighbours of other lobes (metal stripes in a dielectric, a metallic map's edges)
            # share their light, not their colour (the stripes' sun highlight came out 25-30%
            # dim, the dielectric's beside them 8-14% bright). Not the colour at the view angle:
            # one material's highlight would then be reweighed across its own Fresnel rise
            # (bunny_npm's Combined 0.0243 -> 0.0250).
            at = d.lamp_rows
            f0 = np.ones((at.size, 3), np.float32) if d.lamp_f0 is None else d.lamp_f0
            colour = np.maximum(f0, np.float32(DEMODULATE_FLOOR)).astype(np.float32)
            direct[at] = filter_lamp_glossy(direct[at] / colour, d.lamp_rough, d.points[at], d.normals[at], d.pix[at],
                                            d.shape, d.view, pool=d.pool, filter=filter) * colour
        d.between()
        sky, bounced[lit] = d.sky.copy(), d.bounced.copy()
        sel = d.traced
        if sel.size:
            at = lit[sel]
            ray_direct, ray_indirect = filter_reflections(d.ray_direct, d.ray_indirect, d.ray_total, d.points[at],
                                                          d.normals[at], d.pix[at], d.shape, d.view, pool=d.pool,
                                                          filter=filter, rough=d.ray_rough)
            t = (d.share * (d.ray_total > 0))[:, None]
            sky[sel] += t * (ray_direct - sky[sel])
            bounced[at] += t * (ray_indirect - bounced[at])
        direct[lit] += d.colour[lit] * (sky + d.lamp)
    direct += d.exact
    colour = d.colour.copy()
    if d.tint is not None:
        _tint_metals(*d.tint, direct, colour)
    return GlossyLight(direct, colour, bounced)


def _tint_metals(mats, material, rows, tint, mu, direct, colour) -> None:
    """Scale, in place, the metallic lobes' share (`GlossyMaterials.metal_share`) of the glossy
    light and colour of textured metals' receivers by their lobe's albedo at their texel's colour
    over its albedo at the texture mean's (their lobe's F0 is the mean; `glossy.metal_tint_scale`):
    per channel, 1 + share (scale - 1)."""
    index = material_rows(material)
    for m, basis in mats.tint_bases.items():
        sel = np.flatnonzero((index == m) & (rows >= 0))
        if sel.size == 0:
            continue
        share = mats.metal_share[rows[sel]].astype(np.float32)[:, None]
        ratio = glossy.metal_tint(basis, tint[sel, 0], tint[sel, 1])
        factor = 1.0 + share * (glossy.metal_tint_scale(mats, rows[sel], ratio, mu[sel]) - 1.0)
        direct[sel] *= factor
        colour[sel] *= factor


def _traced_reflections(system, points, normals, to_eye, rough, frame, pix, shape, lamps, rays, lookup, between,
                        screen=None, rows=None):
    """(traced (t,), direct, indirect (t, 3), total (t,), share (t,), sky, bounced, lamp (n, 3)):
    what the lobes at the receivers reflect before Glossy Color, unfiltered (`finish_glossy`
    filters and blends it): reflection rays (`reflection.traced_reflection`) at the receivers
    `traced` whose lobes are smooth enough, their light from the world and emitters (Glossy
    Direct), other surfaces (Glossy Indirect) and `total`, with their weight against the cache's
    split-sum estimates (`glossy.cache_reflection`) `share`; those estimates (sky, bounced) at
    every receiver, read only where they count (rough lobes, rays that found no light: the rest
    zero); and the area lamps `lamps` (n, L) marks as the rays met them (lamp sampling skipped
    them). lookup : the cache's HitLookup to reuse (None: built here; the whole grid's table costs
    ~50 ms on a 48^3 grid). rows : (n,) the receivers' glossy material rows (their Fresnel weighs
    the rays: `reflection.traced_reflection`), or None."""
    n = points.shape[0]
    share = traced_share(rough) if rays > 0 else np.zeros(n)
    sel = np.flatnonzero(share > 0)
    lamp = np.zeros((n, 3), np.float32)
    empty = np.zeros((0, 3), np.float32)
    direct, indirect, total = empty, empty, np.zeros(0, np.float32)
    if sel.size:
        if lookup is None:
            lookup = HitLookup(system.cache, bounced=system.settings.indirect_quality == MULTI_BOUNCE)
        direct, indirect, total, lamp[sel] = traced_reflection(system, lookup, points[sel], normals[sel],
                                                               to_eye[sel], rough[sel], rays, frame, lamps[sel],
                                                               pixels=(pix[sel], shape[1]), screen=screen,
                                                               rows=None if rows is None else rows[sel])
        between()
    sky = np.zeros((n, 3), np.float32)
    bounced = np.zeros((n, 3), np.float32)
    # The cache's estimate where the rays' weight is under 1 (or they may find no light).
    need = np.ones(n, bool)
    need[sel] = share[sel] * (total > 0) < 1.0
    need = np.flatnonzero(need)
    if need.size:
        sky[need], bounced[need] = cache_reflection(system.cache, points[need], normals[need], to_eye[need],
                                                    rough[need])
    return sel, direct, indirect, total, share[sel].astype(np.float32), sky, bounced, lamp

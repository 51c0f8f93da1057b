"""Pixel filter of final renders: jittered subframes placed as Cycles places its samples, and the
accumulation of their passes into what Cycles writes.

Cycles integrates every pixel over its pixel filter (`scene.cycles.pixel_filter_type` and
`filter_width`: Blackman-Harris of 1.5 px by default; Gaussian and box are here too) and
importance-samples it (`scene/film.cpp: filter_table`): the filter is separable,
each axis offset drawn from the inverse CDF of a Blackman-Harris window that spans twice the
filter size (`width *= 2`), i.e. offsets in [-size, size] pixels around the pixel centre, and all
samples then count with equal weight. A raster pass takes one sample per pixel; rendering K
subframes whose projection is shifted by K such offsets, and averaging them, is the same
estimator with one shared sample pattern for every pixel. The pattern is a deterministic
low-discrepancy set (Hammersley, one point per stratum along each axis) pushed through the
filter's inverse CDF, so K = 4 already covers the filter's quartiles on both axes. The film then
weighs each pixel's sum with its neighbours' by the filter's share of their footprints, a K-th of
it over K subframes (`reconstruction_taps`): a sample stands for the pixel around it, which the
filter reaches into; at K = 1 that is all the anti-aliasing a frame gets.

How each pass accumulates follows Cycles' film (`kernel/film/data_passes.h`, `film/read.h`):
Combined, Diffuse Color, AO and Normal are sample averages (a background sample adds 0, or the
world's radiance to Combined); Diffuse Direct and Indirect accumulate the reflected light
(colour x irradiance / pi) and are divided by the accumulated Diffuse Color at the end (the
passes' `divide_type`), so an edge pixel's light is weighted by each side's albedo and Combined =
(Direct + Indirect) x Color holds for the filtered pixel too; Depth is not filtered: Cycles writes one sample's depth (its first), a
point sample, its first, and Cycles places its first sample at the pixel centre
(`rand_filter = 0.5` for sample 0): here the unjittered raster's.

The CPU work stays that of one sample per pixel: the cache steps run on the unjittered raster, and
a subframe traces shadow rays (its share of the pixel's) only where its sample sees another
surface than the centre's (`same_surface`): silhouettes and creases, a few % of the pixels.

Pure numpy: the pipeline reads the targets and hands them in.
"""

from __future__ import annotations

from concurrent import futures
from dataclasses import dataclass

import numpy as np

from ..penumbra import LAMP_GROUP, LAMP_SEED_STRIDE
from ..pixel_gather import LUMA, write_texels
from ..rows import rows_above
from ..system import DIRECT_BLOCK_RAYS
from ..translucent import BACK_SEED_OFFSET, mix_back
from ..visible import pixels_to_points
from .world_background import camera_rays

#: Blackman-Harris coefficients as Cycles' `filter_func_blackman_harris` uses them.
BH_COEFFS = (0.35875, -0.48829, 0.14128, -0.01168)

#: Resolution of the tabulated inverse CDF (Cycles' FILTER_TABLE_SIZE is 1024; a finer table
#: costs nothing here, the pattern is built once per frame).
_TABLE_SIZE = 4097

#: Passes averaged over the subframes (the deferred targets plus the G-buffer's normal).
AVERAGED_PASSES = ("combined", "diffuse_direct", "diffuse_indirect", "diffuse_color", "ao")
#: Light passes Cycles divides by the Diffuse Color pass after accumulating (colour x light).
COLOR_DIVIDED_PASSES = ("diffuse_direct", "diffuse_indirect")


def blackman_harris(v: np.ndarray, filter_size: float) -> np.ndarray:
    """Cycles' filter weight at offset v (pixels) from the pixel centre: a Blackman-Harris
    window over [-filter_size, filter_size], 0 outside."""
    v = np.asarray(v, np.float64)
    t = v / (2.0 * filter_size) + 0.5  # 0..1 across the window
    a0, a1, a2, a3 = BH_COEFFS
    x = 2.0 * np.pi * t
    w = a0 + a1 * np.cos(x) + a2 * np.cos(2 * x) + a3 * np.cos(3 * x)
    return np.where(np.abs(v) <= filter_size, w, 0.0)


def blackman_harris_cdf(v: np.ndarray, filter_size: float) -> np.ndarray:
    """The filter's normalised integral from -filter_size to v (closed form): P(offset <= v)."""
    t = np.clip(np.asarray(v, np.float64) / (2.0 * filter_size) + 0.5, 0.0, 1.0)
    a0, a1, a2, a3 = BH_COEFFS
    x = 2.0 * np.pi * t
    integral = a0 * t + (a1 * np.sin(x) + a2 * np.sin(2 * x) / 2 + a3 * np.sin(3 * x) / 3) / (2 * np.pi)
    return integral / a0


#: Cycles' pixel filters (`scene.cycles.pixel_filter_type`).
FILTER_TYPES = ("BLACKMAN_HARRIS", "GAUSSIAN", "BOX")


def filter_support(filter_type: str, width: float) -> float:
    """Largest offset (pixels) the filter reaches, as Cycles' table spans it: Blackman-Harris
    width (its window spans 2 x width), Gaussian 1.5 x width (sigma = width / 4), box width / 2."""
    return {"BLACKMAN_HARRIS": 1.0, "GAUSSIAN": 1.5, "BOX": 0.5}[filter_type] * width


def filter_weight(v: np.ndarray, filter_type: str, width: float) -> np.ndarray:
    """Cycles' filter function at offset v (pixels), width its Filter Width; 0 outside."""
    v = np.asarray(v, np.float64)
    if filter_type == "BLACKMAN_HARRIS":
        return blackman_harris(v, width)
    inside = np.abs(v) <= filter_support(filter_type, width)
    if filter_type == "GAUSSIAN":
        # filter_func_gaussian(v, 3 width): exp(-2 (6 v / (3 width))^2)
        return np.where(inside, np.exp(-8.0 * v * v / (width * width)), 0.0)
    if filter_type == "BOX":
        return inside.astype(np.float64)
    raise ValueError(f"unknown pixel filter {filter_type!r}, expected one of {FILTER_TYPES}")


def filter_offsets(u: np.ndarray, width: float, filter_type: str = "BLACKMAN_HARRIS") -> np.ndarray:
    """Offsets (pixels) whose distribution is the filter's, for uniform u in [0, 1): the inverse
    CDF tabulated as Cycles tabulates its own (Blackman-Harris from its closed-form integral)."""
    u = np.asarray(u, np.float64)
    if filter_type not in FILTER_TYPES:
        raise ValueError(f"unknown pixel filter {filter_type!r}, expected one of {FILTER_TYPES}")
    if width <= 0.0:
        return np.zeros_like(u)
    v, cdf = _filter_cdf(filter_type, width)
    return np.interp(u, cdf, v)


def _filter_cdf(filter_type: str, width: float) -> tuple[np.ndarray, np.ndarray]:
    """(offsets, P(offset <= them)) tabulated over the filter's support (width > 0)."""
    reach = filter_support(filter_type, width)
    v = np.linspace(-reach, reach, _TABLE_SIZE)
    if filter_type == "BLACKMAN_HARRIS":
        return v, blackman_harris_cdf(v, width)
    w = filter_weight(v, filter_type, width)
    cdf = np.concatenate([[0.0], np.cumsum((w[1:] + w[:-1]) * 0.5)])
    return v, cdf / cdf[-1]


def _radical_inverse2(i: np.ndarray) -> np.ndarray:
    i = np.asarray(i, np.uint64)
    out = np.zeros(i.shape, np.float64)
    scale = 0.5
    while np.any(i):
        out += (i & np.uint64(1)).astype(np.float64) * scale
        i = i >> np.uint64(1)
        scale *= 0.5
    return out


def subpixel_offsets(count: int, filter_size: float, filter_type: str = "BLACKMAN_HARRIS") -> np.ndarray:
    """(count, 2) float64 offsets (x, y) in pixels of the subframes of one final-render frame.

    count = 1 is the pixel centre (one sample, which the film's filter weighs with its neighbours':
    `reconstruction_taps`). Else a
    Hammersley set centred in its strata, x = (i + 0.5) / count, y = radical inverse of i shifted
    by half a stratum, each axis mapped through the filter's inverse CDF: deterministic, every
    frame the same.
    """
    count = int(count)
    if count < 1:
        raise ValueError(f"count must be >= 1, got {count}")
    if count == 1:
        return np.zeros((1, 2))
    i = np.arange(count)
    ux = (i + 0.5) / count
    uy = np.mod(_radical_inverse2(i) + 0.5 / count, 1.0)
    return np.stack([filter_offsets(ux, filter_size, filter_type), filter_offsets(uy, filter_size, filter_type)],
                    axis=1)


def reconstruction_taps(count: int, filter_size: float, filter_type: str = "BLACKMAN_HARRIS") -> np.ndarray:
    """(2 r + 1,) float64 weights of the separable pixel filter a frame of `count` subframes
    applies to its accumulated passes (`FilmAccumulator.set_filter`), summing to 1.

    Why: Cycles' pixel is the filter's average of the radiance over +-1.5 px; a raster sample
    is the radiance at one point. With one subframe (the pixel centre) the filter's share of
    each neighbouring pixel's footprint (the filter integrated over [k - 0.5, k + 0.5], per axis:
    Blackman-Harris 1.5 px gives 0.119 to each side) weights the neighbours' samples: what Cycles'
    filter makes of an image of pixel-sized samples. K jittered subframes already sample the
    filter, K times more finely: the neighbours then keep 1 / K of that share (measured against
    Cycles at 640x360, Combined, the seven benchmark scenes: one sample 0.119 best or nearly,
    bunny_npm 0.0350 -> 0.0309, atrium 0.0523 -> 0.0447; 4 subframes 0.03-0.04 best, 8 about
    0.015; the full share over 4 or 8 subframes blurs: morse 0.0470 -> 0.0556). A box filter of
    1 px or less, or a filter width 0, keeps every pixel as it is ([1])."""
    count = max(int(count), 1)
    if filter_type not in FILTER_TYPES:
        raise ValueError(f"unknown pixel filter {filter_type!r}, expected one of {FILTER_TYPES}")
    reach = filter_support(filter_type, filter_size) if filter_size > 0 else 0.0
    radius = int(np.ceil(reach - 0.5)) if reach > 0.5 else 0
    if radius == 0:
        return np.ones(1)
    v, cdf = _filter_cdf(filter_type, filter_size)
    k = np.arange(-radius, radius + 1, dtype=np.float64)
    edges = np.interp(np.concatenate([k - 0.5, [radius + 0.5]]), v, cdf, left=0.0, right=1.0)
    taps = np.diff(edges)
    taps[0] += edges[0]
    taps[-1] += 1.0 - edges[-1]
    taps /= count
    taps[radius] = 1.0 - (taps.sum() - taps[radius])
    return taps


def filter_image(image: np.ndarray, taps: np.ndarray) -> np.ndarray:
    """(h, w, c) float32 image filtered separably by `taps` (odd length) along both axes, edge
    pixels repeated beyond the border; `taps` of length 1 returns the image itself."""
    image = np.asarray(image, np.float32)
    if taps.size == 1:
        return image
    r = taps.size // 2
    out = image
    for axis in (0, 1):
        pad = [(0, 0)] * image.ndim
        pad[axis] = (r, r)
        padded = np.pad(out, pad, mode="edge")
        n = out.shape[axis]
        acc = np.zeros(out.shape, np.float32)
        window = [slice(None)] * image.ndim
        for j, t in enumerate(taps):
            window[axis] = slice(j, j + n)  # a view: no copy of the shifted image
            acc += np.float32(t) * padded[tuple(window)]
        out = acc
    return out


def subframe_texture_filter(count: int, filter_size: float) -> float:
    """Pixels of footprint each subframe's texture taps cover (GBufferPass.execute): a single
    raster pre-filters textures over the whole filter; of K subframes, each covers its stratum,
    about filter_size / sqrt(K), so a texture is neither filtered twice nor aliased between them."""
    return float(filter_size) / np.sqrt(max(int(count), 1))


def jittered_projection(proj: np.ndarray, offset, width: int, height: int) -> np.ndarray:
    """The projection that renders the image sampled at pixel centre + offset (pixels; x right,
    y up as the G-buffer's rows go): clip x and y shift by -2 offset / size in NDC (times w,
    so perspective and orthographic matrices alike)."""
    p = np.array(proj, np.float64).reshape(4, 4)
    dx, dy = float(offset[0]), float(offset[1])
    p[0] -= (2.0 * dx / width) * p[3]
    p[1] -= (2.0 * dy / height) * p[3]
    return p.astype(np.float32)


#: A jittered subframe's pixel that sees the centre raster's surface reuses its direct light (the
#: full shadow-ray count, one stratified set) instead of tracing its share again: the normals agree
#: to this cosine, the point lies within SAME_PLANE x view depth of the centre point's tangent
#: plane and within SAME_REACH x view depth of the point itself (a 1.5 px offset moves a point by
#: ~0.005 x depth at 640 px and 50 degrees, ~6x that at grazing angles).
SAME_COS = 0.95
SAME_PLANE = 0.005
SAME_REACH = 0.05
#: Relative lamp-light step between neighbouring centre pixels that marks a light edge (`light_edges`).
LIGHT_EDGE_CONTRAST = 0.25
#: ... and a step of at least this share of the frame's mean lamp light (`edge_floor`). Why: under
#: a high sun (its disc of 1 degree) every wall gets a grazing sliver of it, ~1/1000 of the lit
#: floors' and noisy, whose neighbours differ by more than the contrast everywhere: a scene of
#: 1000 cubes marked 2/3 of its pixels and re-lit them in every subframe (their lamp light 1.58 s
#: of a 7.1 s frame at 640x360). With this floor 0.65 s and 5.95 s; Combined against Cycles 256
#: spp (320x180) 0.0647 -> 0.0653 (0.01: 0.0651 at 6.85 s); the benchmark scenes' Combined equal
#: or lower (640x360: bunny_npm 0.02708 -> 0.02701, its lamp light 479 -> 380 ms; dragon_npm
#: 0.04977 -> 0.04963; atrium 0.02356 -> 0.02355; Cornell, spheres, car, morse within 0.0001).
LIGHT_EDGE_FLOOR = 0.03


def same_surface(position0: np.ndarray, normal0: np.ndarray, position: np.ndarray,
                 normal: np.ndarray, depth0: np.ndarray) -> np.ndarray:
    """(n,) bool: pixels whose subframe sample (position, normal) lies on the centre sample's
    surface (position0, normal0; view depth depth0): `same_plane`, and within SAME_REACH x depth0
    of it. (n, >= 3) float32 arrays (xyz used) and (n,); rows without geometry in either must be
    masked by the caller."""
    d = _offsets(position0, position)
    reach = d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
    return _same_plane(d, normal0, normal, depth0) & (reach <= (SAME_REACH * depth0) ** 2)


def same_plane(position0: np.ndarray, normal0: np.ndarray, position: np.ndarray, normal: np.ndarray,
               depth0: np.ndarray) -> np.ndarray:
    """(n,) bool: the samples (position, normal) face as the samples (position0, normal0) do (their
    normals within SAME_COS) and lie on their tangent planes (within SAME_PLANE x depth0, the
    latter's view depths). Arrays as `same_surface`'s."""
    return _same_plane(_offsets(position0, position), normal0, normal, depth0)


def _offsets(position0: np.ndarray, position: np.ndarray) -> list[np.ndarray]:
    """The x, y, z columns of position - position0 ((n,) each), taken once for both tests."""
    return [position[:, k] - position0[:, k] for k in range(3)]


def _same_plane(d: list[np.ndarray], normal0: np.ndarray, normal: np.ndarray, depth0: np.ndarray) -> np.ndarray:
    """`same_plane` of samples `_offsets` d from the centre samples."""
    cos = normal[:, 0] * normal0[:, 0] + normal[:, 1] * normal0[:, 1] + normal[:, 2] * normal0[:, 2]
    plane = np.abs(d[0] * normal0[:, 0] + d[1] * normal0[:, 1] + d[2] * normal0[:, 2])
    return (cos >= SAME_COS) & (plane <= SAME_PLANE * depth0)


@dataclass
class CentreSample:
    """The unjittered raster's direct light and surfaces, which subframes reuse. Flat per pixel."""

    direct: np.ndarray  # (h * w, 4) float32, rgb = lamp irradiance W/m^2
    position: np.ndarray  # (h * w, 4) float32 G-buffer position, w = 1 on geometry
    normal: np.ndarray  # (h * w, >= 3) float32 unit (xyz): the shading normal
    depth: np.ndarray  # (h * w,) float32 view depth
    light_edge: np.ndarray | None = None  # (h * w,) bool: a shadow or light boundary crosses the pixel
    #: (h * w, >= 3) float32 unit smooth surface normal (the G-buffer's `surface` target), what
    #: surface identity compares (`same_surface`): a normal map's differently bent neighbours are
    #: one surface. None: the shading normal (no material bends it).
    surface: np.ndarray | None = None
    #: (h * w, L, 3) float32 each lamp's share of `direct` (L lamps), or None (one lamp, or more
    #: than `frame.SUBFRAME_LAMP_LIMIT`): with it a light edge is known per lamp (`lamp_edge`).
    lamp_light: np.ndarray | None = None
    #: (h * w, L) bool: lamp l's light changes across the pixel (`lamp_edges`); None without
    #: `lamp_light`. `light_edge` is then its any() over the lamps.
    lamp_edge: np.ndarray | None = None
    #: (h * w, 3) float32 the emitters' share of `direct` where it was filtered over the image
    #: (`penumbra.filter_emitter_light`), or None. Its steps are no light edges, and a subframe
    #: keeps it wherever its pixel sees the centre's surface (`subframe_direct`): sampled again
    #: at the halo's light edges, its raw samples speckled the wall beside a glowing sign.
    emitter: np.ndarray | None = None

    @property
    def surface_normal(self) -> np.ndarray:
        return self.normal if self.surface is None else self.surface

    @classmethod
    def from_gbuffer(cls, direct, position, normal, depth, surface=None, lamp_light=None,
                     emitter=None) -> CentreSample:
        """From the read-backs (h, w, 4) / (h, w, >= 3) / (h, w, 1) and the direct light;
        surface : the `surface` target's read-back (h, w, >= 3), or None / `normal` itself;
        lamp_light : (h * w, L, 3) each lamp's share of `direct`, or None; emitter : `emitter`."""
        h, w = position.shape[:2]
        n = h * w
        total = _rgb_sum(np.asarray(direct)).reshape(h, w)
        if emitter is not None:
            total = np.maximum(total - emitter.sum(axis=1).reshape(h, w), 0.0)
        floor = edge_floor(total)
        lamp_edge = None
        if lamp_light is None:
            edge = light_edges(total, floor=floor).reshape(n)
        else:
            lamp_edge = lamp_edges(lamp_light, total, floor=floor)
            edge = lamp_edge[:, 0].copy()  # any() over the lamps, column by column (a reduction
            for k in range(1, lamp_edge.shape[1]):  # over rows of a few lamps is ~5x slower)
                edge |= lamp_edge[:, k]
        return cls(direct, position.reshape(n, -1), normal.reshape(n, -1), depth.reshape(n), edge,
                   None if surface is None or surface is normal else surface.reshape(n, -1),
                   lamp_light, lamp_edge, emitter)


def edge_floor(total: np.ndarray) -> float:
    """The lamp light under which a step is no light edge (`light_edges`' floor): LIGHT_EDGE_FLOOR
    of the mean lamp light of the pixels it lights."""
    lit = total[total > 0.0]
    return float(LIGHT_EDGE_FLOOR * lit.mean()) if lit.size else 0.0


def light_edges(light: np.ndarray, contrast: float = LIGHT_EDGE_CONTRAST, scale: np.ndarray | None = None,
                floor: float = 0.0) -> np.ndarray:
    """(h, w) bool: pixels whose lamp light differs from a 4-neighbour's by more than `contrast`
    of the larger of the two (of their `scale`, (h, w), when given): a shadow's or a light's
    boundary crosses the pixel's footprint.

    Why: a subframe that sees the centre's surface reuses the centre's light, which is right on a
    smooth surface but leaves a sun's shadow on a floor as aliased as one sample per pixel (the
    atrium's jagged column shadows held most of its Diffuse Direct error); these pixels are
    traced again in every subframe, as silhouettes are.
    """
    light = np.asarray(light, np.float32)
    scale = light if scale is None else np.asarray(scale, np.float32)
    edge = np.zeros(light.shape, bool)
    for axis in (0, 1):
        a, b = neighbour_pairs(axis)
        big = np.maximum(scale[a], scale[b])
        np.maximum(big, np.float32(max(floor / max(contrast, 1e-12), 1e-12)), out=big)
        big *= np.float32(contrast)
        step = light[a] - light[b]
        np.abs(step, out=step)
        jump = step > big
        edge[a] |= jump  # the pair's first pixel and its second (views: no padded copies)
        edge[b] |= jump
    return edge


def neighbour_pairs(axis: int, step: int = 1) -> tuple[tuple[slice, slice], tuple[slice, slice]]:
    """Index pairs of every pixel and its neighbour `step` pixels further along `axis` of an
    (h, w) image (views: no padded copies)."""
    a, b = [slice(None), slice(None)], [slice(None), slice(None)]
    a[axis], b[axis] = slice(0, -step), slice(step, None)
    return tuple(a), tuple(b)


def _rgb_sum(rgb: np.ndarray) -> np.ndarray:
    """r + g + b of the last axis's first three channels, left to right as numpy's sum over that
    axis adds them (the same bits): three strided adds, not a reduction over rows of three."""
    total = rgb[..., 0] + rgb[..., 1]
    total += rgb[..., 2]
    return total


def lamp_edges(lamp_light: np.ndarray, total: np.ndarray, contrast: float = LIGHT_EDGE_CONTRAST,
               floor: float = 0.0) -> np.ndarray:
    """(h * w, L) bool: where lamp l's light (lamp_light (h * w, L, 3)) steps between neighbours by
    more than `contrast` of the pixels' total lamp light (total (h, w)): the light edges of
    `light_edges`, each put down to the lamps whose light makes it. A room lit by five soft lamps
    has some lamp's shadow edge on a quarter of its pixels, and a subframe re-lit them by every
    lamp (morse_apartment 640x360: 12.5k pixels x 5 lamps x 6 rays per subframe, 50 ms each)."""
    h, w = total.shape
    sums = _rgb_sum(lamp_light)  # (h * w, L)
    return np.stack([light_edges(sums[:, k].reshape(h, w), contrast, scale=total, floor=floor).reshape(-1)
                     for k in range(sums.shape[1])], axis=1)


def subframe_rays(pix: np.ndarray, width: int, height: int, view: np.ndarray, proj: np.ndarray,
                  offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(origins, directions), each (K, m, 3) float32 (unit directions): the camera rays through
    m pixels (flat indices `pix` into a `width` x `height` image, rows bottom-up) at K jittered
    subframes' samples (pixel centre + `offsets` (K, 2), as `jittered_projection` samples them),
    from the near plane (perspective and orthographic cameras alike).

    Why: a still viewport shades its jittered subframes from the worker's light at the pixel
    centres; where a pixel's light or surface changes within it (a shadow edge, a facet's edge,
    a silhouette) each subframe needs the light of what it sees itself, as final renders trace
    it there (`subframe_direct`); the worker finds that by casting these rays."""
    pix = np.asarray(pix).reshape(-1)
    offsets = np.asarray(offsets, np.float64).reshape(-1, 2)
    m, k = pix.size, offsets.shape[0]
    x = (pix % width).astype(np.float64)
    y = (pix // width).astype(np.float64)
    origins = np.zeros((k, m, 3), np.float32)
    directions = np.zeros((k, m, 3), np.float32)
    for i, (ox, oy) in enumerate(offsets):
        origins[i], directions[i] = camera_rays(view, proj, (x + 0.5 + ox) / width * 2.0 - 1.0,
                                                (y + 0.5 + oy) / height * 2.0 - 1.0)
    return origins, directions


def surface_edges(position: np.ndarray, normal: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """(h, w) bool: pixels with a 4-neighbour on another surface than their own (not `same_plane`
    either way: normals apart by more than SAME_COS, or off the tangent plane by more than
    SAME_PLANE x view depth) or on none
    (geometry beside the background, both sides): where a jittered subframe may see another
    surface, or another facet of a faceted one. position, normal (h, w, >= 3; position's w = 1
    on geometry), depth (h, w) view depth."""
    position = np.asarray(position, np.float32)
    h, w = position.shape[:2]
    geo = position[..., 3] > 0.5
    p, n = position[..., :3], np.asarray(normal, np.float32)[..., :3]
    d = np.maximum(np.asarray(depth, np.float32).reshape(h, w), np.float32(1e-6))
    edge = np.zeros((h, w), bool)
    for axis in (0, 1):
        a, b = neighbour_pairs(axis)
        pa, na, da = p[a].reshape(-1, 3), n[a].reshape(-1, 3), d[a].reshape(-1)
        pb, nb, db = p[b].reshape(-1, 3), n[b].reshape(-1, 3), d[b].reshape(-1)
        # Each on the other's tangent plane, facing alike (`same_plane`, both ways).
        same = (same_plane(pa, na, pb, nb, da) & same_plane(pb, nb, pa, na, db)).reshape(geo[a].shape)
        differ = (geo[a] != geo[b]) | (geo[a] & geo[b] & ~same)
        edge[a] |= differ
        edge[b] |= differ
    return edge


def bends_normals(centre: CentreSample, normal: np.ndarray, surface: np.ndarray | None) -> bool:
    """Whether a subframe's `surface` read-back is the smooth surface under shading normals
    (`normal`) that a material bends, with the centre's own (`CentreSample.surface`)."""
    return surface is not None and surface is not normal and centre.surface is not None


def compared_normal(centre: CentreSample, normal: np.ndarray, surface: np.ndarray | None) -> np.ndarray:
    """The subframe normals surfaces are told apart by (`subframe_surfaces`, `subframe_glossy`):
    the smooth surface read-back where a material bends normals, else the shading normals."""
    return surface if bends_normals(centre, normal, surface) else normal


def subframe_surfaces(centre: CentreSample, position: np.ndarray, normal: np.ndarray,
                      surface: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """((h * w,) bool, (h * w,) bool): pixels where the subframe (read-backs (h, w, 4) /
    (h, w, >= 3)) sees geometry, and where it sees the centre sample's surface (`same_surface`
    of the smooth surface normals: `surface`, the subframe's `surface` read-back, against
    `centre.surface_normal`) lit alike: where a material bends normals, the shading normals agree
    to SAME_COS too, so a normal map's detail within a pixel keeps its own light."""
    n_pix = centre.position.shape[0]
    pos = position.reshape(n_pix, -1)
    nrm = normal.reshape(n_pix, -1)
    hit = pos[:, 3] > 0.5
    bent = bends_normals(centre, normal, surface)
    geo = compared_normal(centre, normal, surface).reshape(n_pix, -1)
    # Whole-image arrays (no gathers): the comparison is the bulk of a subframe's CPU work.
    same = hit & (centre.position[:, 3] > 0.5) & same_surface(centre.position, centre.surface_normal, pos, geo,
                                                              centre.depth)
    if bent:
        c = centre.normal
        same &= (nrm[:, 0] * c[:, 0] + nrm[:, 1] * c[:, 1] + nrm[:, 2] * c[:, 2]) >= SAME_COS
    return hit, same


def subframe_gi(resolver, centre_indirect: np.ndarray, centre_direct: np.ndarray, hit: np.ndarray, same: np.ndarray,
                position: np.ndarray, normal: np.ndarray, offset, seed_frame: int,
                rays: int, surface: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, int]:
    """A jittered subframe's full-res GI textures, ((h * w, 4) indirect, (h * w, 4) direct, rays
    traced), as `pixel_gather.textures` lays them out: the centre's (`centre_indirect`,
    `centre_direct`: `pixel_gather.FullResGI.indirect` / `.direct`) where the subframe sees the
    centre's surface, resolved at the subframe's own sample elsewhere (`pixel_gather.GIResolver.at`,
    `rays` rays where no GI pixel shares its surface), the background's where it sees none.
    hit, same : `subframe_surfaces`. surface : the subframe's `surface` read-back where a material
    bends normals, else None. offset : the subframe's jitter (pixels), or a callable
    (points, flat pixels) -> per-point (dx, dy) where the centre image shows the points elsewhere
    (a lens subframe: `lens.centre_offsets`).

    Why: the film weights each sample's light by its own colour; a post's edge pixel whose
    subframe sees the ground behind it (or a bar the centre raster missed) must bring that
    surface's light, not the centre surface's. Only those few % of the pixels are resolved: the
    rest is a copy of the centre's textures, so a subframe costs little more than its resolve."""
    n_pix = hit.shape[0]
    indirect = np.array(centre_indirect, np.float32).reshape(n_pix, 4)
    direct = np.array(centre_direct, np.float32).reshape(n_pix, 4)
    miss = ~hit
    indirect[miss] = (0.0, 0.0, 0.0, 1.0)
    direct[miss] = 0.0
    fresh = np.flatnonzero(hit & ~same)
    traced = 0
    if fresh.size:
        p, n, keep = pixels_to_points(position.reshape(n_pix, -1)[fresh][None], normal.reshape(n_pix, -1)[fresh][None])
        rows = fresh[keep]
        smooth = None
        if surface is not None and surface is not normal:
            smooth = pixels_to_points(position.reshape(n_pix, -1)[fresh][None], surface.reshape(n_pix, -1)[fresh][None])[1]
        at = offset(p, rows) if callable(offset) else offset
        value, traced = resolver.at(p, n, rows, at, seed_frame, rays, surfaces=smooth)
        write_texels(indirect, direct, rows, value)
    return indirect, direct, traced


#: Neighbouring centre pixels on different surfaces whose indirect light differs by more than
#: this share of the larger mark a GI edge (`gi_edges`): a 10 x step, a sunlit ground's bounce
#: on a dark bar against ground that sees little of it.
GI_CONTRAST = 0.9
#: More subframes cost a whole frame's raster passes and shadow rays each, so a frame takes them
#: only when its GI edges are at least this share of the image (640x360 unless said: the
#: fine-detail yard 3.6% at 320x240, 2.1% at 640x480; dragon 0.86%, car 0.72%, bunny 0.56%,
#: morse apartment 0.38%, spheres 0.05%, atrium, Cornell and animated 0).
EXTRA_MIN_SHARE = 0.014


def gi_edges(centre: CentreSample, indirect: np.ndarray, height: int, width: int,
             contrast: float = GI_CONTRAST) -> np.ndarray:
    """(h * w,) bool: centre-raster pixels next to a 4-neighbour on another surface (`same_surface`
    fails between them) whose indirect light differs by more than `contrast` of the larger
    (indirect: `pixel_gather.textures`' (h * w, 4)).

    Why: where two surfaces of very different bounce light meet within a pixel or two (a thin
    bar lit by the sunny ground, in front of ground that sees little), Diffuse Indirect is as
    exact as the subframes' share of each surface; the centre raster finds them before the
    subframes run, so the frame can take more of them (`worth_extra`)."""
    n = height * width
    pos = centre.position.reshape(height, width, -1)
    # The smooth surface: a normal map's differently bent neighbours are one surface.
    nrm = centre.surface_normal.reshape(height, width, -1)
    depth = centre.depth.reshape(height, width)
    luma = np.asarray(indirect, np.float32).reshape(n, 4)[:, :3] @ np.asarray(LUMA, np.float32)
    lum = luma.reshape(height, width)
    geo = pos[..., 3] > 0.5
    out = np.zeros((height, width), bool)
    for axis in (0, 1):
        if out.shape[axis] < 2:
            continue
        a, b = neighbour_pairs(axis)
        both = geo[a] & geo[b]
        m = pos[a].shape[0] * pos[a].shape[1]
        same = same_surface(pos[a].reshape(m, pos.shape[-1]), nrm[a].reshape(m, nrm.shape[-1]),
                            pos[b].reshape(m, pos.shape[-1]), nrm[b].reshape(m, nrm.shape[-1]),
                            depth[a].reshape(m)).reshape(both.shape)
        top = np.maximum(lum[a], lum[b])
        edge = both & ~same & (np.abs(lum[a] - lum[b]) > np.float32(contrast) * top) & (top > 0)
        out[a] |= edge
        out[b] |= edge
    return out.reshape(n)


def worth_extra(edges: np.ndarray, share: float = EXTRA_MIN_SHARE) -> bool:
    """Whether a frame takes the extra subframes: its (h * w,) bool GI `edges` are at least
    `share` of the image."""
    return bool(edges.any()) and edges.sum() >= share * edges.size


def subframe_direct(system, centre: CentreSample, position: np.ndarray, normal: np.ndarray,
                    seed_frame: int, samples: int, surfaces=None, surface: np.ndarray | None = None,
                    emitters: bool = False, translucent: np.ndarray | None = None) -> np.ndarray:
    """A jittered subframe's direct light, (h * w, 4) float32: the centre's where the subframe's
    pixel sees the same surface, `samples` shadow rays per lamp (seeded by seed_frame) elsewhere.

    position, normal : the subframe's G-buffer read-backs (h, w, 4) / (h, w, >= 3); the
    G-buffer's normals are unit (normalised in its fragment shader). surface : the subframe's
    `surface` read-back where a material bends normals (None: the shading normal): the surface
    `same_surface` compares and the smooth normal of the bump shadowing term. emitters : the
    centre's light holds the emissive triangles' samples (`emitters.py`): pixels on another
    surface take their own. translucent : (h w, 3) the subframe's pixels' translucent shares or
    None: pixels lit afresh take the lamps' light on their back too (`translucent.mix_back`).
    """
    n_pix = centre.direct.shape[0]
    pos = position.reshape(n_pix, -1)
    nrm = normal.reshape(n_pix, -1)
    bent = surface is not None and surface is not normal
    hit, same = subframe_surfaces(centre, position, normal, surface) if surfaces is None else surfaces
    on_surface = same
    lamp_edge = None
    if centre.lamp_edge is not None:
        lamp_edge = centre.lamp_edge & (hit & same)[:, None]  # same surface, some lamp's edge
    elif centre.light_edge is not None:
        same = same & ~centre.light_edge  # a new array: the caller's `surfaces` stay as they are
    direct = centre.direct.copy()
    direct[np.flatnonzero(~same)] = 0.0  # ~5x np.where's speed: few pixels leave the centre's surface

    def lit(rows, frame, **kwargs):
        """(rows, (k, 3)) the light at the subframe's pixels `rows` that have a point."""
        p, n, keep = pixels_to_points(pos[rows][None], nrm[rows][None])
        if bent:
            kwargs["smooth"] = pixels_to_points(pos[rows][None], surface.reshape(n_pix, -1)[rows][None])[1]
        light = system.direct(p, n, frame, samples=samples, **kwargs)
        if translucent is None:
            return rows[keep], light

        def back(r):
            smooth = {} if "smooth" not in kwargs else {"smooth": -kwargs["smooth"][r]}
            rest = {k: v for k, v in kwargs.items() if k != "smooth"}
            return system.direct(p[r], -n[r], frame + BACK_SEED_OFFSET, samples=samples, **rest, **smooth)

        return rows[keep], mix_back(light, translucent[rows[keep]], back)

    fresh = hit & ~same
    # The lamps' rays (and the emitters') are independent calls of their own seeds: one job each
    # on the system's pool, so that a subframe's few thousand fresh and edge pixels (each call
    # below a block of `GISystem.direct`, which would run it on this thread alone) use both cores.
    jobs = _Jobs(system, samples)
    emitted = None
    kept = None
    if emitters and centre.emitter is not None:
        # The centre's filtered emitter light where the pixel sees its surface (a lamp's light
        # edge: its lamps are traced again below), samples of its own elsewhere.
        kept = np.flatnonzero(fresh & on_surface)
        fresh_emitted = fresh & ~on_surface
    else:
        fresh_emitted = fresh
    if emitters and fresh_emitted.any():
        e_rows = np.flatnonzero(fresh_emitted)
        e_p, e_n, e_keep = pixels_to_points(pos[e_rows][None], nrm[e_rows][None])
        emitted = jobs.submit(e_p.shape[0], system.emitter_light, e_p, e_n, seed_frame, samples)
    if lamp_edge is None:
        rows = np.flatnonzero(fresh)
        count = len(getattr(getattr(system, "scene", None), "lights", None) or ())
        if not rows.size:
            lamps = []
        elif count <= LAMP_GROUP:
            lamps = [jobs.submit(rows.size, lit, rows, seed_frame)]
        else:
            # Many lamps: a job per LAMP_GROUP of them (lamp group g0 from seed_frame + g0 x
            # LAMP_SEED_STRIDE, as the penumbra passes), so that both cores trace them: one job
            # of 50 lamps over a subframe's few thousand edge pixels ran on one core (a room of
            # 50 point lamps: ~0.26 s a subframe).
            lamps = [jobs.submit(rows.size, lit, rows, seed_frame + g0 * LAMP_SEED_STRIDE,
                                 lights=list(range(g0, min(g0 + LAMP_GROUP, count))))
                     for g0 in range(0, count, LAMP_GROUP)]
    else:
        # Lamp by lamp: another surface (a silhouette) takes every lamp's light from its own rays;
        # on the centre's surface only the lamps whose edge crosses the pixel are traced again, the
        # others keep the centre's share, as a pixel without any edge keeps all of them. Lamp k
        # draws from seed_frame + k x LAMP_SEED_STRIDE, as the centre's penumbra passes do: lamp
        # 0's rays are those of the one-lamp image (a lamp that emits nothing beside it changes
        # no pixel).
        lamps = []
        for k in range(lamp_edge.shape[1]):
            want = np.flatnonzero(fresh | lamp_edge[:, k])
            if want.size:
                lamps.append((k, jobs.submit(want.size, lit, want, seed_frame + k * LAMP_SEED_STRIDE, lights=[k])))
    jobs.run_large()
    if lamp_edge is None:
        for job in lamps:
            rows, light = job.result()
            if len(lamps) == 1:
                direct[rows, :3] = light
            else:  # (the rows' centre light was cleared: they left its surface or cross a light edge)
                direct[rows, :3] += light
        if emitted is not None:
            direct[e_rows[e_keep], :3] += emitted.result()
        if kept is not None and kept.size:
            direct[kept, :3] += centre.emitter[kept]
        return direct
    touched = []
    for k, job in lamps:
        rows, light = job.result()
        edge = lamp_edge[rows, k]
        light[edge] -= centre.lamp_light[rows[edge], k]
        direct[rows, :3] += light
        touched.append(rows)
    if emitted is not None:
        direct[e_rows[e_keep], :3] += emitted.result()
    if touched:
        # The differences' rounding, where they were taken (elsewhere nothing is below 0; a
        # strided pass over the whole image cost ~4 ms a subframe).
        rows = np.unique(np.concatenate(touched))
        direct[rows, :3] = np.maximum(direct[rows, :3], 0.0)
    return direct


class _Jobs:
    """A subframe's light calls: each call of at most one block of `GISystem.direct`'s rays is a
    job on the system's worker pool, submitted at once; a larger one runs on this thread after
    them (`run_large`), where it splits its own blocks over the pool (on a pool thread it would
    trace them one after another). On a thread of the pool itself every call runs at once (a
    worker waiting on jobs queued behind itself deadlocks). `submit` returns a future."""

    def __init__(self, system, samples: int):
        updater = getattr(system, "updater", None)
        self._pool = None if updater is None or updater.on_pool_thread() else updater.pool
        self._most = max(1, DIRECT_BLOCK_RAYS // max(samples, 1))  # points per call that go to the pool
        self._large: list = []

    def submit(self, points: int, fn, *args, **kwargs) -> futures.Future:
        if self._pool is not None and points <= self._most:
            return self._pool.submit(fn, *args, **kwargs)
        future = futures.Future()
        self._large.append((future, fn, args, kwargs))
        return future

    def run_large(self) -> None:
        for future, fn, args, kwargs in self._large:
            future.set_result(fn(*args, **kwargs))
        self._large = []


class FilmAccumulator:
    """Sums the subframes' passes with equal weights (the filter is importance-sampled).

    `add(passes)` per subframe (the numpy reference of `accumulate.AccumulatePass`, whose sums
    `set_sums` takes), `read(name)` at the end: the averaged passes of AVERAGED_PASSES,
    "normal" (the average of hit normals, 0 where a subframe saw the background),
    "combined_premultiplied" (rgb times alpha averaged: a transparent film's Combined, where the
    background adds nothing) and "depth" (set once with `set_depth`).
    """

    def __init__(self) -> None:
        self._sums: dict[str, np.ndarray] = {}
        self.count = 0
        self._depth = None
        self._taps = np.ones(1)
        self._filtered: dict[str, np.ndarray] = {}
        self._resolved: dict[str, np.ndarray] = {}  # passes resolved on the GPU (`set_resolved`)

    def set_filter(self, taps: np.ndarray) -> None:
        """Filter every pass but Depth by the separable `taps` (`reconstruction_taps`) as it is
        read (the glossy passes as `set_glossy` takes them, so set the filter first): Cycles'
        pixel filter over the neighbours' samples. The sums are filtered, not the averages: the
        colour-divided passes stay their filtered light over their filtered colour, as Cycles'
        film divides."""
        self._taps = np.asarray(taps, np.float64)
        self._filtered = {}

    def _sum(self, name: str) -> np.ndarray:
        """The sum of pass `name` over the subframes, filtered by the film's taps (once)."""
        if self._taps.size == 1:
            return self._sums[name]
        if name not in self._filtered:
            self._filtered[name] = filter_image(self._sums[name], self._taps)
        return self._filtered[name]

    def add(self, passes: dict[str, np.ndarray]) -> None:
        """passes : name -> (h, w, c) float32 of one subframe: AVERAGED_PASSES, "normal" and
        "depth" (the subframe's, to mask its background normals)."""
        color = passes["diffuse_color"]
        for name in AVERAGED_PASSES:
            value = passes[name]
            if name in COLOR_DIVIDED_PASSES:
                value = value.copy()
                value[..., :3] *= color[..., :3]
            self._accumulate(name, value)
        combined = passes["combined"]
        premultiplied = combined.copy()
        premultiplied[..., :3] *= combined[..., 3:4]
        self._accumulate("combined_premultiplied", premultiplied)
        normal = passes["normal"][..., :3] * (passes["depth"] < 1e9)
        self._accumulate("normal", normal)
        self.count += 1

    def set_sums(self, sums: dict[str, np.ndarray], count: int) -> None:
        """Take the sums of `count` subframes summed elsewhere (accumulate.AccumulatePass, the GPU
        twin of `add`): the names `read` knows, except depth."""
        # float32 as the GPU summed them: no copies of every full-resolution pass.
        self._sums = {name: np.asarray(v, np.float32) for name, v in sums.items()}
        self._filtered = {}
        self._resolved = {}
        self.count = int(count)

    def set_resolved(self, passes: dict[str, np.ndarray], count: int) -> None:
        """Take the passes of `count` subframes resolved elsewhere (`film_resolve.FilmResolvePass`,
        the GPU twin of `read`: the same filter, set with `set_filter` first, and divisions):
        `read` returns them as they are."""
        self._resolved = {name: np.asarray(v, np.float32) for name, v in passes.items()}
        self._sums = {}
        self._filtered = {}
        self.count = int(count)

    def set_glossy(self, radiance, colour, height: int, width: int, indirect=None) -> None:
        """The glossy passes, from (h w, 4) lamp radiance and Glossy Color of the centre raster
        (None: no glossy lobes, all 0): "glossy_color", "glossy_direct" (radiance / colour,
        Cycles' division, 0 where the colour is) and "glossy_indirect" (`indirect`, the light
        before its colour, 0 where the colour is)."""
        shape = (height, width, 3)
        if radiance is None:
            self._extra = {name: np.zeros(shape, np.float32) for name in ("glossy_color", "glossy_direct", "glossy_indirect")}
            return
        radiance = filter_image(radiance[:, :3].reshape(shape), self._taps)
        raw_colour = colour[:, :3].reshape(shape)
        colour = filter_image(raw_colour, self._taps)
        # Divided where the pixel's own colour is (a neighbour's filtered share alone is not).
        own = (colour > 1e-8) & rows_above(raw_colour.reshape(-1, 3), 1e-8).reshape(shape[:2] + (1,))
        direct = np.divide(radiance, colour, out=np.zeros(shape, np.float32), where=own)
        light = np.zeros(shape, np.float32)
        if indirect is not None:  # the light before its colour: its colour-weighted filter over the colour's
            bounced = filter_image(indirect[:, :3].reshape(shape) * raw_colour, self._taps)
            np.divide(bounced, colour, out=light, where=own)
        self._extra = {"glossy_color": colour, "glossy_direct": direct.astype(np.float32),
                       "glossy_indirect": np.where(colour > 1e-8, light, 0.0).astype(np.float32)}

    def set_refraction(self, coverage: np.ndarray, radiance: np.ndarray) -> None:
        """The camera's refractive glass (`refraction.render_glass`: coverage (h, w), radiance
        (h, w, 3), rows bottom-up; set after the glossy passes): Combined becomes the see-through
        image where a pixel's rays missed the glass and their paths' light where they met it; the
        Diffuse and Glossy Color passes keep the share that missed (Cycles' light through glass
        is its Transmission passes'), and the passes divided by them stay as they are, but for
        pixels all of whose rays met glass: 0 there, as Cycles' (no sample saw a diffuse colour;
        the see-through surface's light had stayed: a glass ball's pixels read its floor's
        Diffuse Direct, 0.38 on average, where Cycles' read 0)."""
        c = np.asarray(coverage, np.float32)[..., None]
        extra = dict(getattr(self, "_extra", {}))
        # A transparent film's Combined too: glass is opaque to it, as Cycles' refracting glass is
        # (its light through glass is no camera ray's, and the world it reaches is seen).
        for name in ("combined", "combined_premultiplied"):
            try:
                value = np.array(self.read(name), np.float32)
            except KeyError:
                continue
            value[..., :3] = (1.0 - c) * value[..., :3] + c * np.asarray(radiance, np.float32)
            if value.shape[-1] > 3:
                value[..., 3:4] = (1.0 - c) * value[..., 3:4] + c
            extra[name] = value
        # The colours keep the share that missed; the light passes divided by them are 0 where
        # nothing missed.
        scales = {name: 1.0 - c for name in ("diffuse_color", "glossy_color")}
        scales.update(dict.fromkeys(COLOR_DIVIDED_PASSES, c < np.float32(1.0 - 1e-6)))
        for name, scale in scales.items():
            try:
                value = np.array(self.read(name), np.float32)
            except KeyError:
                continue
            value[..., :3] *= scale
            extra[name] = value
        self._extra = extra

    def set_depth(self, depth: np.ndarray) -> None:
        """The Depth pass: one point sample per pixel, not filtered (see the module docstring)."""
        self._depth = np.array(depth, np.float32)

    def _accumulate(self, name: str, value: np.ndarray) -> None:
        self._filtered.pop(name, None)
        self._resolved.pop(name, None)
        total = self._sums.get(name)
        if total is None:
            self._sums[name] = np.array(value, np.float64)
        else:
            total += value

    def read(self, name: str) -> np.ndarray:
        """The pass `name` as (h, w, c) float32, rows bottom-up."""
        if name in getattr(self, "_extra", {}):
            return self._extra[name]
        if name == "depth":
            if self._depth is None:
                raise KeyError("depth was never set")
            return self._depth
        if self.count == 0:
            raise KeyError(f"{name}: no subframe was added")
        if name in self._resolved:
            return self._resolved[name]
        if name in COLOR_DIVIDED_PASSES:
            out = _divide_even(self._sum(name), self._sum("diffuse_color"), self.count)
            if self._taps.size > 1:
                # A pixel none of whose own samples saw a diffuse colour keeps 0, as in Cycles: the
                # filter's few % of a neighbour's colour would make it that neighbour's light.
                colour = self._sums["diffuse_color"]
                out[..., :3] *= rows_above(colour.reshape(-1, colour.shape[-1])[:, :3], 0.0).reshape(colour.shape[:2] + (1,))
            return out
        return (self._sum(name) / self.count).astype(np.float32)


def _divide_even(light: np.ndarray, color: np.ndarray, count: int) -> np.ndarray:
    """light / color per channel, as Cycles' `safe_divide_even_color`: a channel whose colour is 0
    takes the mean ratio of the pixel's other channels, a black pixel 0. Alpha: the average."""
    # Channel by channel on contiguous planes: reductions over a last axis of 3 and strided
    # (h, w, 3)-of-4 views cost ~20 ms per pass at 640x360; the same float32 sums in the same order.
    n = light.shape[0] * light.shape[1]
    flat_light = light.reshape(n, light.shape[-1])
    flat_color = color.reshape(n, color.shape[-1])
    ok = [flat_color[:, k] > 0 for k in range(3)]
    ratio = [np.zeros(n, np.float32) for _ in range(3)]
    total = np.zeros(n, np.float32)
    valid = np.zeros(n, np.float32)
    for k in range(3):
        np.divide(flat_light[:, k], flat_color[:, k], out=ratio[k], where=ok[k])
        total += ratio[k]
        valid += ok[k]
    mean = np.divide(total, valid, out=np.zeros(n, np.float32), where=valid > 0)
    out = np.zeros((n, light.shape[-1]), np.float32)
    for k in range(3):
        out[:, k] = np.where(ok[k], ratio[k], mean)
    if light.shape[-1] > 3:
        out[:, 3:] = flat_light[:, 3:] / np.float32(count)
    return out.reshape(light.shape)

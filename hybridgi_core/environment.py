"""An environment map (an HDRI world) split into what the renderer can light with: a shadowed sun
plus the sky without it.

Spreading an HDRI's mean over the whole sky puts its sun's energy on surfaces the sun never
reaches (an atrium lit by `sunrise.exr` came out 2.3x too bright against Cycles).
`split_environment` finds the map's brightest compact region (the sun disc and its glow), turns
it into a SUN lamp (direction, irradiance, angular diameter, shadowed by the lamp code like any
other), then up to MAX_SUNS - 1 further compact regions of at most MAX_MORE_SUN_ANGLE (a studio
map's softboxes, an interior's windows and lamps) the same way, and keeps the rest three ways: a coarse map that escaping rays read by direction
(`SkyMap`), its L2 SH, and its uniform mean (what a surface facing up receives from the upper
hemisphere; the background colour).

Equirectangular maps follow Blender's convention (`equirect_directions`): row 0 at the bottom
(the nadir), the middle column facing +X, u growing clockwise seen from above; `to_world` maps
texture directions to world directions (the inverse of a Mapping node's transform). Pure numpy.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from .sh import basis

#: Half-angle (radians) around the brightest pixel within which the sun region is looked for.
SUN_SEARCH = np.radians(12.0)
#: A pixel belongs to the sun region when brighter than this share of the brightest pixel.
SUN_THRESHOLD = 0.02
#: The region counts as a sun only if it carries this share of the light a surface facing it gets.
SUN_MIN_SHARE = 0.2
#: Compact bright regions split off a map as shadowed SUN lamps, at most (`split_environment`).
MAX_SUNS = 4
#: Widest angular diameter a further region may have to be split off (`split_environment`): a
#: broad bright patch (forest.exr's sky through the trees, 20 degrees) lights better from the map.
MAX_MORE_SUN_ANGLE = np.radians(15.0)
#: Rec.709 luminance weights.
LUMA = np.array([0.2126, 0.7152, 0.0722], np.float64)
#: Rows of the equirectangular sky map rays read (columns: twice as many); ~2.8 degrees a texel.
SKY_MAP_ROWS = 64
#: Directions `BackgroundMap.radiance` reads at once.
BLOCK_DIRECTIONS = 1 << 18
#: Widest map the camera's background keeps (texels across; wider maps are halved until they
#: fit): 11 texels a degree, what a 1920-pixel view of 40 degrees or wider shows. A 4096 x 2048
#: map is 48 MiB of half floats on the GPU (RGBA); an 8K HDRI would be four times that.
BACKGROUND_MAX_WIDTH = 4096
#: The sky a split keeps (its uniform mean, SH and SKY_MAP_ROWS map) is taken from a copy of the
#: map at most this many texels across (`split_environment`).
SPLIT_WIDTH = 1024


@dataclass(frozen=True)
class EnvironmentSplit:
    """sun_direction : (3,) unit world direction towards the sun, None when the map has none
    sun_irradiance : (3,) W/m^2 on a surface facing the sun (a SUN lamp's colour x strength)
    sun_angle : radians, angular diameter of the region (the SUN lamp's angle)
    sky : (3,) radiance of the uniform sky that stands for the rest of the map (the mean a
        surface facing up receives)
    sky_sh : (9, 3) L2 radiance SH of the rest of the map
    sky_map : (SKY_MAP_ROWS, 2 SKY_MAP_ROWS, 3) float32 the rest of the map (the sun region
        filled), area-averaged down (maps no larger keep their pixels): what rays that escape read
        (`SkyMap`)
    """

    sun_direction: np.ndarray | None
    sun_irradiance: np.ndarray
    sun_angle: float
    sky: np.ndarray
    sky_sh: np.ndarray
    sky_map: np.ndarray | None = None
    to_world: np.ndarray | None = None  # (3, 3) the map's texture -> world directions, as given
    #: (h, w, 3) float16 the whole map, sun included, at most BACKGROUND_MAX_WIDTH texels across
    #: (`background_pixels`): what the camera sees of the world (`BackgroundMap`)
    background: np.ndarray | None = None
    #: ((3,) direction, (3,) irradiance, angle) of each further compact bright region (a studio
    #: map's other softboxes), split off as the sun is, brightest first (`MAX_SUNS` in all)
    more_suns: tuple = ()


#: Changes whenever `split_environment`'s answer for the same map changes: splits kept on disk
#: (`split_arrays`, the add-on's split store) are keyed by it.
SPLIT_VERSION = 1


def split_arrays(split: EnvironmentSplit) -> dict[str, np.ndarray]:
    """`split` as named arrays (for `np.savez`; `split_from_arrays` reads them back)."""
    out = {"sun_irradiance": np.asarray(split.sun_irradiance), "sun_angle": np.asarray(float(split.sun_angle)),
           "sky": np.asarray(split.sky), "sky_sh": np.asarray(split.sky_sh)}
    optional = {"sun_direction": split.sun_direction, "sky_map": split.sky_map, "to_world": split.to_world,
                "background": split.background}
    out.update({name: np.asarray(value) for name, value in optional.items() if value is not None})
    for i, (direction, irradiance, angle) in enumerate(split.more_suns):
        out[f"more_sun_{i}_direction"] = np.asarray(direction)
        out[f"more_sun_{i}_irradiance"] = np.asarray(irradiance)
        out[f"more_sun_{i}_angle"] = np.asarray(float(angle))
    return out


def split_from_arrays(arrays) -> EnvironmentSplit:
    """The `EnvironmentSplit` that `split_arrays` wrote (arrays: a mapping such as `np.load`'s)."""
    names = set(arrays.keys())
    get = lambda name: np.asarray(arrays[name]) if name in names else None  # noqa: E731
    suns = []
    while f"more_sun_{len(suns)}_angle" in names:
        i = len(suns)
        suns.append((get(f"more_sun_{i}_direction"), get(f"more_sun_{i}_irradiance"), float(get(f"more_sun_{i}_angle"))))
    return EnvironmentSplit(get("sun_direction"), get("sun_irradiance"), float(get("sun_angle")), get("sky"),
                            get("sky_sh"), get("sky_map"), get("to_world"), get("background"), tuple(suns))


def equirect_directions(height: int, width: int, rows: slice | None = None) -> tuple[np.ndarray, np.ndarray]:
    """((h, w, 3) unit texture-space directions of the pixel centres, (h,) solid angle of a pixel
    in each row). Blender/Cycles: u = (pi - atan2(y, x)) / 2pi, v = 0.5 + asin(z) / pi.
    rows : only those rows of the map (their directions and solid angles)."""
    v = (np.arange(height)[rows if rows is not None else slice(None)] + 0.5) / height
    u = (np.arange(width) + 0.5) / width
    latitude = (v - 0.5) * np.pi
    longitude = np.pi - 2.0 * np.pi * u
    cl = np.cos(latitude)[:, None]
    dirs = np.stack(np.broadcast_arrays(cl * np.cos(longitude)[None, :], cl * np.sin(longitude)[None, :],
                                        np.sin(latitude)[:, None]), axis=-1)
    solid = (2.0 * np.pi / width) * (np.pi / height) * np.cos(latitude)
    return dirs, solid


def _to_world(dirs: np.ndarray, to_world: np.ndarray | None) -> np.ndarray:
    """Unit world directions of texture-space `dirs` (..., 3)."""
    if to_world is None:
        return dirs
    dirs = dirs @ np.asarray(to_world, np.float64).T
    dirs /= np.maximum(np.linalg.norm(dirs, axis=-1, keepdims=True), 1e-12)
    return dirs


def _rotation(to_world: np.ndarray | None) -> bool:
    """Whether `to_world` keeps angles (a rotation, the common Mapping node): then the cosines
    between directions can be taken in texture space, without turning every pixel's direction."""
    if to_world is None:
        return True
    m = np.asarray(to_world, np.float64)
    return bool(np.allclose(m.T @ m, np.eye(3), atol=1e-9))


def _clean(pixels: np.ndarray) -> np.ndarray:
    """A float32 copy of a map with non-finite and negative values as 0 (one pass where there are
    none: np.nan_to_num's four take ~4x as long on a 4K map)."""
    p = np.array(pixels, np.float32)
    bad = ~np.isfinite(p)
    if bad.any():
        p[bad] = 0.0
    np.maximum(p, 0.0, out=p)
    return p


def split_environment(pixels: np.ndarray, to_world: np.ndarray | None = None) -> EnvironmentSplit:
    """Split an (h, w, 3) linear equirectangular radiance map (see the module docstring).

    The sun is found and measured at the map's own resolution, in the rows within SUN_SEARCH of
    its brightest pixel; the sky it leaves (its uniform mean, SH and coarse map) is taken from a
    copy box-filtered to at most SPLIT_WIDTH texels across. Why: an L2 SH and a 64-row map need
    no more, and a 4096 x 2048 HDRI's float64 planes over every pixel (directions, nine SH bases)
    cost 2.3-5 s of its first sync; now ~0.4 s."""
    full = _clean(pixels)
    background = background_pixels(full, clean=True)
    h, w = full.shape[:2]
    work = _box_equirect(full, SPLIT_WIDTH).astype(np.float64)
    wh, ww = work.shape[:2]
    dirs, solid = equirect_directions(wh, ww)
    dirs = _to_world(dirs, to_world)
    weight = np.broadcast_to(solid[:, None], (wh, ww))
    suns = []
    for _ in range(MAX_SUNS):
        found = _take_sun(full, work, dirs, weight, to_world, MAX_MORE_SUN_ANGLE if suns else np.pi)
        if found is None:
            break
        suns.append(found)
    sun, irradiance, angle = suns[0] if suns else (None, np.zeros(3), 0.0)
    # The uniform sky: the cosine-weighted mean over the upper hemisphere (irradiance / pi of an
    # unoccluded surface facing up).
    up = np.clip(dirs[..., 2], 0.0, None) * weight
    sky = (work * up[..., None]).sum(axis=(0, 1)) / max(float(up.sum()), 1e-12)
    flat = dirs.reshape(-1, 3)
    sky_sh = basis(flat, 2).astype(np.float64).T @ (work.reshape(-1, 3) * weight.reshape(-1, 1))
    return EnvironmentSplit(sun, irradiance.astype(np.float32), angle, sky.astype(np.float32), sky_sh.astype(np.float32),
                            sky_map=downsample_equirect(work, solid, SKY_MAP_ROWS),
                            to_world=None if to_world is None else np.asarray(to_world, np.float64),
                            background=background,
                            more_suns=tuple((d, e.astype(np.float32), a) for d, e, a in suns[1:]))


def _take_sun(full: np.ndarray, work: np.ndarray, dirs: np.ndarray, weight: np.ndarray, to_world,
              widest: float = np.pi):
    """(unit world direction, (3,) irradiance on a surface facing it, angular diameter) of the
    compact region around the brightest pixel of `full` (the map at its own resolution), if it
    carries SUN_MIN_SHARE of the light a surface facing it gets; its pixels are then filled with
    the ring around them, in `full` and in its filtered copy `work` (both in place). None: no sun
    (left as they are), as for a region wider than `widest` (radians)."""
    h, w = full.shape[:2]
    wh, ww = work.shape[:2]
    luma_full = full @ LUMA.astype(np.float32)
    peak = np.unravel_index(int(np.argmax(luma_full)), luma_full.shape)
    peak_luma = float(luma_full[peak])
    if peak_luma <= 0:
        return None
    peak_tex = equirect_directions(h, w, slice(peak[0], peak[0] + 1))[0][0, peak[1]]
    peak_dir = _to_world(peak_tex[None], to_world)[0]
    # Light from the whole map on a surface facing the peak (the filtered copy: the share test).
    total_light = float(((work @ LUMA) * weight * np.clip(dirs @ peak_dir, 0.0, None)).sum())
    # The rows the sun's region can reach: within SUN_SEARCH of the peak's latitude.
    reach = int(np.ceil(SUN_SEARCH / np.pi * h)) + 1
    rows = slice(max(peak[0] - 2 * reach, 0), min(peak[0] + 2 * reach + 1, h))
    band = full[rows].astype(np.float64)
    b_dirs, b_solid = equirect_directions(h, w, rows)
    if _rotation(to_world):  # cosines in texture space: the band's directions stay unturned
        to_peak = b_dirs @ peak_tex
        if to_world is not None:
            b_dirs = _LazyWorld(b_dirs, to_world)
    else:
        b_dirs = _to_world(b_dirs, to_world)
        to_peak = b_dirs @ peak_dir  # cosine of each pixel's angle to the brightest one
    luma = band @ LUMA
    b_weight = np.broadcast_to(b_solid[:, None], luma.shape)
    region = (to_peak > np.cos(SUN_SEARCH)) & (luma > SUN_THRESHOLD * peak_luma)
    region_light = float((luma * b_weight * np.clip(to_peak, 0.0, None))[region].sum())
    if region_light <= SUN_MIN_SHARE * total_light:
        return None
    power = (luma * b_weight)[region]
    sun = (b_dirs[region] * power[:, None]).sum(axis=0)
    sun /= np.linalg.norm(sun)
    # Irradiance on a surface facing the sun: the region's radiance times its solid angle.
    irradiance = (band[region] * b_weight[region][:, None] * np.clip(b_dirs[region] @ sun, 0, None)[:, None]).sum(axis=0)
    omega = float(b_weight[region].sum())
    angle = float(2.0 * np.sqrt(omega / np.pi))
    if angle > widest:
        return None
    # The sky behind the sun: the ring around the region, not its glow.
    ring = (to_peak > np.cos(2.0 * SUN_SEARCH)) & ~region
    fill = (band[ring] * b_weight[ring][:, None]).sum(axis=0) / max(float(b_weight[ring].sum()), 1e-12)
    band[region] = fill
    full[rows] = band
    # The filtered copy again, in the rows the fill reaches.
    f = w // ww  # the copy's texels per side of the map's (halvings of even sides: exact)
    lo, hi = rows.start // f, min(-(-rows.stop // f), wh)
    work[lo:hi] = _box_equirect(full[lo * f:hi * f], SPLIT_WIDTH, lo * f, h)
    return sun, irradiance, angle


def _box_equirect(pixels: np.ndarray, max_width: int, first: int = 0, total: int | None = None) -> np.ndarray:
    """(h', w', 3) float32 of an (h, w, 3) equirectangular map: solid-angle-weighted 2 x 2 means
    (rows nearer a pole cover less of the sphere) until at most `max_width` texels across, or
    until a side is odd (a dropped row or column would shift every texel's direction).
    first, total : the rows are rows first.. of a map `total` rows high (a band of it, `first` a
    multiple of 2^halvings: its rows' latitudes)."""
    p = np.asarray(pixels, np.float32)
    total = p.shape[0] if total is None else total
    while p.shape[1] > max_width and p.shape[0] % 2 == 0 and p.shape[1] % 2 == 0:
        h, w = p.shape[:2]
        cos = np.cos(((first + np.arange(h) + 0.5) / total - 0.5) * np.pi).astype(np.float32)
        cols = p[:h, 0:w:2] + p[:h, 1:w:2]
        ct, cb = cos[0::2, None, None], cos[1::2, None, None]
        p = (cols[0::2] * ct + cols[1::2] * cb) / (2.0 * (ct + cb))
        first, total = first // 2, total // 2
    return p


class _LazyWorld:
    """Texture-space directions turned to world ones only where indexed (`split_environment`:
    the sun's region is a few hundred of the band's millions of pixels)."""

    def __init__(self, dirs: np.ndarray, to_world: np.ndarray):
        self.dirs, self.to_world = dirs, to_world

    def __getitem__(self, index) -> np.ndarray:
        return _to_world(self.dirs[index], self.to_world)


def background_pixels(pixels: np.ndarray, max_width: int = BACKGROUND_MAX_WIDTH, clean: bool = False) -> np.ndarray:
    """(h', w', 3) float16 of an (h, w, 3) equirectangular map for the camera's background: 2 x 2
    box means until it is at most `max_width` texels across (an odd row or column is dropped),
    non-finite and negative values as 0, values beyond half-float range clamped to it (a sun
    disc's 1e5-1e6 stays within: 65504 is the limit, a brighter texel would turn infinite).
    clean : the caller's map is float32 without such values already (`_clean`)."""
    p = np.asarray(pixels, np.float32) if clean else _clean(pixels)
    while p.shape[1] > max_width and p.shape[0] >= 2:
        h, w = p.shape[0] // 2 * 2, p.shape[1] // 2 * 2
        p = p[:h, :w].reshape(h // 2, 2, w // 2, 2, 3).mean(axis=(1, 3), dtype=np.float32)
    return np.minimum(p, np.float32(np.finfo(np.float16).max)).astype(np.float16)


@dataclass(frozen=True)
class BackgroundMap:
    """What the camera sees of the world, by direction: an equirectangular radiance map (Blender's
    layout, `equirect_directions`) times `strength`, rotated by `to_world` (texture -> world
    directions, a Mapping node's inverse; None: unrotated).

    Why: the light of an environment map is split into a sun, an SH sky and a coarse map
    (`split_environment`), none of which is what an artist sees behind the scene; the camera
    sees the HDRI itself, as in Cycles. The GPU draws it per pixel (`raster.world_background`);
    `radiance` is the same lookup in numpy."""

    pixels: np.ndarray  # (h, w, 3) float16 (`background_pixels`)
    strength: float = 1.0
    to_world: np.ndarray | None = None

    def radiance(self, directions: np.ndarray) -> np.ndarray:
        """(n, 3) float32 radiance towards unit world directions (n, 3), bilinear as the GPU reads;
        in blocks of BLOCK_DIRECTIONS (an empty 4K frame's 8M directions in one piece cost ~1 GB)."""
        d = np.asarray(directions, np.float32).reshape(-1, 3)
        out = np.empty((d.shape[0], 3), np.float32)
        for a in range(0, d.shape[0], BLOCK_DIRECTIONS):
            out[a:a + BLOCK_DIRECTIONS] = self._sky.radiance(d[a:a + BLOCK_DIRECTIONS])
        out *= np.float32(self.strength)
        return out

    @functools.cached_property
    def _sky(self) -> SkyMap:
        """The map as a float32 `SkyMap` (made once: a 4096-wide map is 100 MB)."""
        return SkyMap(np.asarray(self.pixels, np.float32), self.to_world)

    def texture_from_world(self) -> np.ndarray:
        """(3, 3) float64 world -> texture directions."""
        return np.eye(3) if self.to_world is None else np.linalg.inv(np.asarray(self.to_world, np.float64))


def downsample_equirect(pixels: np.ndarray, solid: np.ndarray, rows: int) -> np.ndarray:
    """(rows, 2 rows, 3) float32 solid-angle-weighted means of an (h, w, 3) equirectangular map
    (solid (h,): a pixel's solid angle in each row) over the coarser map's texels, in the same
    layout; maps smaller than that keep their own pixels."""
    h, w = pixels.shape[:2]
    if h <= rows:
        return np.asarray(pixels, np.float32)
    r = (np.arange(h) * rows) // h
    c = (np.arange(w) * 2 * rows) // w
    cell = (r[:, None] * 2 * rows + c[None, :]).ravel()
    wt = np.broadcast_to(solid[:, None], (h, w)).ravel()
    count = rows * 2 * rows
    total = np.bincount(cell, weights=wt, minlength=count)
    out = np.stack([np.bincount(cell, weights=pixels[..., k].ravel() * wt, minlength=count) for k in range(3)], axis=1)
    return (out / np.maximum(total, 1e-30)[:, None]).reshape(rows, 2 * rows, 3).astype(np.float32)


class SkyMap:
    """An equirectangular radiance map read bilinearly in world directions.

    Why not the L2 SH alone: a room sees the sky through a window or a door, and an outdoor
    scene's ground sees the bright horizon, directions where nine coefficients ring or clip; rays
    (probe and pixel) that escape read the map itself, as Cycles does.

    pixels : (h, w, 3) float32 in Blender's layout (`equirect_directions`); to_world : (3, 3)
    texture -> world directions (a Mapping node's inverse), or None.
    """

    def __init__(self, pixels: np.ndarray, to_world: np.ndarray | None = None):
        self.pixels = np.ascontiguousarray(pixels, np.float32)
        self.to_texture = None if to_world is None else np.linalg.inv(np.asarray(to_world, np.float64)).astype(np.float32)
        self.to_world = None if to_world is None else np.asarray(to_world, np.float32)
        self._sampler = None

    def sampler(self) -> SkySampler:
        """The map's `SkySampler` (made on first use; any thread: a race only makes it twice)."""
        if self._sampler is None:
            self._sampler = SkySampler(self)
        return self._sampler

    def radiance(self, directions: np.ndarray) -> np.ndarray:
        """(n, 3) float32 radiance towards unit world directions (n, 3)."""
        d = np.asarray(directions, np.float32).reshape(-1, 3)
        if self.to_texture is not None:
            d = d @ self.to_texture.T
        h, w = self.pixels.shape[:2]
        x, y, z = d[:, 0], d[:, 1], d[:, 2]
        norm = np.sqrt(x * x + y * y + z * z)
        u = (np.float32(np.pi) - np.arctan2(y, x)) * np.float32(0.5 / np.pi)
        v = np.float32(0.5) + np.arcsin(np.clip(z / np.maximum(norm, np.float32(1e-30)), -1.0, 1.0)) * np.float32(1.0 / np.pi)
        fx = u * np.float32(w) - np.float32(0.5)
        fy = np.clip(v * np.float32(h) - np.float32(0.5), 0.0, np.float32(h - 1))
        x0 = np.floor(fx)
        y0 = np.minimum(np.floor(fy), np.float32(max(h - 2, 0)))
        tx, ty = (fx - x0)[:, None], (fy - y0)[:, None]
        c0 = x0.astype(np.int64) % w
        c1 = (c0 + 1) % w
        r0 = y0.astype(np.int64)
        r1 = np.minimum(r0 + 1, h - 1)
        p = self.pixels
        top = p[r0, c0] * (1 - tx) + p[r0, c1] * tx
        bottom = p[r1, c0] * (1 - tx) + p[r1, c1] * tx
        return (top * (1 - ty) + bottom * ty).astype(np.float32)


#: Share of a `SkySampler`'s samples drawn uniformly over the sphere (by solid angle), the rest by
#: the texels' power: every direction keeps a density, however dark its texel.
UNIFORM_SHARE = 0.1


class SkySampler:
    """Directions drawn from a `SkyMap` by its texels' squared luminance x solid angle,
    uniform within a texel in (u, v), mixed with UNIFORM_SHARE of uniform directions, and the
    density of any direction under that distribution (per steradian, world directions).

    Why: a compact bright region left in the map (a sun too weak to be split off, a window, a
    softbox) is found by a glossy lobe's own samples once in many pixels, with a huge value
    (fireflies on rough metal under sunset.exr); drawn by its power and weighed against the lobe's
    samples (multiple importance sampling, `reflection.py`) it is found at every pixel, as Cycles'
    world importance map finds it."""

    def __init__(self, sky: SkyMap):
        self.sky = sky
        h, w = sky.pixels.shape[:2]
        self.shape = (h, w)
        _dirs, solid = equirect_directions(h, w)
        # By squared luminance: the lobe's own samples do well on the smooth rest of the sky; these
        # go where it is far brighter than that (luminance alone sent 4/5 of them to a sunset's
        # plain sky: 0.63 of the lobe rays' noise left, against 0.3 this way).
        luma = np.maximum(sky.pixels.astype(np.float64) @ LUMA, 0.0)
        power = luma * luma * solid[:, None]
        total = float(power.sum())
        area = np.broadcast_to(solid[:, None], (h, w)) / (4.0 * np.pi)
        p = (1.0 - UNIFORM_SHARE) * power / total + UNIFORM_SHARE * area if total > 0 else area.copy()
        self.texel_p = (p / p.sum()).ravel()  # probability of each texel
        self.cdf = np.cumsum(self.texel_p)
        self.cdf[-1] = 1.0

    def sample(self, u0: np.ndarray, u1: np.ndarray, u2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """((n, 3) float32 unit world directions, (n,) float32 densities) from uniform numbers."""
        h, w = self.shape
        texel = np.minimum(np.searchsorted(self.cdf, np.asarray(u0, np.float64), side="right"), h * w - 1)
        row, col = np.divmod(texel, w)
        uu = (col + np.asarray(u1, np.float64)) / w
        vv = (row + np.asarray(u2, np.float64)) / h
        lat = (vv - 0.5) * np.pi
        lon = np.pi - 2.0 * np.pi * uu
        cl = np.cos(lat)
        d = np.stack([cl * np.cos(lon), cl * np.sin(lon), np.sin(lat)], axis=1)
        if self.sky.to_world is not None:
            d = d @ self.sky.to_world.T.astype(np.float64)
            d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-30)
        pdf = self.texel_p[texel] / ((2.0 * np.pi / w) * (np.pi / h) * np.maximum(cl, 1e-6))
        return d.astype(np.float32), pdf.astype(np.float32)

    def pdf(self, directions: np.ndarray) -> np.ndarray:
        """(n,) float32 density (per steradian) of drawing the unit world `directions` (n, 3)."""
        h, w = self.shape
        d = np.asarray(directions, np.float32).reshape(-1, 3)
        if self.sky.to_texture is not None:
            d = d @ self.sky.to_texture.T
        x, y, z = d[:, 0], d[:, 1], d[:, 2]
        norm = np.maximum(np.sqrt(x * x + y * y + z * z), np.float32(1e-30))
        sin_lat = np.clip(z / norm, -1.0, 1.0)
        u = (np.float32(np.pi) - np.arctan2(y, x)) * np.float32(0.5 / np.pi)
        v = np.float32(0.5) + np.arcsin(sin_lat) * np.float32(1.0 / np.pi)
        col = np.clip((u * w).astype(np.int64), 0, w - 1)
        row = np.clip((v * h).astype(np.int64), 0, h - 1)
        cl = np.sqrt(np.maximum(1.0 - sin_lat * sin_lat, 0.0))
        return (self.texel_p[row * w + col] / ((2.0 * np.pi / w) * (np.pi / h) * np.maximum(cl, 1e-6))).astype(np.float32)

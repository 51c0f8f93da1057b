"""Frozen settings of the irradiance cache and its ray sampling (units in comments).

Every field is checked on construction (`check_ranges`): a value that is not finite or lies
outside its documented range raises `SettingsError` naming the field and the range, never
clamped, so a NaN typed into the viewport cannot reach the pixels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

from .errors import LimitError, SettingsError

#: Indirect quality levels: what a probe ray's hit contributes.
AO_ONLY = 0  # occlusion and depth only; no radiance at hits
ONE_BOUNCE = 1  # hits shaded by lamps, emission and sky: one bounce of indirect light
MULTI_BOUNCE = 2  # hits also read the cache itself: converges to the multi-bounce solution

#: Default cap of the cache's CPU arrays (MiB). Resolution 128 on a cube-shaped scene needs ~1.6 GiB;
#: the 512 maximum would need over 100 GiB, which no render should start allocating.
DEFAULT_CACHE_MEMORY_MIB = 4096

#: Texels of the largest 2D texture the GPU gather packs the cache into (raster/gather.py): 16384
#: per side, the limit of llvmpipe, Apple and most desktop GPUs (gather checks the real one again).
GPU_TEXTURE_TEXELS = 16384 * 16384

#: Bytes per cell that do not depend on the SH order or the depth map: backface, samples,
#: last_frame (int64), urgency, and the cell centres (3 float32).
_CELL_FIXED_BYTES = 4 + 4 + 8 + 4 + 12


def check_ranges(obj, ranges: dict, what: str) -> None:
    """Raise SettingsError for the first fields of `obj` outside `ranges`.

    ranges : {name: (low, high, low_open, high_open)} with None for an open end, or a frozenset
    of the allowed values. Numbers must be finite.
    """
    problems = []
    for name, rule in ranges.items():
        value = getattr(obj, name)
        if isinstance(rule, frozenset):
            if value not in rule:
                problems.append(f"{name}={value!r} is not one of {', '.join(map(repr, sorted(rule)))}")
            continue
        low, high, low_open, high_open = rule
        if isinstance(value, bool) or not isinstance(value, int | float):
            problems.append(f"{name}={value!r} is not a number")
            continue
        if not math.isfinite(value):
            problems.append(f"{name}={value!r} is not a finite number (valid: {_range_text(rule)})")
            continue
        below = low is not None and (value <= low if low_open else value < low)
        above = high is not None and (value >= high if high_open else value > high)
        if below or above:
            problems.append(f"{name}={value!r} is out of range (valid: {_range_text(rule)})")
    if problems:
        raise SettingsError(f"{what}: " + "; ".join(problems))


def _range_text(rule) -> str:
    low, high, low_open, high_open = rule
    if low is not None and high is not None:
        return f"{low} {'<' if low_open else '<='} value {'<' if high_open else '<='} {high}"
    if low is not None:
        return f"{'>' if low_open else '>='} {low}"
    return f"{'<' if high_open else '<='} {high}"


def _closed(low, high=None):
    return (low, high, False, False)


@dataclass(frozen=True)
class CacheSettings:
    resolution: int = 48  # cells along the longest axis of the grid bounds (48: atrium DI error 0.098 vs Cycles, 32: 0.107)
    sh_order: int = 2  # 1 -> L1 (4 coefficients per channel), 2 -> L2 (9)
    rays_per_cell: int = 64  # probe rays per visible cell per update
    ray_length: float = 0.0  # metres; 0 = unlimited (the scene diagonal)
    hysteresis: float = 0.9  # share of the old value an update keeps (EMA), 0..1
    indirect_quality: int = MULTI_BOUNCE  # AO_ONLY, ONE_BOUNCE or MULTI_BOUNCE
    ao_distance: float = 1.0  # metres; rays longer than this count as unoccluded (World AO distance)
    depth_texels: int = 8  # octahedral depth-moment map per cell is depth_texels^2 (visibility test)
    normal_bias: float = 0.1  # cells; shading points move this far along the normal before the gather
    inside_threshold: float = 0.5  # a cell whose back-face hit share exceeds this is inside geometry
    lod_ratio: float = 1.0  # share of triangles kept in the ray mesh (fast-simplification), 0..1
    light_samples: int = 1  # shadow-ray samples per area/sun light per hit
    seed: int = 0  # base seed; frame f rotates rays with seed + f
    threads: int = 2  # worker threads for tracing and shading
    max_memory_mib: int = DEFAULT_CACHE_MEMORY_MIB  # cap of the cache arrays (check_cell_count)
    #: Camera-centred levels (`levels.py`): 1 = the one grid over the scene; 2-3 add grids of half
    #: the cell size over the nearest visible geometry (final renders with pixel rays)
    cache_levels: int = 1
    #: False: surfaces that rays hit reflect no light (Cycles' diffuse bounce limit 0): beyond its
    #: lamps a pixel sees only the sky and emitters, as Cycles' Diffuse Direct; no Diffuse Indirect.
    bounce_light: bool = True
    #: Cycles' Filter Glossy (`cycles.blur_glossy`; 0 = off): how much Cycles blurs the glossy
    #: lobes of ray hits after a diffuse bounce, which the hits' glossy albedo follows
    #: (`specular.hit_blur_roughness`).
    filter_glossy: float = 1.0

    #: Valid values of each field: (low, high, low_open, high_open) or a frozenset of choices
    #: (a class attribute, not a field: it has no annotation).
    RANGES = {
        "resolution": _closed(1, 512),
        "sh_order": frozenset((1, 2)),
        "rays_per_cell": _closed(1, 65536),
        "ray_length": _closed(0.0),
        "hysteresis": (0.0, 1.0, False, True),
        "indirect_quality": frozenset((AO_ONLY, ONE_BOUNCE, MULTI_BOUNCE)),
        "ao_distance": (0.0, None, True, False),
        "depth_texels": _closed(2, 32),
        "normal_bias": _closed(0.0, 2.0),
        "inside_threshold": (0.0, 1.0, True, False),
        "lod_ratio": (0.0, 1.0, True, False),
        "light_samples": _closed(1, 256),
        "seed": _closed(0),
        "threads": _closed(1, 64),
        "max_memory_mib": _closed(1),
        "cache_levels": _closed(1, 3),
        "filter_glossy": _closed(0.0, 1e6),
    }

    def __post_init__(self) -> None:
        check_ranges(self, self.RANGES, "cache settings")

    @property
    def sh_coeffs(self) -> int:
        """SH coefficients per channel: 4 for L1, 9 for L2."""
        return (self.sh_order + 1) ** 2

    @property
    def cell_bytes(self) -> int:
        """CPU bytes of one cache cell (IrradianceCache's arrays, float32 unless noted)."""
        k, t = self.sh_coeffs, self.depth_texels**2
        return 2 * k * 3 * 4 + k * 4 + t * 2 * 4 + _CELL_FIXED_BYTES

    def check_cell_count(self, dims: tuple[int, int, int]) -> None:
        """Raise LimitError before allocating a cache of `dims` cells that would exceed
        `max_memory_mib` or not fit the gather's GPU textures (GPU_TEXTURE_TEXELS).

        The message names the limit, the estimate and the largest resolution that fits.
        """
        count = int(dims[0]) * int(dims[1]) * int(dims[2])
        texels = count * max(2 * self.sh_coeffs, self.depth_texels**2)
        need = count * self.cell_bytes
        limit = self.max_memory_mib * 2**20
        problems = []
        if need > limit:
            problems.append((need / limit, f"needs {need / 2**30:.1f} GiB, over the cache memory limit of "
                                           f"{limit / 2**30:.1f} GiB"))
        if texels > GPU_TEXTURE_TEXELS:
            problems.append((texels / GPU_TEXTURE_TEXELS, f"needs {texels} texels, over the GPU's "
                                                          "16384x16384 texture limit"))
        if not problems:
            return
        # Cell count grows with the cube of the resolution: the tighter limit sets what fits.
        ratio = max(r for r, _text in problems)
        fits = max(1, int(self.resolution * ratio ** (-1 / 3)))
        raise LimitError(
            f"cache of {dims[0]}x{dims[1]}x{dims[2]} cells at resolution {self.resolution} "
            + " and ".join(text for _r, text in problems)
            + f": lower the HybridGI Resolution to {fits} or less"
        )

    def with_(self, **changes) -> CacheSettings:
        return replace(self, **changes)


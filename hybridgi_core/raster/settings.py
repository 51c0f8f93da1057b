"""Frozen settings of the raster passes (units in comments). Pure Python: no `gpu` import."""

from __future__ import annotations

from dataclasses import dataclass, replace

from ..settings import check_ranges

#: How ray-traced (cache) AO and screen-space AO combine (the seed's MIN and MUL blends).
AO_BLEND_MODES = ("MUL", "MIN")  # index = BLEND_MUL / BLEND_MIN in deferred_frag.glsl

#: Debug views of the deferred pass (its `debug_view` argument).
DEBUG_FINAL = 0  # Combined as rendered
DEBUG_INDIRECT = 1  # albedo x indirect irradiance / pi only
DEBUG_AO = 2  # the combined AO as grey
DEBUG_AO_SPLIT = 3  # left half: ray AO, right half: screen-space AO


@dataclass(frozen=True)
class RasterSettings:
    downsample: int = 4  # full-res pixels per low-res pixel along x and y (GI resolution divisor)
    ssao_radius: float = 0.5  # metres; screen-space AO / near-field bounce search radius
    ssao_strength: float = 1.0  # scales the screen-space occlusion and bounce, 0..4
    ssao_samples: int = 16  # hemisphere samples per low-res pixel
    ao_blend: str = "MUL"  # "MUL": ray_ao * ss_ao; "MIN": min(ray_ao, ss_ao)
    bilateral_radius: int = 2  # low-res taps on each side of the centre, per axis
    bilateral_sigma: float = 1.0  # spatial Gaussian sigma in low-res pixels
    bilateral_plane_sigma: float = 0.02  # plane-distance tolerance as a share of the view depth
    bilateral_normal_power: float = 8.0  # exponent of max(0, n_p . n_q) in the range weight
    #: Per-pixel final-gather rays per GI pixel (`hybridgi_core/pixel_gather.py`); 0 = off: the
    #: cache gather and the screen-space pass alone, as before. On, they replace the gather's
    #: output and the screen-space AO / bounce (the rays see what that pass stood in for).
    pixel_rays: int = 0
    pixel_filter: int = 3  # a-trous passes over the pixel rays' residual (taps 1, 2, 4 .. apart)
    #: Final renders with pixel rays and downsample > 1: resolve the GI per full-res pixel on the CPU
    #: (`pixel_gather.full_res_images`: the cache's SH at every pixel's own normal, own rays where
    #: no GI pixel shares the pixel's surface or the correction varies) instead of the bilateral
    #: upsampling of GI-resolution irradiance.
    pixel_full_res: bool = True
    #: Reflection rays per full-res pixel whose glossy lobe is smoother than
    #: `reflection.TRACE_ROUGHNESS` (`hybridgi_core/reflection.py`); 0 = the cache's hemisphere
    #: mean for every lobe (no image of the surroundings in polished surfaces). 8: at the default
    #: quality 4 -> 8 took the glossy error down by a tenth for ~2% of the frame (dragon 0.0220 ->
    #: 0.0199, bunny 0.0135 -> 0.0120 at 640x360), better than any other knob's trade there.
    reflection_rays: int = 8
    #: The SSAO radius is the automatic one (one level-0 cache cell): with finer cache levels
    #: (`levels.py`) the cache gather's near field is their cell, so the pass searches that far
    #: (`FramePipeline._gather_levels`).
    ssao_auto: bool = False

    #: Valid values of each field, as in CacheSettings.RANGES.
    RANGES = {
        "downsample": (1, 16, False, False),
        "ssao_radius": (0.0, None, True, False),
        "ssao_strength": (0.0, 4.0, False, False),
        "ssao_samples": (1, 64, False, False),
        "ao_blend": frozenset(AO_BLEND_MODES),
        "bilateral_radius": (0, 8, False, False),
        "bilateral_sigma": (0.0, None, True, False),
        "bilateral_plane_sigma": (0.0, None, True, False),
        "bilateral_normal_power": (0.0, None, False, False),
        "pixel_rays": (0, 1024, False, False),
        "pixel_filter": (0, 6, False, False),
        "pixel_full_res": frozenset((False, True)),
        "reflection_rays": (0, 256, False, False),
        "ssao_auto": frozenset((False, True)),
    }

    def __post_init__(self) -> None:
        check_ranges(self, self.RANGES, "raster settings")

    def with_(self, **changes) -> RasterSettings:
        return replace(self, **changes)

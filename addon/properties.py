"""HybridGI's scene settings (`scene.hybridgi`) and their conversion to the core's frozen settings."""

# No `from __future__ import annotations` here: bpy reads the property annotations at registration
# and needs them evaluated.

import math

import bpy
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty, PointerProperty

from hybridgi_core import settings as core_settings
from hybridgi_core.raster import settings as raster
from hybridgi_core.snapshot import NO_WORLD_AO_DISTANCE

SH_ORDER_ITEMS = (
    ("L1", "L1", "4 spherical-harmonic coefficients per colour channel: cheaper, broad light reads ~5% low", 1),
    ("L2", "L2", "9 coefficients per colour channel: removes the L1 bias", 2),
)
SH_ORDER = {"L1": 1, "L2": 2}

INDIRECT_QUALITY_ITEMS = (
    ("AO", "Ambient Occlusion", "Probe rays measure occlusion only; no bounce light", 0),
    ("ONE_BOUNCE", "One Bounce", "Probe-ray hits are lit by lamps, emission and the sky", 1),
    ("MULTI_BOUNCE", "Multi Bounce", "Hits also read the cache itself and converge to all bounces over updates", 2),
)
INDIRECT_QUALITY = {
    "AO": core_settings.AO_ONLY,
    "ONE_BOUNCE": core_settings.ONE_BOUNCE,
    "MULTI_BOUNCE": core_settings.MULTI_BOUNCE,
}

BLEND_MODE_ITEMS = (
    ("MUL", "Multiply", "The product of both: stronger contact shadows", 0),
    ("MIN", "Minimum", "The darker of ray-traced and screen-space occlusion: no double darkening", 1),
)

# The numbers are the deferred pass's DEBUG_* constants (hybridgi_core/raster/settings.py);
# CELLS is drawn by the pipeline itself.
DEBUG_VIEW_ITEMS = (
    ("FINAL", "Final", "The shaded image", 0),
    ("INDIRECT", "Indirect Light", "Albedo times the indirect light gathered from the cache", 1),
    ("AO", "Ambient Occlusion", "Ray-traced and screen-space occlusion after blending", 2),
    ("AO_SPLIT", "AO Split", "Ray-traced occlusion on the left half, screen-space occlusion on the right", 3),
    ("CELLS", "Cache Cells", "Each pixel coloured by the cache cell it reads", 4),
)
DEBUG_VIEW = {identifier: number for identifier, _name, _description, number in DEBUG_VIEW_ITEMS}

# How final renders of an animation treat the cache between frames (addon/pipeline.py).
ANIMATION_MODE_ITEMS = (
    ("INDEPENDENT", "Independent", "Every frame converges a fresh cache with the same deterministic warm-up: "
     "frame N renders identically whatever was rendered before (render farms may split the animation)", 0),
    ("INCREMENTAL", "Incremental", "Successive frames keep one cache: what moved, deformed or changed is re-traced "
     "and the cells near it refresh quickly, then one update of the visible cells instead of a full warm-up. "
     "Faster and temporally smooth; a frame depends on the frames rendered before it in the job", 1),
)



def cycles_diffuse_bounces(scene) -> int | None:
    """The diffuse bounces Cycles would render for this scene (min of its Max Bounces and Diffuse
    bounces), None without Cycles' settings."""
    cycles = getattr(scene, "cycles", None)
    if cycles is None or not hasattr(cycles, "diffuse_bounces"):
        return None
    return max(min(int(cycles.max_bounces), int(cycles.diffuse_bounces)), 0)


def cycles_filter_glossy(scene) -> float:
    """Cycles' Filter Glossy of this scene (`blur_glossy`; its default 1.0 without Cycles' settings)."""
    value = getattr(getattr(scene, "cycles", None), "blur_glossy", 1.0)
    try:
        value = float(value)
    except (TypeError, ValueError):
        return 1.0
    return value if math.isfinite(value) and value >= 0.0 else 1.0


def bounce_limited_quality(scene) -> int:
    """The highest Indirect Quality Cycles' diffuse bounce limit allows: One Bounce for 1 (and
    for 0, whose hits then reflect nothing: `CacheSettings.bounce_light`, so the sky and emitters
    still light directly, as in Cycles' Diffuse Direct), every bounce for more."""
    bounces = cycles_diffuse_bounces(scene)
    if bounces is None or bounces >= 2:
        return core_settings.MULTI_BOUNCE
    return core_settings.ONE_BOUNCE

class HybridGISettings(bpy.types.PropertyGroup):
    """Render settings of the HybridGI engine, stored per scene."""

    # Irradiance cache (step 4-5 of the paper).
    resolution: IntProperty(
        name="Resolution",
        description="Cache cells along the longest axis of the scene's bounding box",
        default=48, min=1, max=512, soft_min=4, soft_max=128,
    )
    cache_levels: IntProperty(
        name="Cache Levels",
        description="Camera-centred cache levels for final renders with Pixel Rays: each level above 1 adds a "
        "grid of half the cell size over the geometry nearest the camera (fitted to what the camera sees, "
        "in whole cells of the coarser level: the same on every machine), finer where detail is seen. "
        "1 = the one grid over the scene",
        default=1, min=1, max=3,
    )
    sh_order: EnumProperty(
        name="SH Order",
        description="Spherical-harmonic order of the radiance stored per cell",
        items=SH_ORDER_ITEMS, default="L2",
    )
    rays_per_cell: IntProperty(
        name="Rays per Cell",
        description="Probe rays traced from each visible cell per cache update",
        default=64, min=1, max=65536, soft_max=1024,
    )
    ray_length: FloatProperty(
        name="Ray Length",
        description="Longest probe ray; 0 traces across the whole scene",
        default=0.0, min=0.0, soft_max=100.0, subtype="DISTANCE", unit="LENGTH",
    )
    hysteresis: FloatProperty(
        name="Hysteresis",
        description="Share of the previous cache value each update keeps: higher is smoother but reacts slower",
        default=0.9, min=0.0, max=0.99, subtype="FACTOR",
    )
    warmup_iterations: IntProperty(
        name="Warm-up Updates",
        description="Convergence of the cache before each final-render frame, in updates: every 8 trace "
        "one batch of probe rays per cell, kept and re-shaded; all bounces are then solved over the "
        "stored hits without further rays (8 = 1 batch; with Pixel Rays the cache only carries further bounces "
        "and the control variate, and 16 = 2 batches gained less than 16 more pixel rays)",
        default=8, min=0, max=1024, soft_max=64,
    )

    # What a probe ray's hit contributes.
    indirect_quality: EnumProperty(
        name="Indirect Quality",
        description="How much light transport the probe rays compute",
        items=INDIRECT_QUALITY_ITEMS, default="MULTI_BOUNCE",
    )
    light_samples: IntProperty(
        name="Light Samples",
        description="Shadow rays per area light and sun at each probe-ray hit",
        default=1, min=1, max=256, soft_max=16,
    )
    lod_ratio: FloatProperty(
        name="Ray Mesh Detail",
        description="Share of triangles kept in the simplified mesh the probe rays trace",
        default=1.0, min=0.01, max=1.0, subtype="FACTOR",
    )
    seed: IntProperty(
        name="Seed",
        description="Seed of the probe-ray directions; frame f rotates them with seed + f",
        default=0, min=0,
    )

    # Screen-space passes (steps 2, 7 and 8).
    downsample: IntProperty(
        name="Downsample",
        description="Resolution divisor of the G-buffer used to find visible cells and for screen-space AO "
        "(2: atrium error vs Cycles 0.107, 4: 0.121, at the same render time)",
        default=2, min=1, max=16,
    )
    ssao_radius: FloatProperty(
        name="Radius",
        description="World-space radius of screen-space ambient occlusion and near-field colour bleeding; "
        "0 = one cache cell (the detail the cache cannot resolve)",
        default=0.0, min=0.0, soft_max=5.0, subtype="DISTANCE", unit="LENGTH",
    )
    ssao_strength: FloatProperty(
        name="Strength",
        description="How strongly screen-space occlusion darkens indirect light",
        default=1.0, min=0.0, max=4.0, soft_max=1.0, subtype="FACTOR",
    )
    blend_mode: EnumProperty(
        name="Blend",
        description="How ray-traced and screen-space occlusion combine",
        items=BLEND_MODE_ITEMS, default="MIN",
    )
    pixel_rays: IntProperty(
        name="Pixel Rays",
        description="Final-gather rays of each GI pixel: sky, emitters, the first bounce and AO get the pixel's "
        "own visibility (contacts, thin geometry), further bounces read the cache at the hits; replaces the "
        "screen-space pass (final renders; the viewport keeps the cache gather). 0 = off: the cache gather alone "
        "(32 with 8 warm-up updates, against 0 with 16: Cornell box Combined error vs Cycles 0.031 -> 0.029 in "
        "27% less GI CPU time, car 0.010 -> 0.006; the residual's noise is most of the image's error: 48 "
        "against 32, Cornell 0.0217 -> 0.0205, car 0.0034 -> 0.0033)",
        default=48, min=0, max=1024, soft_max=64,
    )
    pixel_filter: IntProperty(
        name="Pixel Filter",
        description="Edge-aware a-trous passes over the pixel rays' correction of the cache (taps 1, 2, 4 ... "
        "GI pixels apart): more removes more noise, fewer keeps contacts sharper",
        default=3, min=0, max=6,
    )

    pixel_full_res: BoolProperty(
        name="Full-Res GI",
        description="With Pixel Rays and Downsample above 1: resolve the GI at every full-resolution pixel (the "
        "cache's light at the pixel's own normal, own rays on thin geometry and where the correction changes "
        "within a GI pixel) instead of upsampling the GI resolution's light (Diffuse Indirect error vs Cycles at "
        "320x240: car 0.123 -> 0.081, yard 0.172 -> 0.139)",
        default=True,
    )

    reflection_rays: IntProperty(
        name="Reflection Rays",
        description="Rays per pixel that a glossy surface (every roughness: polished floors, metals, lacquer, "
        "the default Principled BSDF's specular, rough plastics) reflects, "
        "shaded at their hits, so it mirrors the room rather than its average colour (final renders). "
        "0 = the cache's mean light for every glossy surface",
        default=8, min=0, max=256, soft_max=16,
    )

    # Film (final renders).
    pixel_samples: IntProperty(
        name="Pixel Samples",
        description="Jittered subframes per final-render pixel, placed by Cycles' pixel filter (its type "
        "and width, Blackman-Harris 1.5 px by default, sampled as Cycles samples it) and averaged: anti-aliased edges and textures in every "
        "pass. The cache is converged once per frame; the direct light's shadow rays are split over the "
        "subframes. 1 = one sample at each pixel centre. Every pass but Depth is then filtered over the "
        "neighbouring pixels by the same filter (their footprint's share, a K-th of it for K subframes)",
        default=8, min=1, max=64, soft_max=16,
    )

    shadow_samples: IntProperty(
        name="Shadow Samples",
        description="Shadow rays per final-render pixel and soft lamp (area lamps, lamps with a radius) where "
        "a penumbra crosses the pixel; elsewhere 8 rays find the penumbrae (a pixel the lamp lights wholly "
        "is exact with them). Split over the Pixel Samples' subframes",
        default=48, min=1, max=1024, soft_max=128,
    )

    glossy_samples: IntProperty(
        name="Glossy Samples",
        description="Lamp samples per final-render pixel and lamp of the glossy lobes (shadow rays included) "
        "where a first 4 find the highlight noisy; elsewhere those 4 are kept. Lobes of roughness 0.45 and above "
        "are filtered over their surface afterwards. Area lamps on lobes of roughness 0.25 and above take no "
        "samples: their light is exact, shadowed as the diffuse light is. Lamps much larger than a smooth lobe "
        "are left to the Reflection Rays",
        default=32, min=1, max=256, soft_max=64,
    )

    # Debugging.
    debug_view: EnumProperty(
        name="View",
        description="Intermediate result to show instead of the final image",
        items=DEBUG_VIEW_ITEMS, default="FINAL",
    )
    use_gi_overlay: BoolProperty(
        name="GI Overlay",
        description="Multiply HybridGI's bounce light and contact shadows into Solid and Material Preview shading",
        default=False,
    )
    use_viewport_overlay: BoolProperty(
        name="Cells Overlay",
        description="Draw the irradiance cache's cells in the 3D viewport",
        default=False,
    )

    # Animation (final renders).
    animation_mode: EnumProperty(
        name="Animation",
        description="How final renders of successive frames use the cache",
        items=ANIMATION_MODE_ITEMS, default="INDEPENDENT",
        # Switching to Independent frees the cache an incremental render job kept for this scene.
        update=lambda self, _context: _drop_render_job(self),
    )

    def cache_settings(self, scene=None):
        """The core's `CacheSettings` for these properties.

        The AO distance is the World's (Cycles reads the same setting; without a World, Cycles'
        10 m, `snapshot.NO_WORLD_AO_DISTANCE`), threads follow the
        scene's render threads. Raises `SettingsError` if a value is out of the core's range.
        """
        scene = scene if scene is not None else self.id_data
        world = scene.world
        ao_distance = world.light_settings.distance if world is not None else NO_WORLD_AO_DISTANCE
        return core_settings.CacheSettings(
            resolution=self.resolution,
            sh_order=SH_ORDER[self.sh_order],
            rays_per_cell=self.rays_per_cell,
            ray_length=_f(self.ray_length),
            hysteresis=_f(self.hysteresis),
            indirect_quality=min(INDIRECT_QUALITY[self.indirect_quality], bounce_limited_quality(scene)),
            bounce_light=cycles_diffuse_bounces(scene) != 0,
            filter_glossy=cycles_filter_glossy(scene),
            # The World allows 0; the core needs a positive distance.
            ao_distance=max(_f(ao_distance), 1e-4),
            lod_ratio=_f(self.lod_ratio),
            light_samples=self.light_samples,
            seed=self.seed,
            threads=min(max(scene.render.threads, 1), 64),
            cache_levels=self.cache_levels,
        )

    def raster_settings(self, cell_size=None):
        """The raster passes' `RasterSettings` for these properties (SettingsError if out of range).

        cell_size : metres of one cache cell, the automatic SSAO radius (radius 0); 0.5 m if unknown.
        """
        radius = _f(self.ssao_radius) or (cell_size if cell_size else 0.5)
        return raster.RasterSettings(
            downsample=self.downsample,
            ssao_radius=radius,
            ssao_strength=_f(self.ssao_strength),
            ao_blend=self.blend_mode,
            pixel_rays=self.pixel_rays,
            pixel_filter=self.pixel_filter,
            pixel_full_res=bool(self.pixel_full_res),
            reflection_rays=self.reflection_rays,
            ssao_auto=not _f(self.ssao_radius),
        )


def _drop_render_job(props):
    if props.animation_mode != "INCREMENTAL":
        from . import animation  # noqa: PLC0415  (imports bpy handlers; only needed on a switch)

        scene = props.id_data
        for layer in scene.view_layers:
            animation.unregister_session(animation.render_job_key(scene.name_full, layer.name))


def _f(value):
    """A float property's single-precision value as the decimal the user typed (0.9, not 0.8999999761)."""
    return float(f"{value:.7g}")


classes = (HybridGISettings,)


def register():
    for cls in classes:
        bpy.utils.register_class(cls)
    bpy.types.Scene.hybridgi = PointerProperty(type=HybridGISettings, name="HybridGI Settings")


def unregister():
    del bpy.types.Scene.hybridgi
    for cls in reversed(classes):
        bpy.utils.unregister_class(cls)

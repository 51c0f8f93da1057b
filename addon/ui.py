"""Properties-editor panels of the HybridGI engine, the built-in panels it shares, and the 3D View
sidebar tab of the live viewport GI."""

import sys

import bpy
from bpy.types import Panel

ENGINE = "HYBRIDGI"


def settings_column(layout, data, names):
    """A split-layout column of `data`'s properties; `names` holds property names, or (name,
    keyword arguments of `prop`) pairs. Panels are the lists they show."""
    layout.use_property_split = True
    layout.use_property_decorate = False
    col = layout.column()
    for item in names:
        name, options = (item, {}) if isinstance(item, str) else item
        col.prop(data, name, **options)
    return col


class HybridGIButtonsPanel:
    bl_space_type = "PROPERTIES"
    bl_region_type = "WINDOW"
    bl_context = "render"
    COMPAT_ENGINES = {ENGINE}

    @classmethod
    def poll(cls, context):
        return context.engine in cls.COMPAT_ENGINES


class HYBRIDGI_PT_cache(HybridGIButtonsPanel, Panel):
    bl_label = "Irradiance Cache"

    def draw(self, context):
        col = settings_column(self.layout, context.scene.hybridgi, (
            "resolution", "cache_levels", ("sh_order", {"expand": True}), "rays_per_cell", "ray_length",
            "hysteresis", "warmup_iterations", "animation_mode"))
        world = context.scene.world
        if world is not None:
            # The AO distance belongs to the World (Cycles reads it there too); shown here
            # because this engine has no World settings panel of its own.
            col.prop(world.light_settings, "distance", text="AO Distance")


class HYBRIDGI_PT_indirect(HybridGIButtonsPanel, Panel):
    bl_label = "Probe Rays"
    bl_parent_id = "HYBRIDGI_PT_cache"

    def draw(self, context):
        settings_column(self.layout, context.scene.hybridgi, ("indirect_quality", "light_samples", "lod_ratio", "seed"))


class HYBRIDGI_PT_screen_space(HybridGIButtonsPanel, Panel):
    bl_label = "Screen Space"

    def draw(self, context):
        settings_column(self.layout, context.scene.hybridgi, (
            "downsample", "pixel_rays", "pixel_filter", "pixel_full_res", "reflection_rays", "ssao_radius",
            "ssao_strength", ("blend_mode", {"expand": True})))


class HYBRIDGI_PT_film(HybridGIButtonsPanel, Panel):
    """Final renders' pixel filter: the subframes, and Cycles' filter (the one they integrate)."""

    bl_label = "Film"

    def draw(self, context):
        col = settings_column(self.layout, context.scene.hybridgi, ("pixel_samples", "shadow_samples", "glossy_samples"))
        cycles = getattr(context.scene, "cycles", None)
        if cycles is not None and hasattr(cycles, "filter_width"):
            col.prop(cycles, "pixel_filter_type", text="Filter")
            if cycles.pixel_filter_type != "BOX":
                col.prop(cycles, "filter_width", text="Width")
        else:
            col.prop(context.scene.render, "filter_size")


class HYBRIDGI_PT_debug(HybridGIButtonsPanel, Panel):
    bl_label = "Debug"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        settings_column(self.layout, context.scene.hybridgi, ("debug_view", "use_viewport_overlay", "use_gi_overlay"))


class HYBRIDGI_PT_passes(HybridGIButtonsPanel, Panel):
    """The passes this engine writes: exactly the view-layer flags `engine.PASSES` reads."""

    bl_label = "Passes"
    bl_context = "view_layer"

    def draw(self, context):
        layout = self.layout
        layout.use_property_split = True
        layout.use_property_decorate = False
        view_layer = context.view_layer

        col = layout.column(heading="Data", align=True)
        col.prop(view_layer, "use_pass_combined")
        col.prop(view_layer, "use_pass_z")
        col.prop(view_layer, "use_pass_normal")

        col = layout.column(heading="Diffuse", align=True)
        col.prop(view_layer, "use_pass_diffuse_direct", text="Direct")
        col.prop(view_layer, "use_pass_diffuse_indirect", text="Indirect")
        col.prop(view_layer, "use_pass_diffuse_color", text="Color")

        col = layout.column(heading="Other", align=True)
        col.prop(view_layer, "use_pass_ambient_occlusion", text="Ambient Occlusion")


class HybridGIViewPanel:
    """The 3D View sidebar tab: shown whatever the engine (the GI overlay works with any)."""

    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "HybridGI"


def _loaded(name):
    """An add-on module if something imported it already; panels never import the GI machinery."""
    return sys.modules.get(f"{__package__}.{name}")


class HYBRIDGI_PT_view3d(HybridGIViewPanel, Panel):
    bl_label = "HybridGI"

    def draw(self, context):
        layout = self.layout
        scene = context.scene
        props = scene.hybridgi
        col = layout.column(align=True)
        col.prop(scene.render, "engine", text="")
        shading = getattr(getattr(context.space_data, "shading", None), "type", None)
        if scene.render.engine == ENGINE and shading != "RENDERED":
            col.label(text="Rendered shading shows the live GI", icon="INFO")
        col.prop(props, "use_gi_overlay", text="GI Overlay (Solid, Material Preview)", toggle=True)


class HYBRIDGI_PT_view3d_settings(HybridGIViewPanel, Panel):
    bl_label = "Settings"
    bl_parent_id = "HYBRIDGI_PT_view3d"

    def draw(self, context):
        settings_column(self.layout, context.scene.hybridgi, (
            "resolution", "rays_per_cell", "hysteresis", ("indirect_quality", {"text": "Quality"}), "downsample",
            ("ssao_strength", {"text": "SSAO"})))


class HYBRIDGI_PT_view3d_stats(HybridGIViewPanel, Panel):
    """Live numbers of the last redraw of a view of this scene (read from a cache, never computed here)."""

    bl_label = "Statistics"
    bl_parent_id = "HYBRIDGI_PT_view3d"

    def draw(self, context):
        layout = self.layout
        viewport = _loaded("viewport")
        live = viewport.LIVE_STATS.get(context.scene.name) if viewport is not None else None
        if live is None:
            layout.label(text="No live view yet")
            return
        if live.error:
            layout.label(text=live.error, icon="ERROR")
        w, d = live.worker, live.draw
        col = layout.column(align=True)
        col.label(text=f"Converged: {w.converged:.0%} of {w.visible_cells:,} visible cells")
        col.label(text=f"GI updates: {w.updates_per_s:.0f}/s, {w.rays_per_s / 1e6:.2f} Mrays/s")
        col.label(text=f"Main thread: {d.cpu_ms:.1f} ms CPU + {d.gpu_ms:.1f} ms GPU")
        box = layout.box().column(align=True)
        box.label(text="Main thread (ms)")
        for name, ms in d.steps_ms.items():
            box.label(text=f"{name}: {ms:.2f}")
        box = layout.box().column(align=True)
        box.label(text="Worker (ms, last run)")
        for name, ms in w.steps_ms.items():
            box.label(text=f"{name}: {ms:.2f}")


class HYBRIDGI_PT_view3d_debug(HybridGIViewPanel, Panel):
    bl_label = "Debug"
    bl_parent_id = "HYBRIDGI_PT_view3d"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        settings_column(self.layout, context.scene.hybridgi, ("debug_view", "use_viewport_overlay"))


#: Properties-editor panels: shown for this engine only.
classes = (
    HYBRIDGI_PT_cache,
    HYBRIDGI_PT_indirect,
    HYBRIDGI_PT_screen_space,
    HYBRIDGI_PT_film,
    HYBRIDGI_PT_debug,
    HYBRIDGI_PT_passes,
)

#: The 3D View sidebar tab: shown whatever the engine.
view3d_classes = (
    HYBRIDGI_PT_view3d,
    HYBRIDGI_PT_view3d_settings,
    HYBRIDGI_PT_view3d_stats,
    HYBRIDGI_PT_view3d_debug,
)

# Built-in panels that serve any engine ('BLENDER_RENDER' in their COMPAT_ENGINES) but that this
# engine replaces or cannot use.
EXCLUDED_PANELS = {
    "DATA_PT_light",  # DATA_PT_EEVEE_light below shows every setting the sync reads
    "NODE_DATA_PT_light",
    "DATA_PT_lightprobe",  # light probes are EEVEE's baked GI; the cache replaces them
    "DATA_PT_lightprobe_display",
    "DATA_PT_lightprobe_parallax",
    "DATA_PT_lightprobe_visibility",
    "DATA_PT_context_lightprobe",
    "DATA_PT_preview",  # no preview renders
}

# EEVEE panels that edit exactly what the sync reads (light units, shader nodes, world surface).
EXTRA_PANELS = (
    "DATA_PT_EEVEE_light",
    "NODE_DATA_PT_EEVEE_light",
    "EEVEE_MATERIAL_PT_context_material",
    "EEVEE_MATERIAL_PT_surface",
    "EEVEE_WORLD_PT_surface",
)


def builtin_panels():
    """Built-in panel classes to share with this engine."""
    panels = [
        panel
        for panel in bpy.types.Panel.__subclasses__()
        if "BLENDER_RENDER" in getattr(panel, "COMPAT_ENGINES", ()) and panel.__name__ not in EXCLUDED_PANELS
    ]
    panels.extend(getattr(bpy.types, name) for name in EXTRA_PANELS if hasattr(bpy.types, name))
    return panels


def register():
    for cls in classes + view3d_classes:
        bpy.utils.register_class(cls)
    for panel in builtin_panels():
        panel.COMPAT_ENGINES.add(ENGINE)


def unregister():
    for panel in builtin_panels():
        panel.COMPAT_ENGINES.discard(ENGINE)
    for cls in reversed(classes + view3d_classes):
        bpy.utils.unregister_class(cls)

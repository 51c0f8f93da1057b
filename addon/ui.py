"""Properties-editor panels of the HybridGI engine, and the built-in panels it shares."""

import bpy
from bpy.types import Panel

ENGINE = "HYBRIDGI"


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
        layout = self.layout
        layout.use_property_split = True
        layout.use_property_decorate = False
        props = context.scene.hybridgi

        col = layout.column()
        col.prop(props, "resolution")
        col.prop(props, "sh_order", expand=True)
        col.prop(props, "rays_per_cell")
        col.prop(props, "ray_length")
        col.prop(props, "hysteresis")
        col.prop(props, "warmup_iterations")
        col.prop(props, "animation_mode")
        world = context.scene.world
        if world is not None:
            # The AO distance belongs to the World (Cycles reads it there too); shown here
            # because this engine has no World settings panel of its own.
            col.prop(world.light_settings, "distance", text="AO Distance")


class HYBRIDGI_PT_indirect(HybridGIButtonsPanel, Panel):
    bl_label = "Probe Rays"
    bl_parent_id = "HYBRIDGI_PT_cache"

    def draw(self, context):
        layout = self.layout
        layout.use_property_split = True
        layout.use_property_decorate = False
        props = context.scene.hybridgi

        col = layout.column()
        col.prop(props, "indirect_quality")
        col.prop(props, "light_samples")
        col.prop(props, "lod_ratio")
        col.prop(props, "seed")


class HYBRIDGI_PT_screen_space(HybridGIButtonsPanel, Panel):
    bl_label = "Screen Space"

    def draw(self, context):
        layout = self.layout
        layout.use_property_split = True
        layout.use_property_decorate = False
        props = context.scene.hybridgi

        col = layout.column()
        col.prop(props, "downsample")
        col.prop(props, "ssao_radius")
        col.prop(props, "ssao_strength")
        col.prop(props, "blend_mode", expand=True)


class HYBRIDGI_PT_debug(HybridGIButtonsPanel, Panel):
    bl_label = "Debug"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        layout = self.layout
        layout.use_property_split = True
        layout.use_property_decorate = False
        props = context.scene.hybridgi

        col = layout.column()
        col.prop(props, "debug_view")
        col.prop(props, "use_viewport_overlay")


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


classes = (
    HYBRIDGI_PT_cache,
    HYBRIDGI_PT_indirect,
    HYBRIDGI_PT_screen_space,
    HYBRIDGI_PT_debug,
    HYBRIDGI_PT_passes,
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
    for cls in classes:
        bpy.utils.register_class(cls)
    for panel in builtin_panels():
        panel.COMPAT_ENGINES.add(ENGINE)


def unregister():
    for panel in builtin_panels():
        panel.COMPAT_ENGINES.discard(ENGINE)
    for cls in reversed(classes):
        bpy.utils.unregister_class(cls)

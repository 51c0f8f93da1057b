"""HybridGI's GI on top of Solid and Material Preview shading: a 3D View draw handler that runs a
`viewport.ViewportSession` for the view and multiplies its indirect light into what Blender drew.

The factor per pixel (`overlay_frag.glsl`): screen-space AO, times the colour of the bounce light
(unit luminance) weighted by the share of indirect light in the pixel's total, so contact shadows
and colour bleeding show while Blender's own shading keeps its brightness. The view's pixels are
display-encoded there, so the factor is encoded the same way (a power of 1/2.2).

Blender drives it through a draw handler (drawing), a depsgraph handler (edits) and a timer (redraws
while the worker converges); none of those run in the bpy module, so tests call `draw_overlay`
and `on_depsgraph_update` directly. On/off: `scene.hybridgi.use_gi_overlay` (the panel's toggle, or
the `HYBRIDGI_OT_gi_overlay` operator for keymaps).

The same handler draws the cache's cells (`scene.hybridgi.use_viewport_overlay`, any shading): a
point at each valid cell's centre, coloured by the radiance it holds, from the cache the last
live view of the scene (engine or overlay) drew.
"""

import logging
import sys

import bpy
import numpy as np
from bpy.app.handlers import persistent

from hybridgi_core import errors
from hybridgi_core.raster import passes as _passes

from . import compat
from .viewport_passes import load_addon_glsl

log = logging.getLogger(__name__)


#: Shading types the overlay draws over (Rendered shading of HYBRIDGI has the GI already).
SHADING_TYPES = frozenset({"SOLID", "MATERIAL"})
#: How strongly the bounce light's colour tints the view (0..1) and the AO darkens it.
BLEED_STRENGTH = 1.0
AO_STRENGTH = 1.0
#: Screen size of a cell's point in the cells overlay, pixels.
CELL_POINT_SIZE = 6.0
#: Seconds between the timer's checks while a session converges, and while all are idle.
POLL_BUSY_S = 0.05
POLL_IDLE_S = 0.5

#: Scene name -> the overlay's ViewportSession for that scene.
_sessions: dict = {}
_draw_handle = None


def is_enabled(scene) -> bool:
    props = getattr(scene, "hybridgi", None)
    return bool(props is not None and props.use_gi_overlay)


def set_enabled(scene, enabled: bool) -> None:
    scene.hybridgi.use_gi_overlay = enabled
    if not enabled:
        close_session(scene.name)


def _viewport():
    """The viewport module, imported on first use: it pulls in embreex through the worker, which
    registering the add-on must not need (as `engine._pipeline`)."""
    from . import viewport  # noqa: PLC0415

    return viewport


def session_for(scene):
    return _sessions.get(scene.name)


def close_session(scene_name: str) -> None:
    session = _sessions.pop(scene_name, None)
    if session is not None:
        session.close()


def close_all() -> None:
    for name in list(_sessions):
        close_session(name)


# --- drawing -------------------------------------------------------------------------------------



_shader_cache: dict = {}


def _overlay_shader():
    shader = _shader_cache.get("overlay")
    if shader is None:
        spec = _passes.fullscreen_spec(
            "hybridgi_gi_overlay",
            load_addon_glsl("overlay_frag.glsl"),
            samplers=((0, "FLOAT_2D", "position_tx"), (1, "FLOAT_2D", "indirect_tx"), (2, "FLOAT_2D", "direct_tx"),
                      (3, "FLOAT_2D", "ssao_tx")),
            push=(("VEC4", "screen_size"), ("VEC4", "strength")),
            outputs=((0, "VEC4", "out_factor"),),
        )
        shader = _shader_cache["overlay"] = (_passes.compile_spec(spec), _passes.fullscreen_batch())
    return shader


def draw_overlay(context) -> bool:
    """Draw the GI overlay into the bound framebuffer for `context` (region, region_data, scene,
    evaluated_depsgraph_get; space_data optional). Returns whether it drew."""
    import gpu  # noqa: PLC0415

    scene = context.scene
    if not is_enabled(scene):
        return False
    space = getattr(context, "space_data", None)
    shading = getattr(getattr(space, "shading", None), "type", None)
    if shading is not None and shading not in SHADING_TYPES:
        return False
    session = _sessions.get(scene.name)
    if session is None or session.worker is None or not session.worker.alive:
        close_session(scene.name)
        session = _sessions[scene.name] = _viewport().ViewportSession(antialias=False)
        session.sync(context.evaluated_depsgraph_get(), scene)
    region = context.region
    camera = _viewport().ViewCamera.from_region_data(context.region_data)
    session.poll_world(context.evaluated_depsgraph_get())
    try:
        texture = session.draw(scene, camera, region.width, region.height)
    except errors.HybridGIError as err:
        log.error("HybridGI overlay: %s", err)
        return False
    if texture is None:
        return False
    pipeline = session.gpu.pipeline
    shaded = pipeline.deferred.outputs()
    shader, batch = _overlay_shader()
    shader.uniform_sampler("position_tx", pipeline.gbuffer.outputs().position)
    shader.uniform_sampler("indirect_tx", shaded.diffuse_indirect)
    shader.uniform_sampler("direct_tx", shaded.diffuse_direct)
    shader.uniform_sampler("ssao_tx", pipeline.ssao.output)
    shader.uniform_float("screen_size", (float(region.width), float(region.height), 0.0, 0.0))
    shader.uniform_float("strength", (BLEED_STRENGTH, AO_STRENGTH, 0.0, 0.0))
    old = (gpu.state.blend_get(), gpu.state.depth_test_get(), gpu.state.depth_mask_get())
    gpu.state.blend_set("MULTIPLY")
    gpu.state.depth_test_set("NONE")
    gpu.state.depth_mask_set(False)
    try:
        batch.draw(shader)
    finally:
        gpu.state.blend_set(old[0])
        gpu.state.depth_test_set(old[1])
        gpu.state.depth_mask_set(old[2])
    return True


_cell_batches: dict = {}


def cell_points(frame) -> tuple:
    """(centres (n, 3), colours (n, 4)) float32 of the valid cells of a `worker.CacheFrame`: the
    radiance the cell holds (DC terms of both bands, Reinhard-mapped for display)."""
    k = frame.settings.sh_coeffs
    n = frame.grid.count
    texels = frame.sh_texels.reshape(-1, 4)[: n * 2 * k].reshape(n, 2 * k, 4)
    valid = texels[:, k, 3] > 0.5
    dc = 0.28209479  # Y00
    radiance = (texels[valid, 0, :3] + texels[valid, k, :3]) * dc
    colour = np.ones((radiance.shape[0], 4), np.float32)
    colour[:, :3] = radiance / (1.0 + radiance)
    return frame.grid.centers()[valid].astype(np.float32), colour


def draw_cells(scene) -> bool:
    """Draw the cells overlay for `scene` (POST_VIEW: world-space points). Returns whether it drew."""
    import gpu  # noqa: PLC0415
    from gpu_extras.batch import batch_for_shader  # noqa: PLC0415

    if not getattr(getattr(scene, "hybridgi", None), "use_viewport_overlay", False):
        return False
    module = sys.modules.get(f"{__package__}.viewport")
    frame = module.drawn_cache(scene.name) if module is not None else None
    if frame is None:
        return False
    shader = compat.point_color_shader()
    cached = _cell_batches.get(scene.name)
    if cached is None or cached[0] is not frame:
        centres, colours = cell_points(frame)
        cached = _cell_batches[scene.name] = (frame, batch_for_shader(shader, "POINTS", {"pos": centres, "color": colours}))
    depth_test = gpu.state.depth_test_get()
    gpu.state.depth_test_set("NONE")  # every cell shows (Blender 4.2 leaves a depth test on here)
    gpu.state.point_size_set(CELL_POINT_SIZE)
    cached[1].draw(shader)
    gpu.state.point_size_set(1.0)
    gpu.state.depth_test_set(depth_test)
    return True


def _draw_callback() -> None:
    context = bpy.context
    draw_overlay(context)
    draw_cells(context.scene)


# --- Blender's handlers ---------------------------------------------------------------------------


@persistent
def on_depsgraph_update(scene, depsgraph) -> None:
    """Edits reach the overlay's session of that scene (depsgraph_update_post)."""
    session = _sessions.get(scene.name)
    if session is not None and session.worker is not None:
        session.sync(depsgraph, scene)


@persistent
def on_load(*_args) -> None:
    """A new file: the sessions belong to the old one's scenes."""
    close_all()
    _cell_batches.clear()


def _poll() -> float:
    """Timer: redraw the 3D views (sidebar stats included) while a session converges; close
    overlay sessions that were switched off."""
    busy = False
    for name, session in list(_sessions.items()):
        scene = bpy.data.scenes.get(name)
        if scene is None or not is_enabled(scene):
            close_session(name)
        elif session.needs_redraw():
            busy = True
    module = sys.modules.get(f"{__package__}.viewport")  # only once some view imported it
    if module is not None and module.any_busy():
        busy = True
    if busy:
        for window in bpy.context.window_manager.windows:
            for area in window.screen.areas:
                if area.type == "VIEW_3D":
                    area.tag_redraw()
    return POLL_BUSY_S if busy else POLL_IDLE_S


class HYBRIDGI_OT_gi_overlay(bpy.types.Operator):
    """Show HybridGI's indirect light over Solid and Material Preview shading"""

    bl_idname = "hybridgi.gi_overlay"
    bl_label = "GI Overlay"
    bl_options = {"REGISTER"}

    def execute(self, context):
        set_enabled(context.scene, not is_enabled(context.scene))
        for area in context.screen.areas if context.screen else ():
            if area.type == "VIEW_3D":
                area.tag_redraw()
        return {"FINISHED"}


classes = (HYBRIDGI_OT_gi_overlay,)


def register():
    global _draw_handle
    for cls in classes:
        bpy.utils.register_class(cls)
    _draw_handle = bpy.types.SpaceView3D.draw_handler_add(_draw_callback, (), "WINDOW", "POST_VIEW")
    bpy.app.handlers.depsgraph_update_post.append(on_depsgraph_update)
    bpy.app.handlers.load_pre.append(on_load)
    bpy.app.timers.register(_poll, first_interval=POLL_IDLE_S, persistent=True)


def unregister():
    global _draw_handle
    if bpy.app.timers.is_registered(_poll):
        bpy.app.timers.unregister(_poll)
    for handlers, fn in ((bpy.app.handlers.load_pre, on_load),
                         (bpy.app.handlers.depsgraph_update_post, on_depsgraph_update)):
        if fn in handlers:
            handlers.remove(fn)
    if _draw_handle is not None:
        bpy.types.SpaceView3D.draw_handler_remove(_draw_handle, "WINDOW")
        _draw_handle = None
    close_all()
    for cls in reversed(classes):
        bpy.utils.unregister_class(cls)


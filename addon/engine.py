"""The HYBRIDGI render engine: thin callbacks into `pipeline`, errors reported from one place."""

import logging

import bpy

from hybridgi_core import errors
from hybridgi_core.rendering import rendering

from . import compat

log = logging.getLogger(__name__)

#: Message of the last failed final render in this process; None after a successful one.
#: Blender prints and swallows exceptions raised in `render()` (the operator still returns
#: FINISHED), so headless callers such as the CLI read this to know a frame failed.
LAST_ERROR = None

#: Passes besides Combined, named like this Blender's Cycles names them (compat.pass_name) so the
#: EXRs of both engines compare layer by layer:
#: (pass name, channels, channel ids, type, the view-layer flag that enables it).
PASSES = tuple((compat.pass_name(name), *rest) for name, *rest in (
    ("Depth", 1, "Z", "VALUE", "use_pass_z"),
    ("Normal", 3, "XYZ", "VECTOR", "use_pass_normal"),
    ("Diffuse Direct", 3, "RGB", "COLOR", "use_pass_diffuse_direct"),
    ("Diffuse Indirect", 3, "RGB", "COLOR", "use_pass_diffuse_indirect"),
    ("Diffuse Color", 3, "RGB", "COLOR", "use_pass_diffuse_color"),
    ("Ambient Occlusion", 3, "RGB", "COLOR", "use_pass_ambient_occlusion"),
    ("Glossy Direct", 3, "RGB", "COLOR", "use_pass_glossy_direct"),
    ("Glossy Indirect", 3, "RGB", "COLOR", "use_pass_glossy_indirect"),
    ("Glossy Color", 3, "RGB", "COLOR", "use_pass_glossy_color"),
))


def enabled_passes(view_layer):
    """Names of the PASSES the view layer asks for (Combined is always there)."""
    return [name for name, _channels, _ids, _kind, flag in PASSES if getattr(view_layer, flag)]


class HybridGIRenderEngine(bpy.types.RenderEngine):
    bl_idname = "HYBRIDGI"
    bl_label = "HybridGI"
    bl_use_gpu_context = True  # the raster passes draw with the `gpu` module inside render()
    bl_use_shading_nodes_custom = False  # materials keep Blender's standard shader nodes
    bl_use_eevee_viewport = True  # Material Preview shading uses EEVEE
    bl_use_postprocess = True

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        #: Per-engine state the pipeline may keep between frames of one render job (the cache).
        self.session = None
        #: The live view of Rendered shading (`viewport.ViewportSession`), made by view_update.
        self.viewport = None

    def __del__(self):
        # The viewport's worker thread must stop with the engine (Blender frees the engine when
        # the viewport leaves Rendered shading).
        try:
            viewport = getattr(self, "viewport", None)
        except ReferenceError:
            return  # Blender freed the engine's RNA first (after a failed render): nothing of ours is left
        if viewport is not None:
            _viewport().free(self)

    def render(self, depsgraph):
        render_frame(self, depsgraph)

    def view_update(self, context, depsgraph):
        _viewport().view_update(self, context, depsgraph)

    def view_draw(self, context, depsgraph):
        _viewport().view_draw(self, context, depsgraph)

    def update_render_passes(self, scene=None, renderlayer=None):
        self.register_pass(scene, renderlayer, "Combined", 4, "RGBA", "COLOR")
        for name, channels, chan_ids, kind, flag in PASSES:
            if getattr(renderlayer, flag):
                self.register_pass(scene, renderlayer, name, channels, chan_ids, kind)


def render_frame(engine, depsgraph):
    """Render one frame through `pipeline.render_frame`; the one place render errors are reported."""
    global LAST_ERROR
    LAST_ERROR = None
    try:
        with rendering():  # freed arrays kept, a short GIL switch interval
            _pipeline().render_frame(engine, depsgraph)
    except errors.HybridGIError as err:
        _fail(engine, str(err))
    except Exception as err:
        # Blender would print this and carry on as if the frame had rendered: record it first so
        # the CLI and tests fail, then let Blender print the traceback.
        _fail(engine, f"internal error: {type(err).__name__}: {err}")
        raise


def _pipeline():
    """The pipeline module (imported by `register` already where it can be: `_preload`)."""
    from . import pipeline  # noqa: PLC0415

    return pipeline


def _viewport():
    """The viewport module (imported by `register` already where it can be: `_preload`)."""
    from . import viewport  # noqa: PLC0415

    return viewport


def _preload():
    """Import the pipeline and viewport modules when the add-on registers, as Cycles imports its
    engine module, not in the first render or draw: a process imports (and, where no bytecode is
    cached, compiles) them once, and that was inside the first render's seconds, 34-42 ms here
    (PYTHONDONTWRITEBYTECODE, as on CI; the CLI's development install is a fresh copy each run):
    a tenth of the car's 0.4 s final render, every frame of a one-frame headless job.
    Registration must not depend on them (embreex missing, a broken install): a failure is
    logged, and the first render imports them again and reports it."""
    for name, load in (("pipeline", _pipeline), ("viewport", _viewport)):
        try:
            load()
        except Exception as err:  # noqa: BLE001 - reported again, as an error, by the first render
            log.warning("HybridGI: the %s module did not import at registration: %s", name, err)


def _fail(engine, message):
    global LAST_ERROR
    LAST_ERROR = message
    log.error("HybridGI render failed: %s", message)
    engine.error_set(message)
    engine.report({"ERROR"}, message)


classes = (HybridGIRenderEngine,)


def register():
    for cls in classes:
        bpy.utils.register_class(cls)
    _preload()


def unregister():
    for cls in reversed(classes):
        bpy.utils.unregister_class(cls)

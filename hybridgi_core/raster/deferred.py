"""Step 9: deferred shading at full resolution, vertical bilateral taps fused in.

Inputs: the G-buffer, a full-res direct-irradiance texture from the CPU's shadow rays (RGBA,
rgb = W/m^2, `readback.upload_texture_2d`), and the horizontal pass's `FilteredGI` (cache indirect
+ ray AO, cache direct, SSAO bounce + AO). `deferred_frag.glsl` documents the formulas.

Outputs (full res, rows bottom-up), following Cycles' pass definitions:

| slot | name             | format  | content                                                   |
|------|------------------|---------|-----------------------------------------------------------|
| 0    | combined         | RGBA32F | albedo (E_dir + E_ind) / pi + glossy + emission; a = 1 geometry, background = world radiance, a = 0 |
| 1    | diffuse_direct   | RGBA32F | (E_lamps + E_cache_direct) / pi                            |
| 2    | diffuse_indirect | RGBA32F | E_indirect / pi                                            |
| 3    | diffuse_color    | RGBA32F | albedo                                                     |
| 4    | ao               | R32F    | blend(ray AO, screen AO); 0 on the background              |
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from .bilateral import BILATERAL_PUSH, FilteredGI, set_bilateral_uniforms
from .glsl import load_glsl
from .passes import RasterError, RasterPass, check_size, compile_spec, fullscreen_spec, low_res_size, make_target
from .readback import read_framebuffer, upload_texture_2d
from .settings import AO_BLEND_MODES, DEBUG_AO_SPLIT, DEBUG_FINAL, RasterSettings
from .world_background import WORLD_TYPEDEF

log = logging.getLogger(__name__)

DEFERRED_TARGETS = (
    ("combined", "RGBA32F", 4),
    ("diffuse_direct", "RGBA32F", 4),
    ("diffuse_indirect", "RGBA32F", 4),
    ("diffuse_color", "RGBA32F", 4),
    ("ao", "R32F", 1),
)


@dataclass
class ShadedFrame:
    """Deferred outputs (textures owned by the pass)."""

    combined: object
    diffuse_direct: object
    diffuse_indirect: object
    diffuse_color: object
    ao: object
    width: int
    height: int


class DeferredPass(RasterPass):
    """`resize(w, h)`; `execute(gbuffer, direct, filtered, world_color, ...) -> ShadedFrame`."""

    name = "deferred"

    def __init__(self, settings: RasterSettings | None = None) -> None:
        super().__init__()
        self.settings = settings or RasterSettings()
        self._targets = None
        self._fb = None
        self._blank = None  # (1x1 texture, zero WorldBlock) bound where the shader reads neither

    def _blanks(self):
        """(a 1x1 texture, a zero `WorldBlock`) for the glossy and world bindings of a draw
        without them (made on first use)."""
        import gpu  # noqa: PLC0415

        if self._blank is None:
            self._blank = (upload_texture_2d(np.zeros((1, 1, 4), np.float32), "RGBA16F"),
                           gpu.types.GPUUniformBuf(np.zeros(36, np.float32)))
        return self._blank

    def _build_shaders(self) -> dict:
        spec = fullscreen_spec(
            "hybridgi_deferred",
            load_glsl("common_lib.glsl", "bilateral_lib.glsl", "bilateral_vertical_lib.glsl",
                      "deferred_frag.glsl"),
            samplers=((0, "FLOAT_2D", "albedo_tx"), (1, "FLOAT_2D", "full_normal_tx"),
                      (2, "FLOAT_2D", "full_position_tx"), (3, "FLOAT_2D", "emission_tx"),
                      (4, "FLOAT_2D", "full_depth_tx"), (5, "FLOAT_2D", "direct_tx"),
                      (6, "FLOAT_2D", "h_indirect_tx"), (7, "FLOAT_2D", "h_direct_tx"),
                      (8, "FLOAT_2D", "h_ssao_tx"), (9, "FLOAT_2D", "glossy_tx"), (10, "FLOAT_2D", "world_tx")),
            push=BILATERAL_PUSH + (("VEC4", "world_color"), ("INT", "blend_mode"),
                                   ("INT", "debug_view"), ("INT", "relative_bounce"), ("INT", "has_glossy"),
                                   ("INT", "has_world_map")),
            typedefs=WORLD_TYPEDEF,
            ubos=((0, "WorldBlock", "world"),),
            outputs=tuple((slot, "FLOAT" if ch == 1 else "VEC4", f"out_{name}")
                          for slot, (name, _f, ch) in enumerate(DEFERRED_TARGETS)),
        )
        return {"main": compile_spec(spec)}

    def _allocate(self, width: int, height: int) -> None:
        import gpu  # noqa: PLC0415

        self._targets = {name: make_target(width, height, fmt) for name, fmt, _c in DEFERRED_TARGETS}
        self._fb = gpu.types.GPUFrameBuffer(
            color_slots=tuple(self._targets[name] for name, _f, _c in DEFERRED_TARGETS))

    def _release_targets(self) -> None:
        self._targets = None
        self._fb = None
        self._blank = None

    def execute(self, gbuffer, direct, filtered: FilteredGI, world_color=(0.0, 0.0, 0.0),
                blend_mode: str | None = None, debug_view: int = DEBUG_FINAL,
                relative_bounce: bool = False, glossy=None, world=None, camera=None) -> ShadedFrame:
        """Shade one frame.

        gbuffer : GBuffer of the resize size
        direct : full-res RGBA texture, rgb = lamp irradiance W/m^2 (CPU shadow rays)
        filtered : BilateralPass output for this G-buffer
        world_color : (3,) world background radiance (colour x strength)
        blend_mode : "MUL" | "MIN"; None = settings.ao_blend
        debug_view : settings.DEBUG_FINAL | DEBUG_INDIRECT | DEBUG_AO | DEBUG_AO_SPLIT (Combined only)
        relative_bounce : SSAOPass.relative_bounce of the frame (bounce without irradiance input)
        glossy : full-res RGBA texture, rgb = the lamps' glossy reflection (radiance, added to
            Combined; `glossy.glossy_direct`), or None
        world : `world_background.WorldTexture` whose map the background shows (instead of
            world_color), or None; camera : its (view, proj), the projection `gbuffer` was drawn
            with (a subframe's jittered one)
        """
        self._require()
        mode = blend_mode or self.settings.ao_blend
        if mode not in AO_BLEND_MODES:
            raise RasterError(f"unknown AO blend mode {mode!r}, expected one of {AO_BLEND_MODES}")
        if not DEBUG_FINAL <= int(debug_view) <= DEBUG_AO_SPLIT:
            raise RasterError(f"unknown debug view {debug_view!r}")
        check_size(gbuffer.position, self.width, self.height, "gbuffer")
        check_size(direct, self.width, self.height, "direct irradiance")
        check_size(filtered.indirect, self.width, low_res_size(self.width, self.height, filtered.factor)[1],
                   "filtered GI")
        wc = np.asarray(world_color, np.float32).reshape(3)
        shader = self._shader()
        shader.uniform_sampler("albedo_tx", gbuffer.albedo)
        shader.uniform_sampler("full_normal_tx", gbuffer.normal)
        shader.uniform_sampler("full_position_tx", gbuffer.position)
        shader.uniform_sampler("emission_tx", gbuffer.emission)
        shader.uniform_sampler("full_depth_tx", gbuffer.depth)
        shader.uniform_sampler("direct_tx", direct)
        shader.uniform_sampler("h_indirect_tx", filtered.indirect)
        shader.uniform_sampler("h_direct_tx", filtered.direct)
        shader.uniform_sampler("h_ssao_tx", filtered.ssao)
        if glossy is not None:
            check_size(glossy, self.width, self.height, "glossy radiance")
        shader.uniform_sampler("glossy_tx", glossy if glossy is not None else self._blanks()[0])
        shader.uniform_int("has_glossy", 1 if glossy is not None else 0)
        set_bilateral_uniforms(shader, self.settings, filtered.factor)
        shader.uniform_float("world_color", (*wc.tolist(), 1.0))
        mapped = world is not None and world.texture is not None and camera is not None
        blank_texture, blank_block = self._blanks() if not mapped else (None, None)
        shader.uniform_block("world", world.ubo(*camera) if mapped else blank_block)
        shader.uniform_sampler("world_tx", world.texture if mapped else blank_texture)
        shader.uniform_int("has_world_map", 1 if mapped else 0)
        shader.uniform_int("blend_mode", AO_BLEND_MODES.index(mode))
        shader.uniform_int("debug_view", int(debug_view))
        shader.uniform_int("relative_bounce", 1 if relative_bounce else 0)
        self._draw_fullscreen(self._fb, shader, (self.width, self.height))
        return self.outputs()

    def outputs(self) -> ShadedFrame:
        t = self._targets
        if t is None:
            raise RasterError("deferred: no targets (resize first)")
        return ShadedFrame(t["combined"], t["diffuse_direct"], t["diffuse_indirect"],
                           t["diffuse_color"], t["ao"], self.width, self.height)

    def read(self, name: str, out: np.ndarray | None = None) -> np.ndarray:
        """Output `name` as (h, w, c) float32 (c = 4, or 1 for ao), rows bottom-up."""
        for slot, (tname, _fmt, ch) in enumerate(DEFERRED_TARGETS):
            if tname == name:
                return read_framebuffer(self._fb, slot, self.width, self.height, ch, out=out)
        raise KeyError(name)


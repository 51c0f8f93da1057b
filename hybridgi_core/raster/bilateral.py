"""Step 8: cross-bilateral upsampling of the low-res GI, horizontal pass only.

The seed replaces two extra raster passes by ONE horizontal pass; the vertical taps run inside the
deferred pass (`bilateral_vertical` in `bilateral_vertical_lib.glsl`; `bilateral_lib.glsl` documents the
scheme):

    low-res GI (w_lo x h_lo) --horizontal taps, guides: full-res row centres--> W x h_lo
    W x h_lo --vertical taps inside deferred shading, guides: full-res G-buffer--> W x H

Inputs (low res, RGBA):
    gi_indirect : rgb = indirect irradiance from the cache (W/m^2), a = ray-traced AO
    gi_direct   : rgb = direct-from-cache irradiance (sky + emissive surfaces, W/m^2), a ignored
    ssao        : rgb = near-field bounce, a = screen-space AO (SSAOPass output)
Outputs (W_full x h_lo, RGBA16F), same layouts, except that the alpha of the filtered gi_direct
holds the tap confidence (share of the spatial weight that matched the guide's surface).

`BilateralVerticalPass` runs the vertical half on its own (tests, debug views); the pipeline uses
the copy fused into `DeferredPass`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from .glsl import load_glsl
from .passes import RasterError, RasterPass, check_size, compile_spec, fullscreen_spec, low_res_size, make_target
from .readback import read_framebuffer
from .settings import RasterSettings

log = logging.getLogger(__name__)

#: Push constants of bilateral_lib.glsl, shared by the horizontal, vertical and deferred passes.
BILATERAL_PUSH = (("INT", "factor"), ("INT", "radius"), ("FLOAT", "sigma"),
                  ("FLOAT", "plane_sigma"), ("FLOAT", "normal_power"))

_OUTPUTS = ((0, "VEC4", "out_indirect"), (1, "VEC4", "out_direct"), (2, "VEC4", "out_ssao"))


def set_bilateral_uniforms(shader, settings: RasterSettings, factor: int) -> None:
    """Set BILATERAL_PUSH on `shader` from `settings` (factor = downsample factor)."""
    shader.uniform_int("factor", int(factor))
    shader.uniform_int("radius", int(settings.bilateral_radius))
    shader.uniform_float("sigma", float(settings.bilateral_sigma))
    shader.uniform_float("plane_sigma", float(settings.bilateral_plane_sigma))
    shader.uniform_float("normal_power", float(settings.bilateral_normal_power))


@dataclass
class FilteredGI:
    """Horizontal-pass outputs (W_full x h_lo), inputs of the fused vertical taps."""

    indirect: object
    direct: object
    ssao: object
    width: int
    height: int
    factor: int


class BilateralPass(RasterPass):
    """Horizontal cross-bilateral pass.

    `resize(full_w, full_h)`; `execute(gbuffer, low, gi_indirect, gi_direct, ssao) -> FilteredGI`.
    """

    name = "bilateral"

    def __init__(self, settings: RasterSettings | None = None) -> None:
        super().__init__()
        self.settings = settings or RasterSettings()
        self.factor = self.settings.downsample
        self._targets = None
        self._fb = None
        self.low_width = self.low_height = 0

    def _build_shaders(self) -> dict:
        spec = fullscreen_spec(
            "hybridgi_bilateral_h",
            load_glsl("common_lib.glsl", "bilateral_lib.glsl", "bilateral_h_frag.glsl"),
            samplers=((0, "FLOAT_2D", "full_position_tx"), (1, "FLOAT_2D", "full_normal_tx"),
                      (2, "FLOAT_2D", "full_depth_tx"), (3, "FLOAT_2D", "lo_position_tx"),
                      (4, "FLOAT_2D", "lo_normal_tx"), (5, "FLOAT_2D", "gi_indirect_tx"),
                      (6, "FLOAT_2D", "gi_direct_tx"), (7, "FLOAT_2D", "ssao_tx")),
            push=BILATERAL_PUSH,
            outputs=_OUTPUTS,
        )
        return {"main": compile_spec(spec)}

    def _allocate(self, width: int, height: int) -> None:
        import gpu  # noqa: PLC0415

        self.low_width, self.low_height = low_res_size(width, height, self.factor)
        self._targets = [make_target(width, self.low_height, "RGBA16F") for _ in range(3)]
        self._fb = gpu.types.GPUFrameBuffer(color_slots=tuple(self._targets))

    def _release_targets(self) -> None:
        self._targets = None
        self._fb = None
        self.low_width = self.low_height = 0

    def execute(self, gbuffer, low, gi_indirect, gi_direct, ssao) -> FilteredGI:
        """Filter the three low-res RGBA textures horizontally (see module docstring)."""
        self._require()
        check_size(gbuffer.position, self.width, self.height, "gbuffer")
        for tex, what in ((low.position, "low-res gbuffer"), (gi_indirect, "gi_indirect"),
                          (gi_direct, "gi_direct"), (ssao, "ssao")):
            check_size(tex, self.low_width, self.low_height, what)
        shader = self._shader()
        shader.uniform_sampler("full_position_tx", gbuffer.position)
        shader.uniform_sampler("full_normal_tx", gbuffer.normal)
        shader.uniform_sampler("full_depth_tx", gbuffer.depth)
        shader.uniform_sampler("lo_position_tx", low.position)
        shader.uniform_sampler("lo_normal_tx", low.normal)
        shader.uniform_sampler("gi_indirect_tx", gi_indirect)
        shader.uniform_sampler("gi_direct_tx", gi_direct)
        shader.uniform_sampler("ssao_tx", ssao)
        set_bilateral_uniforms(shader, self.settings, self.factor)
        self._draw_fullscreen(self._fb, shader, (self.width, self.low_height))
        return self.outputs()

    def outputs(self) -> FilteredGI:
        if self._targets is None:
            raise RasterError("bilateral: no targets (resize first)")
        a, b, c = self._targets
        return FilteredGI(a, b, c, self.width, self.low_height, self.factor)

    def read(self, slot: int, out: np.ndarray | None = None) -> np.ndarray:
        """Output `slot` (0 indirect, 1 direct+confidence, 2 ssao) as (h_lo, W, 4) float32."""
        return read_framebuffer(self._fb, slot, self.width, self.low_height, 4, out=out)


class BilateralVerticalPass(RasterPass):
    """The vertical taps alone, at full res (debug views and tests of the upsampling).

    `resize(full_w, full_h)`; `execute(gbuffer, filtered) -> (indirect, direct, ssao)` textures
    (RGBA16F, full res; direct.a is the interpolated confidence).
    """

    name = "bilateral vertical"

    def __init__(self, settings: RasterSettings | None = None) -> None:
        super().__init__()
        self.settings = settings or RasterSettings()
        self._targets = None
        self._fb = None

    def _build_shaders(self) -> dict:
        spec = fullscreen_spec(
            "hybridgi_bilateral_v",
            load_glsl("common_lib.glsl", "bilateral_lib.glsl", "bilateral_vertical_lib.glsl",
                      "bilateral_v_frag.glsl"),
            samplers=((0, "FLOAT_2D", "full_position_tx"), (1, "FLOAT_2D", "full_normal_tx"),
                      (2, "FLOAT_2D", "full_depth_tx"), (3, "FLOAT_2D", "h_indirect_tx"),
                      (4, "FLOAT_2D", "h_direct_tx"), (5, "FLOAT_2D", "h_ssao_tx")),
            push=BILATERAL_PUSH,
            outputs=_OUTPUTS,
        )
        return {"main": compile_spec(spec)}

    def _allocate(self, width: int, height: int) -> None:
        import gpu  # noqa: PLC0415

        self._targets = [make_target(width, height, "RGBA16F") for _ in range(3)]
        self._fb = gpu.types.GPUFrameBuffer(color_slots=tuple(self._targets))

    def _release_targets(self) -> None:
        self._targets = None
        self._fb = None

    def execute(self, gbuffer, filtered: FilteredGI):
        self._require()
        check_size(gbuffer.position, self.width, self.height, "gbuffer")
        check_size(filtered.indirect, self.width, low_res_size(self.width, self.height, filtered.factor)[1],
                   "filtered GI")
        shader = self._shader()
        shader.uniform_sampler("full_position_tx", gbuffer.position)
        shader.uniform_sampler("full_normal_tx", gbuffer.normal)
        shader.uniform_sampler("full_depth_tx", gbuffer.depth)
        shader.uniform_sampler("h_indirect_tx", filtered.indirect)
        shader.uniform_sampler("h_direct_tx", filtered.direct)
        shader.uniform_sampler("h_ssao_tx", filtered.ssao)
        set_bilateral_uniforms(shader, self.settings, filtered.factor)
        self._draw_fullscreen(self._fb, shader, (self.width, self.height))
        return tuple(self._targets)

    def read(self, slot: int, out: np.ndarray | None = None) -> np.ndarray:
        """Output `slot` (0 indirect, 1 direct, 2 ssao) as (H, W, 4) float32, rows bottom-up."""
        return read_framebuffer(self._fb, slot, self.width, self.height, 4, out=out)

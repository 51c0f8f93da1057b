"""Step 7: screen-space AO and near-field colour bleeding at the low resolution.

Output: one RGBA16F target at the low-res size, rgb = near-field bounce, a = screen-space AO
(1 = open), the same "GI rgb + AO in a" layout the bilateral pass filters.

The bounce is irradiance (W/m^2) reflected towards each pixel by the occluders found, when an
`irradiance` texture (low-res RGBA, rgb = irradiance arriving at each pixel, e.g. the previous
frame's direct + indirect) is given; occluder radiance is then albedo x E / pi. Without one the
occluders are taken as lit by unit irradiance, so the bounce is the albedo-weighted occluded share
(unitless); `relative_bounce = True` then tells the deferred pass to scale it by the receiver's
own irradiance, a first-order stand-in for the occluders' light (they are within `radius`).
"""

from __future__ import annotations

import logging

import numpy as np

from .glsl import load_glsl
from .passes import (
    CAMERA_TYPEDEF,
    RasterError,
    RasterPass,
    camera_block,
    check_size,
    compile_spec,
    fullscreen_spec,
    make_target,
)
from .readback import read_framebuffer, upload_texture_2d
from .settings import RasterSettings

log = logging.getLogger(__name__)


class SSAOPass(RasterPass):
    """`resize(low_w, low_h)`; `execute(low, view, proj, irradiance=None) -> GPUTexture`.

    settings : RasterSettings (ssao_radius metres, ssao_strength, ssao_samples)
    """

    name = "ssao"

    def __init__(self, settings: RasterSettings | None = None) -> None:
        super().__init__()
        self.settings = settings or RasterSettings()
        self._target = None
        self._fb = None
        self._ubo = None
        self._dummy = None
        #: True after an execute without an irradiance texture (see the module docstring).
        self.relative_bounce = True

    def _build_shaders(self) -> dict:
        spec = fullscreen_spec(
            "hybridgi_ssao",
            load_glsl("common_lib.glsl", "ssao_frag.glsl"),
            samplers=((0, "FLOAT_2D", "albedo_tx"), (1, "FLOAT_2D", "normal_tx"),
                      (2, "FLOAT_2D", "position_tx"), (3, "FLOAT_2D", "irradiance_tx")),
            push=(("FLOAT", "radius"), ("FLOAT", "strength"), ("INT", "samples"), ("INT", "has_irradiance"),
                  ("INT", "normal_gba")),
            typedefs=CAMERA_TYPEDEF,
            ubos=((0, "CameraBlock", "camera"),),
            outputs=((0, "VEC4", "out_ssao"),),
        )
        return {"main": compile_spec(spec)}

    def _allocate(self, width: int, height: int) -> None:
        import gpu  # noqa: PLC0415

        self._target = make_target(width, height, "RGBA16F")
        self._fb = gpu.types.GPUFrameBuffer(color_slots=(self._target,))

    def _release_targets(self) -> None:
        self._target = None
        self._fb = None

    def free(self) -> None:
        super().free()
        self._ubo = None
        self._dummy = None

    def execute(self, low, view: np.ndarray, proj: np.ndarray, irradiance=None, surfaces: bool = False):
        """AO and bounce for the low-res G-buffer `low` (LowResGBuffer of the resize size).

        view, proj : (4, 4) camera matrices of the frame (the same as the G-buffer's).
        irradiance : optional low-res RGBA texture, rgb = irradiance at each pixel (W/m^2).
        surfaces : normal maps bend the G-buffer's normals (`GBufferPass.bends_normals`): the
            hemisphere is the smooth surface's (`low.material`'s gba); around a bent normal it dips
            under the surface, whose own pixels then occlude and bounce light (a ridged
            normal-mapped floor's near-field bounce: Diffuse Indirect +53% of Cycles').
        Returns the RGBA16F texture (rgb bounce, a AO).
        """
        import gpu  # noqa: PLC0415

        self._require()
        check_size(low.position, self.width, self.height, "low-res gbuffer")
        if irradiance is not None:
            check_size(irradiance, self.width, self.height, "irradiance")
        data = camera_block(view, proj)
        if self._ubo is None:
            self._ubo = gpu.types.GPUUniformBuf(data)
        else:
            self._ubo.update(data)
        if self._dummy is None:
            self._dummy = upload_texture_2d(np.ones((1, 1, 4), np.float32), "RGBA16F")
        s = self.settings
        shader = self._shader()
        shader.uniform_block("camera", self._ubo)
        shader.uniform_sampler("albedo_tx", low.albedo)
        smooth = bool(surfaces) and getattr(low, "material", None) is not None
        shader.uniform_sampler("normal_tx", low.material if smooth else low.normal)
        shader.uniform_int("normal_gba", 1 if smooth else 0)
        shader.uniform_sampler("position_tx", low.position)
        shader.uniform_sampler("irradiance_tx", irradiance if irradiance is not None else self._dummy)
        shader.uniform_float("radius", float(s.ssao_radius))
        shader.uniform_float("strength", float(s.ssao_strength))
        shader.uniform_int("samples", int(s.ssao_samples))
        shader.uniform_int("has_irradiance", 0 if irradiance is None else 1)
        self.relative_bounce = irradiance is None
        self._draw_fullscreen(self._fb, shader, (self.width, self.height))
        return self._target

    @property
    def output(self):
        if self._target is None:
            raise RasterError("ssao: no target (resize first)")
        return self._target

    def read(self, out: np.ndarray | None = None) -> np.ndarray:
        """(h, w, 4) float32, rgb bounce + a AO, rows bottom-up."""
        return read_framebuffer(self._fb, 0, self.width, self.height, 4, out=out)

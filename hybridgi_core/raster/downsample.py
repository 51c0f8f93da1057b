"""Step 2: downsample the G-buffer by an integer factor for the GI passes.

Depth-aware: every low-res pixel is a copy of one full-res sample of its factor x factor block,
the one nearest to the camera (see `downsample_frag.glsl`), so a low-res position is always a
point on a real surface; averaging would put points in mid-air at silhouettes, where the CPU
would then pick cache cells and shoot shadow rays.

Targets at ceil(W / f) x ceil(H / f), same formats and meaning as the G-buffer:
albedo RGBA16F, normal RGBA16F, position RGBA32F (w = 1 geometry, 0 background), depth R32F,
material RGBA32F (index + 1, smooth surface normal).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from .glsl import load_glsl
from .passes import RasterError, RasterPass, check_size, compile_spec, fullscreen_spec, low_res_size, make_target
from .readback import read_framebuffer

log = logging.getLogger(__name__)

DOWNSAMPLE_TARGETS = (
    ("albedo", "RGBA16F", 4),
    ("normal", "RGBA16F", 4),
    ("position", "RGBA32F", 4),
    ("depth", "R32F", 1),
    # The same sample's material index + 1 (the viewport's glossy lobes) in r, its smooth surface
    # normal under a normal map in gba (the gather's bent lobes, `GatherPass.execute(surfaces=)`).
    ("material", "RGBA32F", 4),
)


@dataclass
class LowResGBuffer:
    """Downsampled G-buffer textures (owned by the pass) and their size."""

    albedo: object
    normal: object
    position: object
    depth: object
    width: int
    height: int
    factor: int
    material: object = None


class DownsamplePass(RasterPass):
    """`resize(full_w, full_h)` sizes the low-res targets; `execute(gbuffer) -> LowResGBuffer`."""

    name = "downsample"

    def __init__(self, factor: int = 4) -> None:
        super().__init__()
        if not 1 <= int(factor) <= 16:
            raise RasterError(f"downsample factor {factor} out of 1..16")
        self.factor = int(factor)
        self.low_width = 0
        self.low_height = 0
        self._targets = None
        self._fb = None
        self._normal_out = None
        self._position_out = None

    def _build_shaders(self) -> dict:
        spec = fullscreen_spec(
            "hybridgi_downsample",
            load_glsl("common_lib.glsl", "downsample_frag.glsl"),
            samplers=((0, "FLOAT_2D", "albedo_tx"), (1, "FLOAT_2D", "normal_tx"),
                      (2, "FLOAT_2D", "position_tx"), (3, "FLOAT_2D", "depth_tx"),
                      (4, "FLOAT_2D", "material_tx")),
            push=(("INT", "factor"),),
            outputs=tuple((slot, "FLOAT" if ch == 1 else "VEC4", f"out_{name}")
                          for slot, (name, _f, ch) in enumerate(DOWNSAMPLE_TARGETS)),
        )
        return {"main": compile_spec(spec)}

    def _allocate(self, width: int, height: int) -> None:
        import gpu  # noqa: PLC0415

        self.low_width, self.low_height = low_res_size(width, height, self.factor)
        self._targets = {name: make_target(self.low_width, self.low_height, fmt)
                         for name, fmt, _ch in DOWNSAMPLE_TARGETS}
        self._fb = gpu.types.GPUFrameBuffer(
            color_slots=tuple(self._targets[name] for name, _f, _c in DOWNSAMPLE_TARGETS))
        shape = (self.low_height, self.low_width, 4)
        self._normal_out = np.empty(shape, np.float32)
        self._position_out = np.empty(shape, np.float32)

    def _release_targets(self) -> None:
        self._targets = None
        self._fb = None
        self._normal_out = self._position_out = None
        self.low_width = self.low_height = 0

    def execute(self, gbuffer) -> LowResGBuffer:
        """Downsample `gbuffer` (a GBuffer of the size given to `resize`)."""
        self._require()
        check_size(gbuffer.depth, self.width, self.height, "gbuffer")
        shader = self._shader()
        shader.uniform_sampler("albedo_tx", gbuffer.albedo)
        shader.uniform_sampler("normal_tx", gbuffer.normal)
        shader.uniform_sampler("position_tx", gbuffer.position)
        shader.uniform_sampler("depth_tx", gbuffer.depth)
        shader.uniform_sampler("material_tx", gbuffer.material)
        shader.uniform_int("factor", self.factor)
        self._draw_fullscreen(self._fb, shader, (self.low_width, self.low_height))
        return self.outputs()

    def outputs(self) -> LowResGBuffer:
        t = self._targets
        if t is None:
            raise RasterError("downsample: no targets (resize first)")
        return LowResGBuffer(t["albedo"], t["normal"], t["position"], t["depth"],
                             self.low_width, self.low_height, self.factor, t["material"])

    def read(self, name: str, out: np.ndarray | None = None) -> np.ndarray:
        """Low-res target `name` as (h, w, c) float32, rows bottom-up."""
        for slot, (tname, _fmt, ch) in enumerate(DOWNSAMPLE_TARGETS):
            if tname == name:
                return read_framebuffer(self._fb, slot, self.low_width, self.low_height, ch, out=out)
        raise KeyError(name)

    def read_normal_position(self) -> tuple[np.ndarray, np.ndarray]:
        """Low-res normals and positions for the CPU (visible cells, direct light).

        Returns (normal, position), each (h, w, 4) float32, rows bottom-up: normal xyz unit
        (a = 1 on geometry), position xyz world + w (1 geometry, 0 background). Both arrays are
        reused by the next call: copy them to keep them. Read straight into numpy memory
        (`read_color` into a Buffer over the array, no Python lists).
        """
        self._require()
        read_framebuffer(self._fb, 1, self.low_width, self.low_height, 4, out=self._normal_out)
        read_framebuffer(self._fb, 2, self.low_width, self.low_height, 4, out=self._position_out)
        return self._normal_out, self._position_out

"""The pixel rays' edge-aware a-trous filter (`pixel_gather.filter_residual`) as GPU passes.

Why: the filter is a fixed 5 x 5 gather per pixel and pass, the GPU's natural work. In numpy it
is ~40 whole-image array operations per tap, 3 passes of 25 taps over 7 channels: 70-100 ms of
the Cornell box's 640x360 final render on this 2-core host, where llvmpipe runs the same
arithmetic fused per pixel (and a GPU in well under a millisecond). The numpy function stays the
reference (and the viewport worker's, which has no GPU context); `tests/test_atrous.py` holds
the two equal.

Calling an `AtrousPass` (residual, position, normal, valid, camera, passes, plane_sigma,
normal_power, variance=, noise_sigma=, stretch=) has `filter_residual`'s signature and answer (up
to float32 rounding in another order); a `FramePipeline` hands it to `full_res_images` as its
`filter`.
"""

from __future__ import annotations

import logging

import numpy as np

from .glsl import load_glsl
from .passes import RasterPass, compile_spec, fullscreen_spec, make_target
from .readback import read_framebuffer, upload_texture_2d

log = logging.getLogger(__name__)

#: Image channels the pass carries (two RGBA targets); variance guides (one RGBA target).
MAX_CHANNELS = 8
MAX_GUIDES = 3


class AtrousPass(RasterPass):
    """`resize(w, h)` at the GI resolution; `__call__` = `filter_residual` (module docstring)."""

    name = "atrous"

    def __init__(self) -> None:
        super().__init__()
        self._sets = None  # two (targets, framebuffer) pairs, ping-ponged between passes

    def _build_shaders(self) -> dict:
        spec = fullscreen_spec(
            "hybridgi_atrous",
            load_glsl("common_lib.glsl", "atrous_frag.glsl"),
            samplers=((0, "FLOAT_2D", "img_a_tx"), (1, "FLOAT_2D", "img_b_tx"), (2, "FLOAT_2D", "var_tx"),
                      (3, "FLOAT_2D", "pos_tx"), (4, "FLOAT_2D", "nrm_tx")),
            push=(("VEC4", "camera"), ("INT", "step"), ("INT", "guides"), ("FLOAT", "plane_sigma"),
                  ("FLOAT", "normal_power"), ("FLOAT", "noise_k2"), ("FLOAT", "stretch")),
            outputs=((0, "VEC4", "out_a"), (1, "VEC4", "out_b"), (2, "VEC4", "out_var")),
        )
        return {"main": compile_spec(spec)}

    def _allocate(self, width: int, height: int) -> None:
        import gpu  # noqa: PLC0415

        self._sets = []
        for _ in range(2):
            targets = tuple(make_target(width, height, "RGBA32F") for _ in range(3))
            self._sets.append((targets, gpu.types.GPUFrameBuffer(color_slots=targets)))

    def _release_targets(self) -> None:
        self._sets = None

    def __call__(self, residual: np.ndarray, position: np.ndarray, normal: np.ndarray, valid: np.ndarray,
                 camera: np.ndarray, passes: int = 3, plane_sigma: float = 0.02, normal_power=8.0,
                 variance: np.ndarray | None = None, noise_sigma: float = 2.0, pool=None,
                 stretch: float | None = None) -> np.ndarray:
        """`filter_residual` on the GPU: (h, w, c) float32 (c <= MAX_CHANNELS), its stretch term
        too. pool is unused (the numpy version's bands)."""
        valid = np.asarray(valid, bool)
        h, w = valid.shape
        image = np.where(valid[..., None], np.asarray(residual, np.float32), np.float32(0.0))
        c = image.shape[-1]
        if passes <= 0 or not valid.any():
            return image.astype(np.float32)
        if c > MAX_CHANNELS or (variance is not None and variance.shape[-1] not in (2, MAX_GUIDES)):
            raise ValueError(f"atrous: {c} channels / variance {None if variance is None else variance.shape}")
        self.resize(w, h)
        self._require()
        planes = np.zeros((h, w, MAX_CHANNELS), np.float32)
        planes[..., :c] = image
        var = np.zeros((h, w, 4), np.float32)
        if variance is not None:
            guides = variance.shape[-1]
            var[..., :guides] = np.where(valid[..., None], variance, 0.0)  # 2 guides: (luminance, AO) in xy
        pos = np.zeros((h, w, 4), np.float32)
        pos[..., :3] = position
        pos[..., 3] = valid
        textures = [upload_texture_2d(a, "RGBA32F") for a in (planes[..., :4], planes[..., 4:], var, pos)]
        per_pixel = isinstance(normal_power, np.ndarray)
        if per_pixel:  # each pixel's own exponent in its normal's w (the shader reads it for normal_power < 0)
            n4 = np.zeros((h, w, 4), np.float32)
            n4[..., :3] = np.asarray(normal, np.float32)[..., :3]
            n4[..., 3] = normal_power
            nrm = upload_texture_2d(n4, "RGBA32F")
        else:
            nrm = upload_texture_2d(np.asarray(normal, np.float32), "RGBA32F", pad_value=0.0)
        shader = self._shader()
        cam = np.zeros(4, np.float32)
        cam[:3] = np.asarray(camera, np.float32)[:3]
        src = textures[:3]
        for i in range(passes):
            targets, fb = self._sets[i % 2]
            shader.uniform_sampler("img_a_tx", src[0])
            shader.uniform_sampler("img_b_tx", src[1])
            shader.uniform_sampler("var_tx", src[2])
            shader.uniform_sampler("pos_tx", textures[3])
            shader.uniform_sampler("nrm_tx", nrm)
            shader.uniform_float("camera", cam)
            shader.uniform_int("step", 1 << i)
            shader.uniform_int("guides", 0 if variance is None else variance.shape[-1])
            shader.uniform_float("plane_sigma", float(plane_sigma))
            shader.uniform_float("normal_power", -1.0 if per_pixel else float(normal_power))
            shader.uniform_float("noise_k2", float(noise_sigma) ** 2)
            shader.uniform_float("stretch", 0.0 if stretch is None else float(stretch))
            self._draw_fullscreen(fb, shader, (w, h))
            src = targets
        _targets, fb = self._sets[(passes - 1) % 2]
        out = np.empty((h, w, MAX_CHANNELS), np.float32)
        out[..., :4] = read_framebuffer(fb, 0, w, h, 4)
        if c > 4:
            out[..., 4:] = read_framebuffer(fb, 1, w, h, 4)
        return out[..., :c]

"""The full-res interpolation of the pixel rays' GI (`pixel_gather.upsample_full`) as a GPU pass.

Why: every full-res pixel gathers its 3 x 3 GI pixels with a few dozen operations per tap, which
numpy runs as ~30 whole-image array passes (75-200 ms of a 640x360 final render on this 2-core
host: `pixel_upsample`), and a GPU in well under a millisecond. The numpy function stays the
reference and the path of the viewport's worker (no GPU context), of a jittered subframe's few
thousand samples (`GIResolver`) and of pixels a normal map bends (their bent lobe is not ported);
`tests/test_upsample.py` holds the two equal.

Calling an `UpsamplePass` with `upsample_full`'s arguments returns its `Upsampled`; a
`FramePipeline` hands it to `full_res_images` as its `upsample`, and the viewport's draw to
`pixel_gather.full_res_preview` for a pixel pass its worker has not resolved yet.
"""

from __future__ import annotations

import numpy as np

from ..pixel_gather import STRETCH, Upsampled, tap_records, upsample_full
from .gather import max_texture_size
from .glsl import load_glsl
from .passes import RasterPass, compile_spec, fullscreen_spec, make_target
from .readback import read_framebuffer, upload_texture_2d

#: The output targets: cache 0-3, (cache 4-6, best), residual 0-3, (residual 4-6, cover),
#: (luminance spread, AO spread, turned, 1).
OUTPUTS = ("out_cache_a", "out_cache_b", "out_res_a", "out_res_b", "out_misc")
#: The GI-resolution inputs, from `tap_records`' rows, and the full-res ones.
SAMPLERS = ("pts_tx", "nrm_tx", "rec_pos_tx", "rec_nrm_tx", "rec_xy_tx", "cache_a_tx", "cache_b_tx", "res_a_tx",
            "res_b_tx", "sh_tx")


class UpsamplePass(RasterPass):
    """`__call__` = `upsample_full` (module docstring); sized per call to the full-res image."""

    name = "upsample"

    def __init__(self) -> None:
        super().__init__()
        self._fb = self._targets = None

    def _build_shaders(self) -> dict:
        spec = fullscreen_spec(
            "hybridgi_upsample",
            load_glsl("common_lib.glsl", "upsample_frag.glsl"),
            samplers=tuple((i, "FLOAT_2D", name) for i, name in enumerate(SAMPLERS)),
            push=(("VEC4", "camera"), ("VEC2", "offset"), ("INT", "factor"), ("INT", "sh_count"),
                  ("FLOAT", "inv2s2"), ("FLOAT", "plane_sigma"), ("FLOAT", "normal_power"), ("FLOAT", "stretch")),
            outputs=tuple((i, "VEC4", name) for i, name in enumerate(OUTPUTS)),
        )
        return {"main": compile_spec(spec)}

    def _allocate(self, width: int, height: int) -> None:
        import gpu  # noqa: PLC0415

        # The framebuffer does not keep its textures alive: the pass does.
        self._targets = tuple(make_target(width, height, "RGBA32F") for _ in OUTPUTS)
        self._fb = gpu.types.GPUFrameBuffer(color_slots=self._targets)

    def _release_targets(self) -> None:
        self._fb = self._targets = None

    def __call__(self, sh_lo, cache_lo, residual_lo, position_lo, normal_lo, valid_lo, points, normals, pix,
                 width: int, factor: int, camera, plane_sigma: float = 0.02, normal_power: float = 8.0,
                 sigma: float = 1.0, rep_xy=None, offset=(0.0, 0.0), records=None, surfaces=None,
                 stretch: float | None = STRETCH) -> Upsampled:
        """`upsample_full` on the GPU; with `surfaces` (bent normals), no pixels or an image whose
        SH texture (2 w x K h texels) would exceed the GPU's texture size, numpy's."""
        pix = np.asarray(pix)
        h, w = valid_lo.shape
        k = sh_lo.shape[1]
        if surfaces is not None or pix.size == 0 or rep_xy is None or max(2 * w, k * h) > max_texture_size():
            return upsample_full(sh_lo, cache_lo, residual_lo, position_lo, normal_lo, valid_lo, points, normals,
                                 pix, width, factor, camera, plane_sigma, normal_power, sigma, rep_xy, offset,
                                 records, surfaces, stretch)
        height = int(pix.max()) // width + 1
        self.resize(width, height)
        self._require()
        rec = tap_records(cache_lo, residual_lo, position_lo, normal_lo, valid_lo, rep_xy) if records is None \
            else records

        def gi_texture(*rows):
            planes = np.zeros((4, h * w), np.float32)
            for i, row in enumerate(rows):
                if row is not None:
                    planes[i] = rec[row]
            return upload_texture_2d(np.ascontiguousarray(planes.T).reshape(h, w, 4), "RGBA32F")

        def full_texture(values, w_value):
            image = np.zeros((height * width, 4), np.float32)
            image[pix, :3] = values
            image[pix, 3] = w_value
            return upload_texture_2d(image.reshape(height, width, 4), "RGBA32F")

        sh = np.zeros((h, w, k, 8), np.float32)
        sh[..., :7] = np.asarray(sh_lo, np.float32).reshape(h, w, k, 7)
        # Coefficient kk of GI pixel (i, j) at texels (2 i, j K + kk) and (2 i + 1, j K + kk).
        sh_image = sh.reshape(h, w, k, 2, 4).transpose(0, 2, 1, 3, 4).reshape(h * k, w * 2, 4)
        textures = {
            "pts_tx": full_texture(np.asarray(points, np.float32), 1.0),
            "nrm_tx": full_texture(np.asarray(normals, np.float32), 0.0),
            "rec_pos_tx": gi_texture(0, 1, 2, 8),
            "rec_nrm_tx": gi_texture(3, 4, 5, 23),
            "rec_xy_tx": gi_texture(6, 7, 24, 25),
            "cache_a_tx": gi_texture(9, 10, 11, 12),
            "cache_b_tx": gi_texture(13, 14, 15, None),
            "res_a_tx": gi_texture(16, 17, 18, 19),
            "res_b_tx": gi_texture(20, 21, 22, None),
            "sh_tx": upload_texture_2d(np.ascontiguousarray(sh_image), "RGBA32F"),
        }
        shader = self._shader()
        for name in SAMPLERS:
            shader.uniform_sampler(name, textures[name])
        cam = np.zeros(4, np.float32)
        cam[:3] = np.asarray(camera, np.float32)[:3]
        shader.uniform_float("camera", cam)
        shader.uniform_float("offset", np.asarray(offset, np.float32))
        shader.uniform_int("factor", int(factor))
        shader.uniform_int("sh_count", int(k))
        shader.uniform_float("inv2s2", float(np.float32(0.5 / (sigma * factor) ** 2)))
        shader.uniform_float("plane_sigma", float(plane_sigma))
        shader.uniform_float("normal_power", float(normal_power))
        shader.uniform_float("stretch", 0.0 if stretch is None else float(stretch))
        self._draw_fullscreen(self._fb, shader, (width, height))
        out = [read_framebuffer(self._fb, i, width, height, 4).reshape(-1, 4)[pix] for i in range(len(OUTPUTS))]
        cache = np.concatenate([out[0], out[1][:, :3]], axis=1)
        residual = np.concatenate([out[2], out[3][:, :3]], axis=1)
        return Upsampled(np.ascontiguousarray(cache), np.ascontiguousarray(residual),
                         np.ascontiguousarray(out[4][:, :2]), np.ascontiguousarray(out[1][:, 3]),
                         np.ascontiguousarray(out[3][:, 3]), out[4][:, 2] > 0.5)

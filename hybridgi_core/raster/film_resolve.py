"""The film's resolve on the GPU: the pixel filter over the accumulated subframe sums and Cycles'
divisions (`film_resolve_frag.glsl`), and the glossy passes from the centre raster's glossy light
(`film_glossy_frag.glsl`), read back as the passes the render result takes.

Why: `subpixel.FilmAccumulator` did it in numpy on the render thread (~37 ms at 640x360: six
separable filters and two colour divisions over full-res RGBA images, nine times that at
1920x1080), work a GPU does in a fraction of a millisecond beside the sums it already holds. The
numpy path stays the reference, and the fallback for filters wider than MAX_RADIUS pixels (a
filter's taps are a loop of (2 r + 1)^2 reads per pixel and pass here).
"""

from __future__ import annotations

import numpy as np

from .accumulate import SUM_TARGETS, AccumulatePass
from .glsl import load_glsl
from .passes import RasterError, RasterPass, compile_spec, fullscreen_spec, make_target
from .readback import read_framebuffer, upload_texture_2d

#: The glossy passes (`subpixel.FilmAccumulator.set_glossy`'s names), three channels each.
GLOSSY_PASSES = ("glossy_color", "glossy_direct", "glossy_indirect")
#: Widest filter (taps either side of the pixel) the pass takes: Blackman-Harris up to ~2.5 px,
#: Gaussian up to ~1.5 px, Box up to ~5 px (Cycles' defaults: 1.5 px Blackman-Harris, radius 1).
MAX_RADIUS = 2


def supports(taps: np.ndarray) -> bool:
    """Whether the pass resolves a film filtered by `taps` (`subpixel.reconstruction_taps`)."""
    return np.asarray(taps).size <= 2 * MAX_RADIUS + 1


class FilmResolvePass(RasterPass):
    """`resize(w, h)`; `execute(accumulate, taps)` after the last subframe; `read_all()` the passes."""

    name = "film resolve"

    def __init__(self) -> None:
        super().__init__()
        self._targets = None
        self._fb = None
        self._glossy_fb = None  # the glossy passes' targets, made on first use

    def _build_shaders(self) -> dict:
        samplers = tuple((i, "FLOAT_2D", f"{name}_tx") for i, (name, _f, _c) in enumerate(SUM_TARGETS))
        spec = fullscreen_spec(
            "hybridgi_film_resolve", load_glsl("film_resolve_frag.glsl"), samplers=samplers,
            push=(("VEC4", "taps0"), ("VEC4", "taps1"), ("INT", "radius"), ("FLOAT", "inv_count")),
            outputs=tuple((slot, "VEC4", f"out_{name}") for slot, (name, _f, _c) in enumerate(SUM_TARGETS)),
        )
        glossy = fullscreen_spec(
            "hybridgi_film_glossy", load_glsl("film_glossy_frag.glsl"),
            samplers=((0, "FLOAT_2D", "radiance_tx"), (1, "FLOAT_2D", "colour_tx"), (2, "FLOAT_2D", "indirect_tx")),
            push=(("VEC4", "taps0"), ("VEC4", "taps1"), ("INT", "radius")),
            outputs=tuple((slot, "VEC4", f"out_{name}") for slot, name in enumerate(GLOSSY_PASSES)),
        )
        return {"main": compile_spec(spec), "glossy": compile_spec(glossy)}

    def _allocate(self, width: int, height: int) -> None:
        import gpu  # noqa: PLC0415

        self._targets = {name: make_target(width, height, fmt) for name, fmt, _c in SUM_TARGETS}
        self._fb = gpu.types.GPUFrameBuffer(color_slots=tuple(self._targets[name] for name, _f, _c in SUM_TARGETS))

    def _release_targets(self) -> None:
        self._targets = None
        self._fb = None
        self._glossy_fb = None

    def execute(self, accumulate: AccumulatePass, taps: np.ndarray) -> None:
        """Resolve `accumulate`'s sums of `accumulate.count` subframes with the filter `taps`."""
        self._require()
        taps = _checked(taps)
        if accumulate.count == 0:
            raise RasterError("film resolve: nothing accumulated")
        shader = self._shader()
        for name, _f, _c in SUM_TARGETS:
            shader.uniform_sampler(f"{name}_tx", accumulate.texture(name))
        _set_taps(shader, taps)
        shader.uniform_float("inv_count", float(np.float32(1.0) / np.float32(accumulate.count)))
        self._draw_fullscreen(self._fb, shader, (self.width, self.height))

    def read_all(self) -> dict[str, np.ndarray]:
        """The resolved passes, (h, w, c) float32 rows bottom-up, under FilmAccumulator's names
        ("normal" (3) and "ao" (1) split out of "normal_ao")."""
        if self._fb is None:
            raise RasterError("film resolve: call resize() and execute() first")
        out = {name: read_framebuffer(self._fb, slot, self.width, self.height, ch)
               for slot, (name, _fmt, ch) in enumerate(SUM_TARGETS)}
        normal_ao = out.pop("normal_ao")
        out["normal"] = normal_ao[..., :3]
        out["ao"] = normal_ao[..., 3:]
        return out

    def glossy(self, radiance: np.ndarray, colour: np.ndarray, indirect: np.ndarray | None,
               taps: np.ndarray) -> dict[str, np.ndarray]:
        """The glossy passes (GLOSSY_PASSES, (h, w, 3) float32 rows bottom-up) of the centre
        raster's (h w, 4) lamp radiance, Glossy Color and the light before its colour
        (`indirect`, None: 0), filtered by `taps`: `FilmAccumulator.set_glossy` on the GPU."""
        import gpu  # noqa: PLC0415

        self._require()
        taps = _checked(taps)
        if self._glossy_fb is None:
            targets = [make_target(self.width, self.height, "RGBA32F") for _ in GLOSSY_PASSES]
            self._glossy_fb = (targets, gpu.types.GPUFrameBuffer(color_slots=tuple(targets)))
        shape = (self.height, self.width, 4)
        shader = self._shader("glossy")
        zeros = np.zeros(shape, np.float32)
        textures = []  # held until the draw: a bound texture that is freed reads as 0
        for name, array in (("radiance", radiance), ("colour", colour), ("indirect", indirect)):
            data = zeros if array is None else np.asarray(array, np.float32).reshape(shape)
            textures.append(upload_texture_2d(data, "RGBA32F"))
            shader.uniform_sampler(f"{name}_tx", textures[-1])
        _set_taps(shader, taps)
        fb = self._glossy_fb[1]
        self._draw_fullscreen(fb, shader, (self.width, self.height))
        del textures
        return {name: read_framebuffer(fb, slot, self.width, self.height, 3) for slot, name in enumerate(GLOSSY_PASSES)}


def _checked(taps: np.ndarray) -> np.ndarray:
    taps = np.asarray(taps, np.float32).reshape(-1)
    if not supports(taps) or taps.size % 2 == 0:
        raise RasterError(f"film resolve: {taps.size} taps (odd, at most {2 * MAX_RADIUS + 1})")
    return taps


def _set_taps(shader, taps: np.ndarray) -> None:
    padded = np.zeros(8, np.float32)
    padded[: taps.size] = taps
    shader.uniform_float("taps0", padded[:4])
    shader.uniform_float("taps1", padded[4:])
    shader.uniform_int("radius", taps.size // 2)

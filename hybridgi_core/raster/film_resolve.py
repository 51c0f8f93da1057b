"""The film's resolve on the GPU: the pixel filter over the accumulated subframe sums and Cycles'
divisions (`film_resolve_frag.glsl`), read back as the passes the render result takes.

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
from .readback import read_framebuffer

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

    def _build_shaders(self) -> dict:
        samplers = tuple((i, "FLOAT_2D", f"{name}_tx") for i, (name, _f, _c) in enumerate(SUM_TARGETS))
        spec = fullscreen_spec(
            "hybridgi_film_resolve", load_glsl("film_resolve_frag.glsl"), samplers=samplers,
            push=(("VEC4", "taps0"), ("VEC4", "taps1"), ("INT", "radius"), ("FLOAT", "inv_count")),
            outputs=tuple((slot, "VEC4", f"out_{name}") for slot, (name, _f, _c) in enumerate(SUM_TARGETS)),
        )
        return {"main": compile_spec(spec)}

    def _allocate(self, width: int, height: int) -> None:
        import gpu  # noqa: PLC0415

        self._targets = {name: make_target(width, height, fmt) for name, fmt, _c in SUM_TARGETS}
        self._fb = gpu.types.GPUFrameBuffer(color_slots=tuple(self._targets[name] for name, _f, _c in SUM_TARGETS))

    def _release_targets(self) -> None:
        self._targets = None
        self._fb = None

    def execute(self, accumulate: AccumulatePass, taps: np.ndarray) -> None:
        """Resolve `accumulate`'s sums of `accumulate.count` subframes with the filter `taps`."""
        self._require()
        taps = np.asarray(taps, np.float32).reshape(-1)
        if not supports(taps) or taps.size % 2 == 0:
            raise RasterError(f"film resolve: {taps.size} taps (odd, at most {2 * MAX_RADIUS + 1})")
        if accumulate.count == 0:
            raise RasterError("film resolve: nothing accumulated")
        padded = np.zeros(8, np.float32)
        padded[: taps.size] = taps
        shader = self._shader()
        for name, _f, _c in SUM_TARGETS:
            shader.uniform_sampler(f"{name}_tx", accumulate.texture(name))
        shader.uniform_float("taps0", padded[:4])
        shader.uniform_float("taps1", padded[4:])
        shader.uniform_int("radius", taps.size // 2)
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

"""The pixel filter's running sums on the GPU: each subframe's deferred targets (and G-buffer
normal) are added into full-res RGBA32F sums, so K subframes cost K fullscreen draws and one
read-back at the end, not K read-backs and K numpy sums. `subpixel.FilmAccumulator` turns the
sums into Cycles' passes (`accumulate_frag.glsl` says what is summed).
"""

from __future__ import annotations

import logging

import numpy as np

from .glsl import load_glsl
from .passes import RasterError, RasterPass, check_size, compile_spec, fullscreen_spec, make_target
from .readback import read_framebuffer

log = logging.getLogger(__name__)

#: The sums (name, format, channels); names as FilmAccumulator's, except "normal_ao": the normal
#: in xyz and AO in w (Blender's framebuffers take 6 colour attachments at most).
SUM_TARGETS = (
    ("combined", "RGBA32F", 4),
    ("combined_premultiplied", "RGBA32F", 4),
    ("diffuse_direct", "RGBA32F", 4),
    ("diffuse_indirect", "RGBA32F", 4),
    ("diffuse_color", "RGBA32F", 4),
    ("normal_ao", "RGBA32F", 4),
)

#: The subframe's inputs: the deferred targets, then the G-buffer's normal and position.
_INPUTS = ("combined", "diffuse_direct", "diffuse_indirect", "diffuse_color", "ao", "normal", "position")


class AccumulatePass(RasterPass):
    """`resize(w, h)`; `execute(shaded, gbuffer, first)` per subframe; `read(name)` the sums."""

    name = "accumulate"

    def __init__(self) -> None:
        super().__init__()
        self._sets = None  # two (targets, framebuffer) pairs, written alternately
        self._current = 0  # the set holding the latest sums
        self.count = 0

    def _build_shaders(self) -> dict:
        samplers = tuple((i, "FLOAT_2D", f"{name}_tx") for i, name in enumerate(_INPUTS))
        samplers += tuple((len(_INPUTS) + i, "FLOAT_2D", f"prev_{name}_tx")
                          for i, (name, _f, _c) in enumerate(SUM_TARGETS))
        spec = fullscreen_spec(
            "hybridgi_accumulate", load_glsl("accumulate_frag.glsl"), samplers=samplers,
            push=(("INT", "first"),),
            outputs=tuple((slot, "FLOAT" if ch == 1 else "VEC4", f"out_{name}")
                          for slot, (name, _f, ch) in enumerate(SUM_TARGETS)),
        )
        return {"main": compile_spec(spec)}

    def _allocate(self, width: int, height: int) -> None:
        import gpu  # noqa: PLC0415

        self._sets = []
        for _ in range(2):
            targets = {name: make_target(width, height, fmt) for name, fmt, _c in SUM_TARGETS}
            fb = gpu.types.GPUFrameBuffer(color_slots=tuple(targets[name] for name, _f, _c in SUM_TARGETS))
            self._sets.append((targets, fb))
        self._current = 0
        self.count = 0

    def _release_targets(self) -> None:
        self._sets = None
        self.count = 0

    def execute(self, shaded, gbuffer, first: bool) -> None:
        """Add one subframe: shaded (a ShadedFrame) and the G-buffer it was shaded from; `first`
        starts new sums."""
        self._require()
        check_size(shaded.combined, self.width, self.height, "shaded frame")
        check_size(gbuffer.normal, self.width, self.height, "gbuffer")
        if not first and self.count == 0:
            raise RasterError("accumulate: the first subframe must start the sums")
        prev, _fb = self._sets[self._current]
        target = 1 - self._current if not first else 0
        if first:
            prev = self._sets[1][0]  # never read (first = 1), but a bound texture is required
        shader = self._shader()
        inputs = (shaded.combined, shaded.diffuse_direct, shaded.diffuse_indirect, shaded.diffuse_color,
                  shaded.ao, gbuffer.normal, gbuffer.position)
        for name, tex in zip(_INPUTS, inputs, strict=True):
            shader.uniform_sampler(f"{name}_tx", tex)
        for name, _f, _c in SUM_TARGETS:
            shader.uniform_sampler(f"prev_{name}_tx", prev[name])
        shader.uniform_int("first", 1 if first else 0)
        self._draw_fullscreen(self._sets[target][1], shader, (self.width, self.height))
        self._current = target
        self.count = 1 if first else self.count + 1

    def texture(self, name: str):
        """The GPU texture of sum `name` so far (the viewport draws the running Combined from it)."""
        if self._sets is None or self.count == 0:
            raise RasterError("accumulate: nothing accumulated")
        return self._sets[self._current][0][name]

    def read(self, name: str) -> np.ndarray:
        """Sum `name` over the subframes so far, (h, w, c) float32, rows bottom-up."""
        if self._sets is None or self.count == 0:
            raise RasterError("accumulate: nothing accumulated")
        _targets, fb = self._sets[self._current]
        for slot, (tname, _fmt, ch) in enumerate(SUM_TARGETS):
            if tname == name:
                return read_framebuffer(fb, slot, self.width, self.height, ch)
        raise KeyError(name)

    def read_all(self) -> dict[str, np.ndarray]:
        """Every sum under FilmAccumulator's names ("normal" and "ao" split out of "normal_ao")."""
        sums = {name: self.read(name) for name, _f, _c in SUM_TARGETS}
        normal_ao = sums.pop("normal_ao")
        sums["normal"] = normal_ao[..., :3]
        sums["ao"] = normal_ao[..., 3:]
        return sums

"""Anti-aliasing of a still viewport: jittered subframes accumulated over redraws, as final renders
accumulate theirs within a frame (`hybridgi_core.raster.subpixel`, the same offsets and pixel filter).

A redraw that runs the pipeline (a new view, new light from the worker, a scene edit) draws the
pixel-centre image, the first sample of a new running sum (added to it with the first subframe). Each later redraw of the same view and
the same worker results adds one jittered subframe (its G-buffer rasterized with a shifted
projection, shaded from the same GI, light and glossy textures) until the sum holds the centre
and all `count` subframes of the final render's pattern; the view shows the running mean, so the
settled image converges to the final render's anti-aliased one. Any change starts over.

Looking through a camera with depth of field, each subframe also renders through its own lens
point (`hybridgi_core.raster.lens`, as final renders do; at least its MIN_SUBFRAMES of them): the
centre image is the pinhole's, the settled mean the blurred one.

The subframes cost the GPU a G-buffer, the resolves and the shading passes each: milliseconds on
a GPU, but on a software renderer (llvmpipe) they take the cores the worker traces on, so there
they wait until the worker is idle (`while_busy` = False), and interactive response is unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from hybridgi_core.raster import lens as _lens
from hybridgi_core.raster import subpixel


@dataclass
class Accumulation:
    """The running anti-aliasing sum of one view (main thread): `drawn` samples so far, the
    centre first; `offsets` (count, 2) the jittered subframes' pixel offsets."""

    offsets: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    texture_filter: float = 0.0
    drawn: int = 0
    inputs: dict | None = None  # what the centre redraw shaded with (cameras, textures)
    lens: _lens.Lens | None = None  # the camera's thin lens looked through, or None (a pinhole)
    apertures: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # each subframe's lens point

    @classmethod
    def pattern(cls, count: int, filter_size: float, filter_type: str, lens: _lens.Lens | None = None
                ) -> Accumulation:
        """The final render's subframe pattern for `count` pixel samples (1: none, the centre alone),
        through `lens` (its lens points; at least `lens.MIN_SUBFRAMES` subframes) where given."""
        count = max(int(count), 1)
        if count == 1:
            return cls()
        if lens is not None and lens.active:
            count = max(count, _lens.MIN_SUBFRAMES)
        else:
            lens = None
        return cls(subpixel.subpixel_offsets(count, filter_size, filter_type),
                   subpixel.subframe_texture_filter(count, filter_size), lens=lens,
                   apertures=_lens.lens_points(count, lens) if lens is not None else np.zeros((0, 2)))

    @property
    def config(self) -> tuple:
        """What a view's key must hold: another pattern starts over."""
        return (self.offsets.shape[0], round(self.texture_filter, 6), self.offsets.tobytes(), self.lens)

    def next_camera(self, view: np.ndarray, proj: np.ndarray, width: int, height: int):
        """(view, jittered projection) of the next subframe: its pixel offset, and its lens point
        with the plane of focus kept (`lens.lens_view`, `lens.focus_offset`) under a lens."""
        offset = self.next_offset()
        if self.lens is not None:
            point = self.apertures[self.drawn - 1]
            view = _lens.lens_view(view, point)
            offset = offset + _lens.focus_offset(proj, point, self.lens, width, height)
        return view, subpixel.jittered_projection(proj, offset, width, height)

    def start(self, inputs: dict) -> None:
        """A centre redraw began a new sum (it is sample 1)."""
        self.drawn = 1 if self.offsets.shape[0] else 0
        self.inputs = inputs if self.offsets.shape[0] else None

    def reset(self) -> None:
        self.drawn = 0
        self.inputs = None

    @property
    def pending(self) -> bool:
        """A subframe is left to add to a started sum."""
        return self.inputs is not None and 0 < self.drawn <= self.offsets.shape[0]

    def next_offset(self) -> np.ndarray:
        return self.offsets[self.drawn - 1]

    @property
    def total(self) -> int:
        """Samples of the complete sum: the centre and every jittered subframe."""
        return self.offsets.shape[0] + 1 if self.offsets.shape[0] else 1

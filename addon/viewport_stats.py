"""What a viewport redraw costs and what the sidebar shows: the camera of a view, per-step
milliseconds of a redraw (GPU steps told apart from main-thread CPU work), and the status line.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from .worker_messages import WorkerStats

#: Steps of `DrawStats` that only submit GPU work or wait for it (not main-thread CPU work).
GPU_STEPS = frozenset({"gbuffer", "downsample", "readback", "resolve", "gather", "ssao", "bilateral", "deferred",
                       "accumulate", "present", "display"})


@dataclass(frozen=True)
class ViewCamera:
    """A viewport camera: world->view and view->clip (4, 4) float64, as `region_data` gives them."""

    view: np.ndarray
    proj: np.ndarray
    lens: object = None  # the scene camera's `raster.lens.Lens` when the view looks through it with depth of field

    @classmethod
    def from_region_data(cls, rv3d, lens=None) -> ViewCamera:
        # window_matrix already frames the region as drawn: perspective, orthographic or the
        # camera view with its zoom and offset (the passepartout area included).
        return cls(np.array(rv3d.view_matrix, np.float64), np.array(rv3d.window_matrix, np.float64), lens)

    @property
    def key(self) -> bytes:
        return self.view.tobytes() + self.proj.tobytes()


@dataclass
class DrawStats:
    """Main-thread milliseconds of one redraw, per step (GPU_STEPS submit or wait for the GPU)."""

    steps_ms: dict = field(default_factory=dict)
    total_ms: float = 0.0  # wall time of the whole redraw
    redrawn: bool = False  # False: the last image was drawn again without running the pipeline
    posted_view: bool = False
    view_current: bool = False  # the direct light drawn was traced for this very view
    low_res: tuple = (0, 0)  # FramePipeline.rasterize records the GI resolution here
    subframe: int = 0  # the anti-aliasing subframe this redraw added (0: a centre redraw)

    def step(self, name: str):
        return _Timer(self.steps_ms, name)

    @property
    def cpu_ms(self) -> float:
        """Main-thread time that is not GPU work: the wall time minus the GPU steps."""
        return max(self.total_ms - self.gpu_ms, 0.0)

    @property
    def gpu_ms(self) -> float:
        return sum(v for k, v in self.steps_ms.items() if k in GPU_STEPS)


class _Timer:
    def __init__(self, out: dict, name: str):
        self.out, self.name = out, name

    def __enter__(self):
        self.t0 = time.perf_counter()

    def __exit__(self, *exc):
        self.out[self.name] = self.out.get(self.name, 0.0) + (time.perf_counter() - self.t0) * 1e3


@dataclass(frozen=True)
class LiveStats:
    """What the sidebar shows for one view: the last redraw and the worker's record."""

    draw: DrawStats
    worker: WorkerStats
    error: str | None


def status_line(published) -> str:
    """The status bar's text for the worker's latest `Published` record ("" before the first)."""
    if published is None:
        return ""
    s = published.stats
    state = "converged" if s.idle else f"converging {s.converged:.0%}"
    return f"{state} | {s.visible_cells} cells | {s.updates_per_s:.0f} updates/s | {s.rays_per_s / 1e6:.1f} Mrays/s"

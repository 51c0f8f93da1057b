"""The records the viewport's main thread and its worker exchange: scene edits and view requests
in, immutable published results out (`worker.py` runs the worker).

Pure numpy dataclasses: nothing here imports bpy, gpu or mathutils, and every array a `Published`
record holds is a copy marked read-only, so either thread may read it while the other goes on.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType

import numpy as np

# --- what the main thread posts -----------------------------------------------------------------


@dataclass(frozen=True)
class FullScene:
    """A whole new snapshot (first sync, objects added or deleted, meshes edited)."""

    snapshot: object  # SceneSnapshot


@dataclass(frozen=True)
class MoveVertices:
    """New world positions and normals of some vertices of the current snapshot (objects moved).

    indices : (k,) int64 rows of geometry.positions; positions, normals : (k, 3) float32
    """

    indices: np.ndarray
    positions: np.ndarray
    normals: np.ndarray


@dataclass(frozen=True)
class SetShading:
    """Replaced lamps, world or materials (None keeps the current ones); geometry unchanged."""

    lights: list | None = None
    world: object | None = None
    materials: list | None = None


@dataclass(frozen=True)
class ViewRequest:
    """One frame's G-buffer read-backs to light, rows bottom-up.

    key : identifies the camera, size and scene geometry of the frame; echoed by `ViewResult`
    position, normal : (h, w, 4) float32 at the GI resolution (world position with w = 1 on
        geometry; unit normal): visible cells and corner visibility
    direct_position, direct_normal : the same at the direct light's resolution (may be the same arrays)
    view, proj : (4, 4) float64 camera of the frame (the main thread reprojects results with them)
    material : (h, w) float32 G-buffer material index + 1 at the GI pixels (the glossy lobes'
        materials: the glossy light is made there), or None: no glossy light
    """

    key: tuple
    position: np.ndarray
    normal: np.ndarray
    direct_position: np.ndarray
    direct_normal: np.ndarray
    view: np.ndarray
    proj: np.ndarray
    debug_cells: bool = False  # also colour the GI pixels by cache cell (the Cache Cells view)
    material: np.ndarray | None = None
    #: Resolve the pixel rays' GI at every pixel of direct_position (the full-res G-buffer), as
    #: final renders do with Full-Res GI (`pixel_gather.full_res_resolve`); else the GI
    #: resolution's textures, which the bilateral pass upsamples
    full_res: bool = False
    #: The G-buffer's material texels (h, w) and diffuse albedo (h, w, 4) at the direct light's
    #: resolution, with the final render's lamp samples and reflection rays: a still view takes
    #: the final render's glossy light at every pixel once its pixel rays are traced
    #: (`glossy_image.frame_glossy`); None / 0: the GI pixels' glossy light alone.
    full_material: np.ndarray | None = None
    full_albedo: np.ndarray | None = None
    #: (h, w) the emission target's alpha at every pixel where a textured metal is in the scene:
    #: with the albedo's alpha, its texels' coordinates (`glossy.metal_tint_basis`); else None
    full_tint: np.ndarray | None = None
    #: The material texels (h, w) at the direct light's resolution in a scene with a Translucent
    #: BSDF (its pixels take the lamps' light on their back too: `translucent.mix_back`); None
    #: without one (`material` serves the GI pixels' coarse passes)
    direct_material: np.ndarray | None = None
    glossy_samples: int = 0
    reflection_rays: int = 0
    #: (K, 2) pixel offsets of the jittered subframes the draw accumulates while the view holds
    #: still (`viewport_aa`), or None: the worker traces the lamps' light at its light edges for
    #: each of them (`EdgeLight`)
    aa_offsets: np.ndarray | None = None


@dataclass(frozen=True)
class EdgeLight:
    """The lamps' light of a still view's jittered subframes where a pixel's light or surface
    changes within it (`ViewportWorker._edge_pass`): pix (m,) int32 flat pixel indices of the
    direct light's resolution (rows bottom-up); for each of the K subframes (`offsets` (K, 2)
    pixel offsets) what its ray through the pixel meets, point (K, m, 3) and unit normal
    (K, m, 3) (zero where it meets nothing), and the lamps' light there, light (K, m, 3) W/m^2."""

    pix: np.ndarray
    light: np.ndarray
    point: np.ndarray
    normal: np.ndarray
    offsets: np.ndarray


@dataclass(frozen=True)
class WorkerOptions:
    solver_batches: int = 2  # batches of rays_per_cell directions per cell the cache refines to
    # while the scene holds still (the first converged image comes from one; `worker_solve.py`)
    first_batch_rays: int | None = 32  # directions per cell of that first batch (at most
    # rays_per_cell; None: rays_per_cell): half the rays and iterations half as costly before the
    # first converged image, which the full batches that follow refine
    direct_samples: int = 1  # shadow-ray samples per pixel and lamp in each direct-light pass
    direct_passes: int = 16  # passes averaged while the view stays still (soft shadows converge)
    # Shadow rays per pixel and lamp of a still view's full-resolution passes, traced as final
    # renders trace theirs (`penumbra.adaptive_direct`: FIRST_SAMPLES everywhere, which the ratio
    # estimator makes exact where a lamp is wholly seen, this many more in penumbrae, filtered
    # there); 0: passes of `direct_samples` rays like the coarse one (Cornell 640x360, 16 such
    # passes: Diffuse Direct 0.029 off Cycles away from edges, 0.0022 for the final render's)
    fine_samples: int = 16
    glossy_passes: int = 16  # passes of the lamps' glossy light (`direct_samples` rays each)
    # Rays of a new view's first, coarse direct pass (at the GI pixels) as a share of one pass at
    # the direct light's resolution (more samples per pixel on fewer pixels; 1 to 16 samples)
    coarse_share: float = 1.0
    # Per-pixel final-gather rays per GI pixel and pass once the cache is done and the view holds
    # still (0: off), and the passes averaged (their frames differ): final renders' default is 32
    # rays, which cut Cornell's Combined error 0.0337 -> 0.0286 (one pass costs about as much as
    # the cache's first batch; 8 rays cost nearly as much as 32: its fixed parts dominate).
    pixel_rays: int = 32
    pixel_passes: int = 2


# --- what the worker publishes ------------------------------------------------------------------


@dataclass(frozen=True)
class CacheFrame:
    """The cache as GPU texture data (`raster.gather.pack_cache` layout), packed by the worker."""

    serial: int
    grid: object  # CacheGrid
    settings: object  # CacheSettings
    sh_texels: np.ndarray
    depth_texels: np.ndarray | None  # None: not packed (a still view with its corner mask reads none)


@dataclass(frozen=True)
class PendingGI:
    """A still view's first pixel pass, its rays in and not yet resolved by the worker: what
    `pixel_gather.full_res_preview` resolves it from (the main thread, with the GPU's filter and
    upsample passes). Why: the worker's numpy resolve (filter, interpolation, detail pixels) takes
    0.3-0.4 s of 2 busy cores at 640x360, a GPU's filter and interpolation a millisecond; the
    view shows the rays' light as soon as they are in while the worker finishes the resolve.

    serial : unique per pass (the draw resolves each once); gi : the pass's `PixelGI` (a copy:
    never written again); position_lo : the request's GI-resolution positions; pix, points,
    normals : the GI pixels; full : (points, normals, flat pixels) of the direct-resolution
    G-buffer, full_shape its (h, w); passes, plane_sigma, normal_power : the filter's settings."""

    serial: int
    gi: object
    position_lo: np.ndarray
    pix: np.ndarray
    points: np.ndarray
    normals: np.ndarray
    view: np.ndarray
    full: tuple
    full_shape: tuple
    passes: int
    plane_sigma: float
    normal_power: float


@dataclass(frozen=True)
class ViewResult:
    """Light of one `ViewRequest`: arrays float32, rows bottom-up like the request.

    direct : (h, w, 4) at the direct resolution, rgb = lamp irradiance W/m^2 (mean over `passes`
        passes), a = 1 where computed; position, normal : the request's direct-resolution arrays
    corner_mask : (h_gi, w_gi) float32 bit masks of the visible neighbour cells, None until traced
    cells : (h_gi, w_gi, 4) `visible.cell_debug_colors` of the GI pixels (a = 1 on geometry) when
        the request asked for them, with gi_position, gi_normal: the request's GI-resolution arrays
    scene_gen : the scene edits the light was traced with
    """

    key: tuple
    serial: int
    scene_gen: int
    position: np.ndarray
    normal: np.ndarray
    view: np.ndarray
    proj: np.ndarray
    direct: np.ndarray
    passes: int
    corner_mask: np.ndarray | None = None
    cells: np.ndarray | None = None
    gi_position: np.ndarray | None = None
    gi_normal: np.ndarray | None = None
    #: Per-pixel final gather of a still view once the cache is done (`pixel_gather.gi_images`,
    #: the mean over `pixel_passes` passes): (h_gi, w_gi, 4) rgb indirect + a AO and rgb
    #: sky/emitter irradiance, the textures that replace the gather and SSAO; None until traced.
    #: At the direct light's resolution instead (h, w, 4) when the request asked for `full_res`.
    gi_indirect: np.ndarray | None = None
    gi_direct: np.ndarray | None = None
    pixel_passes: int = 0
    #: The first pixel pass's rays before the worker has resolved them (gi_indirect is None
    #: then): the draw resolves them itself (`PendingGI`).
    gi_pending: PendingGI | None = None
    #: The glossy layers' light towards this view's camera (`glossy_image`: the lamps' part, the
    #: mean of `glossy_passes` passes by their samples, plus the cache's split-sum part): (h, w, 4) rgb radiance
    #: added to Combined, a = 1 where computed, at glossy_position / glossy_normal (the request's
    #: GI-resolution arrays: a highlight is smooth at the pixel scale; the direct light's once a
    #: still view has the final render's glossy light, `glossy_image.frame_glossy`); None when no
    #: material has a glossy layer.
    glossy: np.ndarray | None = None
    glossy_position: np.ndarray | None = None
    glossy_normal: np.ndarray | None = None
    glossy_passes: int = 0
    #: The lamps' light of the jittered subframes at the light edges (`EdgeLight`), or None
    edges: EdgeLight | None = None


@dataclass(frozen=True)
class WorkerStats:
    updates: int = 0  # solver steps (a traced batch, a re-solve, an iteration) since the worker started
    updates_per_s: float = 0.0  # over the last RATE_WINDOW_S
    rays_per_s: float = 0.0  # probe, shadow and visibility rays over the last RATE_WINDOW_S
    visible_cells: int = 0
    converged: float = 0.0  # share of the visible cells that settled since the last change
    steps_ms: Mapping[str, float] = field(default_factory=lambda: MappingProxyType({}))
    scene_gen: int = 0  # edits applied so far (compare with `post_edit`'s return value)
    idle: bool = False


@dataclass(frozen=True)
class Published:
    cache: CacheFrame | None = None
    view: ViewResult | None = None
    stats: WorkerStats = WorkerStats()
    empty: bool = False  # the scene has no geometry (the world alone is drawn)
    error: str | None = None  # the worker stopped on this error


def frozen(array: np.ndarray) -> np.ndarray:
    """`array`, made read-only: what the worker publishes is never written again."""
    array.flags.writeable = False
    return array

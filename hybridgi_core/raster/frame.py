"""The seed's nine steps for one view: every raster pass plus the CPU cache work between them.

Shared by final renders and the viewport: both hand in a `GISystem` (the cache lives in world
space and outlives views) and camera matrices, and read back a `ShadedFrame`.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from concurrent import futures
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass, field

import numpy as np

from .. import glossy_image, glossy_ltc, pixel_gather, refraction
from .. import translucent as translucent_mod
from ..camera import camera_position
from ..catcher import CatcherPixels
from ..emitters import emitter_samples, worth_sampling
from ..evaluate import HitLookup
from ..lights import RATIO_MIN_SAMPLES, one_sample_exact_lamps, rough_lights
from ..penumbra import FIRST_SAMPLES as PENUMBRA_FIRST_SAMPLES
from ..penumbra import adaptive_direct, filter_camera, filter_emitter_light
from ..sampling import frame_rng
from ..screen_light import ScreenLight
from ..settings import MULTI_BOUNCE
from ..system import UPDATES_PER_BATCH
from ..visible import pixels_to_points
from . import film_resolve, thread_cpu
from .accumulate import AccumulatePass
from .atrous import AtrousPass
from .bilateral import BilateralPass
from .deferred import DeferredPass, ShadedFrame
from .downsample import DownsamplePass
from .gather import GatherPass, gather_levels
from .gbuffer import GBufferPass, camera_eye, catcher_mask
from .lens import SHARP_COC_PX, Lens, centre_offsets, coc_pixels, focus_offset, lens_points, lens_view, subframes_for
from .passes import low_res_size
from .readback import upload_texture_2d
from .reused_light import filter_on_surface, reuse_taps
from .settings import DEBUG_FINAL, RasterSettings
from .ssao import SSAOPass
from .subframe_glossy import subframe_glossy
from .subpixel import (
    CentreSample,
    FilmAccumulator,
    compared_normal,
    gi_edges,
    jittered_projection,
    reconstruction_taps,
    subframe_direct,
    subframe_gi,
    subframe_surfaces,
    subframe_texture_filter,
    subpixel_offsets,
    worth_extra,
)
from .upsample import UpsamplePass
from .world_background import WorldTexture

log = logging.getLogger(__name__)

#: Subframe s of a frame seeds its shadow rays with frame + s * this: other samples in every
#: subframe, subframe 0 those of a frame without subframes.
SUBFRAME_SEED_STRIDE = 1 << 24
#: Most lamps whose shares of the centre's light the subframes keep (h x w x lamps x 3 floats) to
#: trace again only the lamps whose light edge crosses a pixel (`subpixel.lamp_edges`); more
#: lamps trace every lamp at every light edge, as one lamp does.
SUBFRAME_LAMP_LIMIT = 8


#: Subframes a frame adds when thin surfaces of far other bounce light cover a share of its
#: image (`FramePipeline._subframe_count`): 8 + 24, Pixel Samples = 32 for that frame.
EXTRA_SUBFRAMES = 24
#: At most this many extra subframes per subframe of the frame's own: a frame of 2 Pixel Samples
#: took 24 more wherever its GI edges passed the share (26 subframes: 13x its raster passes and
#: subframe shadow rays), where its own noise left their gain unseen; 8 Pixel Samples keep all 24.
EXTRA_PER_SUBFRAME = 3


def subframe_dither(index: int) -> float:
    """Subframe `index`'s offset of the G-buffer's coverage thresholds (`GBufferPass.execute`'s
    dither): the golden ratio's multiples, so the centre raster (0) and any run of subframes
    spread over [0, 1) and a pixel sees a surface of coverage c in about c of its samples."""
    return float(((index + 1) * 0.6180339887498949) % 1.0)


#: Steps of a final render's steps_ms that are GPU work (llvmpipe here, milliseconds on a GPU):
#: the render targets' allocation (`addon/pipeline.py`), the G-buffer, downsample (+ its
#: read-back), gather (+ the cache texture's upload), SSAO, bilateral, deferred, the film's
#: accumulation and its resolve, the pixel rays' and glossy light's a-trous filters and full-res
#: interpolation (each + its upload and read-back). The benchmark's seconds without GPU passes subtract them.
GPU_PASS_STEPS = ("targets", "gbuffer", "downsample", "gather", "ssao", "bilateral", "deferred", "accumulate",
                  "atrous", "upsample", "film_resolve")


@dataclass
class FrameStats:
    steps_ms: dict[str, float] = field(default_factory=dict)
    visible_cells: int = 0
    rays: int = 0
    low_res: tuple[int, int] = (0, 0)
    detail_pixels: int = 0  # full-res pixels that traced their own pixel rays (`_pixel_gi_full`)
    extra_pixels: int = 0  # centre GI edge pixels that made the frame take extra subframes (`_subframe_count`)
    subframes: int = 1  # jittered subframes the frame took (`_subframe_count`)

    @contextmanager
    def step(self, name: str):
        """Time a step into steps_ms[name]; a GPU pass (GPU_PASS_STEPS) also counts the worker
        threads' CPU time beside it (`thread_cpu`)."""
        t0 = time.perf_counter()
        try:
            with self._beside_gpu() if name in GPU_PASS_STEPS else nullcontext():
                yield
        finally:
            self.steps_ms[name] = self.steps_ms.get(name, 0.0) + (time.perf_counter() - t0) * 1e3

    def gpu_pass(self, fn):
        """`fn` (a GPU pass whose time another step records) wrapped so that the worker threads'
        CPU time during its calls counts as `step`'s GPU passes count theirs."""
        def run(*args, **kwargs):
            with self._beside_gpu():
                return fn(*args, **kwargs)
        return run

    @contextmanager
    def _beside_gpu(self):
        """Add the worker threads' CPU milliseconds while the block runs to GPU_OVERLAP_STEP."""
        others = thread_cpu.other_threads_ns()
        try:
            yield
        finally:
            key = thread_cpu.GPU_OVERLAP_STEP
            self.steps_ms[key] = self.steps_ms.get(key, 0.0) + thread_cpu.cpu_ms_since(others)


@dataclass
class CentreLight:
    """`FramePipeline._centre_direct`'s result: direct (h w, 4) the lamp light, lamp_light (h w,
    lamps, 3) each lamp's share or None, screen the pixel rays' ScreenLight, the geometry pixels'
    points, normals, flat pix and smooth normals (None without normal maps), ms its wall time."""

    direct: np.ndarray
    lamp_light: np.ndarray | None
    screen: ScreenLight
    points: np.ndarray
    normals: np.ndarray
    pix: np.ndarray
    smooth: np.ndarray | None
    ms: float
    #: (n, lamps) float32 each lamp's visibility at the points (`glossy_ltc.visibility`; NaN
    #: unknown), or None: the glossy lobes' closed-form area-lamp light is shadowed by it.
    visibility: np.ndarray | None = None
    #: (h w, 3) float32 the emitters' filtered share of `direct` (`penumbra.filter_emitter_light`),
    #: or None: subframes keep it on the centre's surface (`subpixel.CentreSample.emitter`).
    emitter: np.ndarray | None = None


#: Fewest shadow rays per lamp a jittered subframe traces at a pixel that sees another surface
#: than the centre's (the shadow samples are split over the subframes, down to this): as many as
#: the centre's first pass (`penumbra.FIRST_SAMPLES`). Why: on fine geometry those pixels are many
#: (the dragon's scales), and 4 rays each (24 shadow samples over 8 subframes) left their Diffuse
#: Direct noisier than one filtered sample: dragon_npm 640x360, r40 rung Combined 0.0510 -> 0.0491
#: (r32's 0.0490 had been better), default 0.0454 -> 0.0447, bunny 0.0237 -> 0.0233 at r40; the
#: seconds within the runs' spread.
SUBFRAME_MIN_SAMPLES = PENUMBRA_FIRST_SAMPLES


def subframe_shadow_samples(direct_samples: int, base: int, count: int) -> int:
    """Shadow rays per lamp a jittered subframe traces at a pixel it lights afresh, when the frame
    takes `count` subframes for `base` Pixel Samples: the shadow samples split over the subframes,
    at least SUBFRAME_MIN_SAMPLES over the first `base` of them, that floor's total spread over all
    of them when the frame adds more (GI edges' extra subframes, lens points). Why: 24 extra
    subframes each kept the floor, 4x the rays of the frame's own subframes; alpha-cut leaves
    under a sun (their dappled shadows relit at most pixels) spent 1.9 s of a 5.0-s 320x180 render
    there."""
    floor = min(int(direct_samples), SUBFRAME_MIN_SAMPLES)
    if count > base > 0:
        floor = max(1, -(-floor * base // count))
    return max(floor, int(direct_samples) // max(count, 1))


def catcher_pixels(position: np.ndarray, normal: np.ndarray) -> CatcherPixels | None:
    """The centre raster's shadow-catcher pixels (`gbuffer.catcher_mask`) with their points and
    smooth normals, or None where it sees none."""
    mask = catcher_mask(position).reshape(-1)
    if not mask.any():
        return None
    pix = np.flatnonzero(mask)
    pos = np.asarray(position, np.float32).reshape(-1, 4)
    nrm = np.asarray(normal, np.float32).reshape(pos.shape[0], -1)[:, :3]
    return CatcherPixels(pix, np.ascontiguousarray(pos[pix, :3]), np.ascontiguousarray(nrm[pix]))


class FramePipeline:
    """Owns the passes of one view; `resize`, `upload`, then `render` per frame; `free` at the end.

    `render` runs the CPU steps in line (final renders). The viewport splits a frame into its GPU
    halves, `rasterize` (steps 1-2) and `shade` (steps 6-9), and runs the CPU steps on a worker
    thread in between, a frame or more behind.
    """

    def __init__(self, settings: RasterSettings | None = None, direct_samples: int = 48,
                 gather: GatherPass | None = None, subframes: int = 1, filter_size: float = 1.5,
                 filter_type: str = "BLACKMAN_HARRIS", glossy_samples: int = 32,
                 extra_subframes: int = EXTRA_SUBFRAMES, lens: Lens | None = None):
        """gather : a GatherPass (subclass) to use instead of a plain one; the viewport's takes
        cache textures its worker thread packed.
        subframes : jittered subframes per `render` (the pixel filter, `subpixel.py`); 1 = one
            sample at each pixel centre.
        filter_size, filter_type : the pixel filter, as Cycles' Filter Width (pixels) and type.
        glossy_samples : lamp samples per pixel and lamp of the glossy lobes where a first pass
            finds the highlight noisy (`glossy_noise`; filtered where the lobe is rough,
            `reflection.filter_lamp_glossy`).
        extra_subframes : subframes a frame adds where thin surfaces need them (`_subframe_count`).
        lens : the camera's thin lens (`lens.py`): depth of field, each subframe through its own
            lens point (at least `lens.MIN_SUBFRAMES` of them when subframes > 1); None: a pinhole."""
        self.settings = settings or RasterSettings()
        #: Shadow-ray samples per pixel and lamp for the full-res direct light in penumbrae (the
        #: rest of the image traces `penumbra.FIRST_SAMPLES`): soft shadows of area lights and suns
        #: are visible noise at 1 sample; the viewport may use fewer. `render` splits them over its
        #: subframes (the filter averages them anyway). 16 -> 48: Cornell Diffuse Direct 0.0030 ->
        #: 0.0025 at +0.05 s, the Stanford dragon's self-shadowed belly 0.043 -> 0.035.
        self.direct_samples = direct_samples
        self.glossy_samples = glossy_samples
        if int(subframes) < 1:
            raise ValueError(f"subframes must be >= 1, got {subframes}")
        self.subframes = int(subframes)
        self.filter_size = float(filter_size)
        self.filter_type = filter_type
        #: More subframes for a frame whose thin surfaces of far other bounce light than what lies
        #: behind them cover a share of the image (`_subframe_count`); 0 = never.
        self.extra_subframes = int(extra_subframes)
        self.lens = lens if lens is not None and lens.active else None
        #: The last `render`'s passes, filtered over its subframes (FilmAccumulator).
        self.film = None
        #: The last `render`'s centre pixels that see a shadow catcher (`catcher.CatcherPixels`), or None.
        self.catchers = None
        self.gbuffer = GBufferPass()
        self.downsample = DownsamplePass(self.settings.downsample)
        self.gather = gather if gather is not None else GatherPass()
        self.ssao = SSAOPass(self.settings)
        self.bilateral = BilateralPass(self.settings)
        self.deferred = DeferredPass(self.settings)
        self.accumulate = AccumulatePass()
        #: The world map the background shows (`set_world`).
        self.world = WorldTexture()
        #: The pixel rays' edge-aware filter at the GI resolution (`pixel_gather.filter_residual`
        #: on the GPU; sized on use).
        self.atrous = AtrousPass()
        #: Their full-res interpolation (`pixel_gather.upsample_full` on the GPU; sized on use).
        self.upsample = UpsamplePass()
        #: The glossy light's edge-aware filters over the full-res image (`glossy_image.finish_glossy`
        #: through `pixel_gather.filter_at_pixels`: the same a-trous pass at the full resolution).
        self.glossy_atrous = AtrousPass()
        #: The film's pixel filter and divisions over the accumulated sums (sized on use).
        self.film_resolve = film_resolve.FilmResolvePass()
        self._passes = (self.gbuffer, self.downsample, self.gather, self.ssao, self.bilateral, self.deferred,
                        self.accumulate, self.atrous, self.upsample, self.glossy_atrous, self.film_resolve)
        #: Final renders with pixel rays resolve the GI at full resolution on the CPU
        #: (`pixel_gather.full_res_images`): a copy of the centre raster's G-buffer (the guide of
        #: those full-res GI samples, as the downsampled G-buffer guides the low-res ones; the
        #: subframes overwrite the G-buffer) and a factor-1 bilateral pass. Made on first use.
        self._full_copy = None
        self._bilateral_full = None
        self.width = self.height = 0
        self._direct_tex = None
        self._glossy_tex = None
        self._glossy_total = None  # (h w, 4) float32 what _glossy_tex holds, for the subframes' remap
        #: The stage thread (`_stage_thread`), made on first use.
        self._stage = None

    def resize(self, width: int, height: int) -> None:
        if (width, height) == (self.width, self.height):
            return
        low = low_res_size(width, height, self.settings.downsample)
        for p in (self.gbuffer, self.downsample, self.bilateral, self.deferred, self.accumulate):
            p.resize(width, height)
        for p in (self.gather, self.ssao):  # these run at the GI resolution
            p.resize(*low)
        self.width, self.height = width, height

    def set_settings(self, settings: RasterSettings) -> bool:
        """Take new settings in place when the targets can stay (SSAO, blend, bilateral values);
        False when they cannot (another downsample factor): build a new pipeline then."""
        if settings.downsample != self.settings.downsample:
            return False
        self.settings = settings
        for p in (self.ssao, self.bilateral, self.deferred):
            p.settings = settings
        return True

    def upload(self, snapshot) -> None:
        """Geometry and materials for the G-buffer (once per scene change)."""
        self.gbuffer.upload(snapshot)

    def free(self) -> None:
        for p in self._passes + tuple(p for p in (self._full_copy, self._bilateral_full) if p is not None):
            p.free()
        if self._stage is not None:
            self._stage.shutdown(wait=True)
            self._stage = None
        self.world.free()
        self._direct_tex = None
        self.width = self.height = 0

    def rasterize(self, view: np.ndarray, proj: np.ndarray, stats: FrameStats | None = None):
        """Steps 1-2 on the GPU: the G-buffer and its downsampled copy -> (GBuffer, LowResGBuffer)."""
        stats = stats if stats is not None else FrameStats()
        with stats.step("gbuffer"):
            gbuf = self.gbuffer.execute(view, proj)
        with stats.step("downsample"):
            low = self.downsample.execute(gbuf)
        stats.low_res = (self.downsample.low_width, self.downsample.low_height)
        return gbuf, low

    def set_world(self, world) -> None:
        """The world the background shows (a snapshot `World`): its map once uploaded
        (`world_background.WorldTexture`; kept while the same map comes back), else the
        `world_color` each `shade` is given."""
        self.world.update(getattr(world, "background_map", None))

    def shade(self, gbuf, low, view: np.ndarray, proj: np.ndarray, direct, corner_visible=None,
              irradiance=None, debug_view: int = DEBUG_FINAL, world_color=(0.0, 0.0, 0.0),
              stats: FrameStats | None = None, gi=None, glossy=None, bilateral=None,
              camera_proj: np.ndarray | None = None) -> ShadedFrame:
        """Steps 6-9 on the GPU, the cache already uploaded (`self.gather.upload`).

        direct : full-res RGBA texture of lamp irradiance (W/m^2) at the G-buffer's pixels
        corner_visible : None (Chebyshev test), (h, w, 8) bool or an R32F bit-mask texture at the
            low resolution (see GatherPass.execute)
        irradiance : low-res RGBA texture of the light the near-field bounce reflects, or None
        gi : (gi_indirect, gi_direct, ssao) low-res textures that replace the gather and the
            screen-space pass (pixel rays: `_pixel_gi`)
        glossy : full-res RGBA texture of the lamps' glossy reflection (radiance, added to
            Combined), or None
        bilateral : the BilateralPass to use (of `low`'s factor); None = the pipeline's own
        camera_proj : the projection `gbuf` was drawn with, where it differs from `proj` (a jittered
            subframe's): the background map is looked up along its pixels' rays (`set_world`)
        """
        stats = stats if stats is not None else FrameStats()
        if gi is not None:
            gi_indirect, gi_direct, ssao = gi
        else:
            with stats.step("gather"):
                gi_indirect, gi_direct = self.gather.execute(low, corner_visible=corner_visible,
                                                             surfaces=self.gbuffer.bends_normals)
            with stats.step("ssao"):
                ssao = self.ssao.execute(low, view, proj, irradiance=irradiance, surfaces=self.gbuffer.bends_normals)
        with stats.step("bilateral"):
            filtered = (bilateral or self.bilateral).execute(gbuf, low, gi_indirect, gi_direct, ssao)
        with stats.step("deferred"):
            shaded = self.deferred.execute(gbuf, direct, filtered, world_color=world_color,
                                           debug_view=debug_view, relative_bounce=self.ssao.relative_bounce,
                                           glossy=glossy, world=self.world,
                                           camera=(view, proj if camera_proj is None else camera_proj))
        return shaded

    def render(self, system, view: np.ndarray, proj: np.ndarray, frame: int, warmup: int = 0,
               update: bool = True, debug_view: int = DEBUG_FINAL, world_color=(0.0, 0.0, 0.0),
               progress=None, update_hook=None) -> tuple[ShadedFrame, FrameStats]:
        """Steps 1-9. warmup > 0 converges the cache first (final renders); update = False only
        reads the cache (a redraw while a worker owns the updates). progress(i, n) is called
        after each warm-up iteration and may raise to cancel. update_hook(cells) -> UpdateStats
        replaces the frame's `system.update(cells, frame)` of the visible cells (an incremental
        render refreshes what changed around them too, with its own rays)."""
        stats = FrameStats()
        if warmup > 0 or update:
            # The cells this camera sees are its open space, whatever the faces around them say
            # (`open_space.py`: a room modelled with its normals facing out).
            system.viewpoint = camera_position(view)
        gbuf, low = self.rasterize(view, proj, stats)
        with stats.step("downsample"):
            normal_lo, position_lo = self.downsample.read_normal_position()
            points, normals, pix = pixels_to_points(position_lo, normal_lo)
        with stats.step("select"):
            cells = system.visible_cells(points, normals)
        stats.visible_cells = int(cells.size)
        with stats.step("gbuffer"):  # the full-res read-back, as the subframes count theirs
            normal = self.gbuffer.read("normal")
            position = self.gbuffer.read("position")
            # The smooth surface under normal maps (`normal` itself where none bends it).
            surface = self.gbuffer.read_surface(normal)
            translucent = self._translucent_shares(system)
            self.catchers = catcher_pixels(position, surface)
        # The centre's lamp light needs the full-res G-buffer only, not the cache: it runs on a
        # thread of its own while this one updates the cache, so that the serial parts of each
        # overlap the other's work on the pool. Only CPU steps run beside it (no GPU pass before
        # the wait): the seconds without the GPU passes count all of it.
        full = pixels_to_points(position, normal)  # (points, normals, flat pixels) of the full-res G-buffer
        full_smooth = None if surface is normal else pixels_to_points(position, surface)[1]
        pending = self._stage_thread().submit(self._centre_direct, system, view, proj, frame, (*full, full_smooth),
                                              translucent)
        begun = None
        try:
            try:
                visible = self._update_cache(system, points, normals, cells, view, frame, warmup, update, stats,
                                             progress, update_hook)
                # The pixel rays' first half (their cache gather and traced rays) trickles to the pool
                # now: it needs the cache, not the centre's lamp light, which may still run
                # (morse_apartment r32: 0.13 s more than the cache update; the frame -0.07 s of
                # 1.37); their shading waits for it.
                lookup = self._frame_lookup(system)
                if self.settings.pixel_rays > 0 and self.settings.downsample > 1 and self.settings.pixel_full_res:
                    with stats.step("pixel_rays"):
                        begun = pixel_gather.begin_full_res(
                            system, position_lo, pix, points, normals, visible, frame, self.settings.pixel_rays,
                            full[0], full[2], (self.width, self.height), full_smooth, lookup, trickle=True)
            finally:
                with stats.step("direct_wait"):
                    futures.wait([pending])  # nothing of this frame runs on after it is abandoned
            return self._render_rest(system, view, proj, frame, stats, gbuf, low, position_lo, normal_lo, points,
                                     normals, pix, position, normal, surface, visible, pending.result(), lookup,
                                     begun, debug_view, world_color)
        finally:
            if begun is not None:
                begun.flush()
                futures.wait(begun.jobs)  # (done by then unless the frame was abandoned)

    def _render_rest(self, system, view, proj, frame, stats, gbuf, low, position_lo, normal_lo, points, normals,
                     pix, position, normal, surface, visible, centre_light, lookup, begun, debug_view,
                     world_color) -> tuple[ShadedFrame, FrameStats]:
        """`render` once the cache and the centre's lamp light are ready: the glossy light, the
        pixel rays' shading and resolve, the subframes, the film."""
        stats.steps_ms["direct"] = stats.steps_ms.get("direct", 0.0) + centre_light.ms
        direct, lamp_light, screen = centre_light.direct, centre_light.lamp_light, centre_light.screen
        p_full, n_full, pix_full, s_full = centre_light.points, centre_light.normals, centre_light.pix, centre_light.smooth
        gi = None
        gi_low, gi_bilateral, full_gi = low, None, None
        # The glossy light needs the cache and the lamp light, not the pixel rays: it runs on the
        # stage thread while this one traces them (both on the pool), as the lamp light ran
        # beside the cache update; both read one HitLookup of the cache.
        glossy_job = self._start_glossy(system, view, proj, p_full, n_full, pix_full, frame, lookup,
                                        direct[pix_full, :3], centre_light.visibility, screen)
        try:
            if self.settings.pixel_rays > 0:
                with stats.step("pixel_rays"):
                    if self.settings.downsample > 1 and self.settings.pixel_full_res:
                        gi, gi_low, gi_bilateral, full_gi = self._pixel_gi_full(
                            system, gbuf, position_lo, normal_lo, pix, points, normals, visible, view, frame,
                            (p_full, n_full, pix_full), stats, screen, s_full, lookup, begun)
                    else:
                        gi = self._pixel_gi(system, position_lo, normal_lo, pix, points, normals, visible, view,
                                            frame, stats, screen)
        finally:
            if glossy_job is not None:
                with stats.step("glossy_wait"):
                    futures.wait([glossy_job])  # nothing of this frame runs on after it is abandoned
        with stats.step("gather"):
            mask = np.zeros((low.height * low.width, 8), bool)
            mask[pix] = visible[:, :8]
            if gi is None:
                self.gather.upload(system.cache)
        with stats.step("direct_low"):
            # Lamp light at the low-res pixels: what the SSAO pass's near-field bounce reflects
            # (the far-field bounce of the cache's light is already in the gathered indirect).
            lit_tex = None
            if gi is None:
                lit = np.zeros((low.height * low.width, 4), np.float32)
                lit[pix, :3] = system.direct(points, normals, frame, samples=1)
                lit_tex = upload_texture_2d(lit.reshape(low.height, low.width, 4), "RGBA16F")
        if gi is None and getattr(system, "levels", None) is not None:
            with stats.step("gather"):
                gi = self._gather_levels(system.levels, low, points, normals, pix, visible, view, proj, lit_tex)
        glossy, glossy_col, glossy_ind = self._finish_glossy(glossy_job, pix_full, stats)
        film = FilmAccumulator()
        film.set_depth(self.gbuffer.read("depth"))  # the centre sample, as Cycles' one sample
        count = self.subframes
        lens = self.lens if count > 1 else None
        if count > 1:
            centre = CentreSample.from_gbuffer(direct, position, normal, film.read("depth"), surface=surface,
                                               lamp_light=lamp_light, emitter=centre_light.emitter)
            coc = coc_pixels(lens, proj, film.read("depth"), self.width) if lens is not None else 0.0
            if coc < SHARP_COC_PX:
                lens = None  # nothing it sees blurs visibly: the pinhole's subframes
            count = self._subframe_count(centre, full_gi, stats, subframes_for(lens, count, coc))
        stats.subframes = count
        offsets = subpixel_offsets(count, self.filter_size, self.filter_type)
        jittered = offsets.shape[0] > 1
        reused = None
        if jittered:
            texture_filter = subframe_texture_filter(offsets.shape[0], self.filter_size)
            # The reused light's filter (numpy, ~25 ms at 640x360) beside the first subframe's raster.
            reused = self._stage_thread().submit(self._reused_centre, centre, offsets.shape[0])
        apertures = lens_points(offsets.shape[0], lens) if lens is not None and jittered else None
        camera_proj, sub_view = proj, view
        for s, offset in enumerate(offsets):
            sub_glossy = self._glossy_tex if glossy is not None else None
            if jittered:
                with stats.step("gbuffer"):  # the raster and its read-back, as "downsample" counts its own
                    shift, at = offset, offset
                    if apertures is not None:
                        # This subframe's eye at its lens point, the plane of focus kept in place.
                        sub_view = lens_view(view, apertures[s])
                        shift = offset + focus_offset(proj, apertures[s], lens, self.width, self.height)
                        at = self._centre_locator(view, proj)
                    camera_proj = jittered_projection(proj, shift, self.width, self.height)
                    gbuf = self.gbuffer.execute(sub_view, camera_proj, texture_filter=texture_filter,
                                                dither=subframe_dither(s))
                    normal = self.gbuffer.read("normal")
                    position = self.gbuffer.read("position")
                    surface = self.gbuffer.read_surface(normal)
                    translucent = self._translucent_shares(system)
                with stats.step("direct"):
                    hit, same = subframe_surfaces(centre, position, normal, surface)
                if glossy is not None:
                    sub_glossy = self._subframe_glossy(centre, hit, same, position, normal, surface, stats)
                # The subframe's GI resolve (numpy, mostly one core) runs on the stage thread beside
                # its direct light (shadow rays on the pool), as the centre's light runs beside the
                # cache update.
                gi_job = None
                if full_gi is not None and full_gi.resolver is not None:
                    gi_job = self._stage_thread().submit(
                        subframe_gi, full_gi.resolver, full_gi.indirect, full_gi.direct, hit, same, position,
                        normal, at, frame + s * SUBFRAME_SEED_STRIDE,
                        max(RATIO_MIN_SAMPLES, self.settings.pixel_rays // offsets.shape[0]), surface=surface)
                try:
                    with stats.step("direct"):
                        if reused is not None:
                            centre, reused = reused.result(), None
                        direct = subframe_direct(system, centre, position, normal,
                                                 frame + s * SUBFRAME_SEED_STRIDE,
                                                 subframe_shadow_samples(self.direct_samples, self.subframes,
                                                                         offsets.shape[0]), surfaces=(hit, same),
                                                 surface=surface, emitters=screen.emitters_sampled,
                                                 translucent=translucent)
                finally:
                    if gi_job is not None:
                        with stats.step("subframe_gi"):
                            futures.wait([gi_job])  # nothing of this frame runs on after it is abandoned
                if gi_job is not None:
                    with stats.step("subframe_gi"):
                        gi, gi_low = self._subframe_gi_textures(gi_job.result(), gbuf, stats)
            with stats.step("direct"):
                self._direct_tex = upload_texture_2d(direct.reshape(self.height, self.width, 4), "RGBA32F")
            shaded = self.shade(gbuf, gi_low, sub_view, proj, self._direct_tex,
                                corner_visible=mask.reshape(low.height, low.width, 8), irradiance=lit_tex,
                                debug_view=debug_view, world_color=world_color, stats=stats, gi=gi,
                                glossy=sub_glossy, bilateral=gi_bilateral,
                                camera_proj=camera_proj)
            with stats.step("accumulate"):
                self.accumulate.execute(shaded, gbuf, first=s == 0)
        taps = reconstruction_taps(self.accumulate.count, self.filter_size, self.filter_type)
        film.set_filter(taps)
        if film_resolve.supports(taps):
            with stats.step("film_resolve"):  # the filter and divisions on the GPU, and the read-back
                self.film_resolve.resize(self.width, self.height)
                self.film_resolve.execute(self.accumulate, taps)
                film.set_resolved(self.film_resolve.read_all(), self.accumulate.count)
        else:  # a filter wider than the GPU pass takes: the numpy reference
            with stats.step("accumulate"):  # the sums' read-back, as "gbuffer" counts the G-buffer's
                sums = self.accumulate.read_all()
            film.set_sums(sums, self.accumulate.count)
        with stats.step("film"):
            film.set_glossy(glossy, glossy_col, self.height, self.width, indirect=glossy_ind)
        if debug_view == DEBUG_FINAL:
            self._refraction(system, view, proj, frame, film, stats, (p_full, n_full, pix_full), lookup)
        self.film = film
        return shaded, stats

    def _refraction(self, system, view, proj, frame: int, film, stats: FrameStats, full,
                    lookup: HitLookup | None) -> None:
        """The camera's refractive glass over the film (`refraction.py`): step "refraction".
        full : the centre G-buffer's (points, normals, flat pixels); lookup : the frame's
        HitLookup or None (`_frame_lookup`: built there once glass is seen)."""
        if not getattr(system.tracer, "has_glass", False):
            return
        with stats.step("refraction"):
            combined = film.read("combined").reshape(self.height * self.width, -1)
            glass = refraction.render_glass(system, lookup, view, proj, self.width, self.height,
                                            frame_rng(system.settings.seed + refraction.SEED_OFFSET, frame),
                                            (*full, combined))
            if glass is not None:
                film.set_refraction(*glass)

    def _stage_thread(self) -> futures.ThreadPoolExecutor:
        """The thread a frame's centre lamp light runs on beside the cache update (made on use).
        Not a worker of the system's pool (`CacheUpdater.on_pool_thread`): it splits its shadow
        rays over that pool as the render thread would. numpy and shadow rays only, no bpy, no gpu."""
        if self._stage is None:
            self._stage = futures.ThreadPoolExecutor(1, thread_name_prefix="hybridgi-stage")
        return self._stage

    def _update_cache(self, system, points, normals, cells, view, frame, warmup, update, stats, progress,
                      update_hook) -> np.ndarray:
        """Steps 3-5 of `render` for the visible cells (CPU only): the warm-up, the frame's update,
        the levels; returns the points' corner visibility (`GISystem.corner_visibility`)."""
        if warmup > 0:
            with stats.step("warmup"):
                warm_cells = np.union1d(system.surface_cells(), cells)
                runs = []
                for i in range(warmup):
                    runs += system.warm_up(1, warm_cells, start=i, total=warmup)
                    if progress is not None:
                        progress(i, warmup)
            stats.rays += sum(r.rays for r in runs)
            for r in runs:
                for k, v in r.steps_ms.items():
                    stats.steps_ms[f"warmup_{k}"] = stats.steps_ms.get(f"warmup_{k}", 0.0) + v
        if update:
            with stats.step("update"):
                run = update_hook(cells) if update_hook is not None else system.update(cells, frame)
            stats.rays += run.rays
            for k, v in run.steps_ms.items():
                stats.steps_ms[f"update_{k}"] = v
        if hasattr(system, "build_levels"):
            self._levels(system, points, normals, view, warmup, stats)
        with stats.step("visibility"):
            return system.corner_visibility(points, normals)

    def _translucent_shares(self, system) -> np.ndarray | None:
        """(h w, 3) the translucent share of the last raster's pixels (`translucent.pixel_shares`:
        one more read-back, only in scenes with a Translucent BSDF), or None."""
        table = translucent_mod.share_table(system.scene.materials)
        if table is None:
            return None
        return translucent_mod.pixel_shares(table, self.gbuffer.read("material").reshape(-1))

    def _centre_direct(self, system, view, proj, frame, full, translucent=None) -> CentreLight:
        """The centre raster's lamp light at full resolution (on the stage thread): adaptive in
        penumbrae (`penumbra.adaptive_direct`), each lamp's share for the subframes' light edges,
        and the `ScreenLight` the pixel rays' hits that the camera sees read it from. full : the
        G-buffer's (points, normals, flat pixels, smooth normals or None: `pixels_to_points`).
        translucent : (h w, 3) the pixels' translucent shares or None: their lamps are sampled on
        the back too (`translucent.mix_back`)."""
        tic = time.perf_counter()
        p_full, n_full, pix_full, s_full = full
        direct = np.zeros((self.height * self.width, 4), np.float32)
        camera = filter_camera(system.scene.lights, camera_eye(view, proj))
        lamps = len(system.scene.lights)
        # Each lamp's share, for the subframes' light edges per lamp (`subpixel.lamp_edges`).
        shares = (np.zeros((p_full.shape[0], lamps, 3), np.float32)
                  if self.subframes > 1 and 1 < lamps <= SUBFRAME_LAMP_LIMIT else None)
        # Several lamps: each traces its first pass's rays where it is not weak (`penumbra.WEAK_SHARE`);
        # the penumbra pass's rays go where the lamp's light is (`penumbra.sample_counts`).
        rough = rough_lights(system.scene.lights, p_full, n_full) if lamps else None
        # The lamps whose first pass may run on probes (`penumbra._coarse_first_pass`).
        exact_lamps = one_sample_exact_lamps(system.scene.lights)
        # Each lamp's exact unshadowed light and share: the glossy lobes' closed-form area-lamp
        # light is shadowed by their ratio (`glossy_ltc`).
        exact, per_lamp = glossy_ltc.direct_outputs(system, p_full.shape[0], shares)
        light = adaptive_direct(system.direct, p_full, n_full, pix_full, (self.height, self.width),
                                frame, self.direct_samples, camera=camera, pool=system.updater.pool, lamps=lamps,
                                smooth=s_full, per_lamp=per_lamp, rough=rough, exact_lamps=exact_lamps,
                                exact_out=exact)[0]
        direct[pix_full, :3] = light
        visibility = glossy_ltc.lamp_visibility(system.scene.lights, light, per_lamp, exact)
        t_full = None if translucent is None else translucent[pix_full]
        rows = translucent_mod.lit_from_behind(t_full)
        if rows.size:
            # The lamps on the back of the translucent pixels, each lamp's share too (the
            # subframes' light edges replace a lamp's share by their own mixed light).
            flipped = -n_full[rows]
            back_shares = None if shares is None else np.zeros((rows.size, lamps, 3), np.float32)
            back = adaptive_direct(system.direct, p_full[rows], flipped, pix_full[rows], (self.height, self.width),
                                   frame + translucent_mod.BACK_SEED_OFFSET, self.direct_samples, camera=camera,
                                   pool=system.updater.pool, lamps=lamps,
                                   smooth=None if s_full is None else -s_full[rows], per_lamp=back_shares,
                                   rough=rough_lights(system.scene.lights, p_full[rows], flipped) if lamps
                                   else None, exact_lamps=exact_lamps)[0]
            t = t_full[rows]
            direct[pix_full[rows], :3] = translucent_mod.blend(direct[pix_full[rows], :3], back, t)
            if visibility is not None:
                visibility[rows] = np.nan  # a blend of both sides' light: lamp sampling there
            if shares is not None:
                shares[rows] = translucent_mod.blend(shares[rows], back_shares, t[:, None, :])
        lamp_light = None
        if shares is not None:
            lamp_light = np.zeros((self.height * self.width, lamps, 3), np.float32)
            lamp_light[pix_full] = shares
        # Hits find their pixel by the surface (the smooth normal), not a normal map's bend. Their
        # light is the lamps' only: hits see emitters through the cache, as before.
        screen = ScreenLight.from_pixels(view, proj, (self.width, self.height), p_full,
                                         n_full if s_full is None else s_full, pix_full, direct[pix_full, :3])
        # Emissive triangles sampled as lights at every pixel (`emitters.py`), where pixel rays
        # remove the cache's share of them (with pixel rays off the cache's gather keeps it).
        emitter = None
        if self.settings.pixel_rays > 0 and worth_sampling(system.surfaces.emitters, system.scene.lights):
            samples = emitter_samples(self.direct_samples)
            if system.surfaces.emitters.ratio:
                # A few triangles in closed form: the shadow rays' share, adaptive in penumbrae as
                # the lamps' (`emitters.MeshLights._ratio_block`).
                direct[pix_full, :3] += adaptive_direct(system.emitter_light, p_full, n_full, pix_full,
                                                        (self.height, self.width), frame, samples, camera=camera,
                                                        pool=system.updater.pool)[0]
            else:
                # Many triangles, sampled by power: their light without shadows and their
                # visibility filtered apart (`penumbra.filter_emitter_light`).
                open_light = np.zeros((p_full.shape[0], 3), np.float32)
                cones = np.zeros((p_full.shape[0], 3), np.float32)
                light = system.emitter_light(p_full, n_full, frame, samples, unshadowed=open_light, cones=cones)
                emitter = np.zeros((self.height * self.width, 3), np.float32)
                # The lamps' `camera` is None beside a sun (its penumbrae a pixel wide); the
                # emitters' light is filtered whatever lamps light the scene (a sun of strength 0
                # crashed here), unless the view is orthographic.
                eye = filter_camera((), camera_eye(view, proj))
                emitter[pix_full] = filter_emitter_light(light, open_light, cones, p_full, n_full, pix_full,
                                                         (self.height, self.width), eye, pool=system.updater.pool)
                direct[pix_full, :3] += emitter[pix_full]
            screen = dataclasses.replace(screen, emitters_sampled=True)
        return CentreLight(direct, lamp_light, screen, p_full, n_full, pix_full, s_full,
                           (time.perf_counter() - tic) * 1e3, visibility, emitter)

    def _centre_locator(self, view, proj):
        """(points, flat pixels) -> where the centre raster shows the points (`lens.centre_offsets`)."""
        return lambda points, pix: centre_offsets(points, pix, self.width, self.height, view, proj)

    def _reused_centre(self, centre: CentreSample, count: int) -> CentreSample:
        """The centre sample whose direct light `count` jittered subframes reuse: spread over the
        pixel filter's share that their jitter does not sample (`reused_light`)."""
        taps = reuse_taps(count, self.filter_size, self.filter_type)
        if taps.size == 1:
            return centre
        direct = centre.direct.copy()
        direct[:, :3] = filter_on_surface(centre.direct[:, :3], centre.position, centre.surface_normal,
                                          centre.depth, (self.height, self.width), taps, keep=centre.light_edge)
        return dataclasses.replace(centre, direct=direct)

    def _subframe_count(self, centre, full_gi, stats, base: int | None = None) -> int:
        """Subframes of this frame: `base` (default `subframes`), plus `extra_subframes` (at most
        EXTRA_PER_SUBFRAME x base) when the centre raster's GI
        edges (`subpixel.gi_edges`: thin surfaces of far other bounce light than what lies behind
        them) are a share of the image (`subpixel.worth_extra`). Why the whole frame: a subframe's
        cost is its raster passes over every pixel, so more of them at a few pixels cost as much
        as at all (yard 320x240 DI: 8 + 24 at the marked pixels 0.095, 32 everywhere 0.091, at the
        same seconds), and one Hammersley set of 32 is better stratified than 8 and 24 apart."""
        base = self.subframes if base is None else int(base)
        if self.extra_subframes <= 0 or full_gi is None:
            return base
        edges = gi_edges(centre, full_gi.indirect, self.height, self.width)
        if not worth_extra(edges):
            return base
        stats.extra_pixels = int(edges.sum())
        extra = min(self.extra_subframes, EXTRA_PER_SUBFRAME * base)
        log.debug("%d GI edge pixels: %d + %d subframes", stats.extra_pixels, base, extra)
        return base + extra

    def _gather_levels(self, levels, low, points, normals, pix, visible, view, proj, lit_tex):
        """The GPU gather of each cache level (its own corner mask: columns 8k .. 8k + 7 of
        `visible`), read back and joined by `CacheLevels.blend` (the numpy reference is
        `CacheLevels.gather`), as the (indirect, direct, ssao) textures `shade` takes."""
        h, w = low.height, low.width
        g = gather_levels(self.gather, levels, low, points, normals, pix, visible, surfaces=self.gbuffer.bends_normals)
        indirect = np.zeros((h * w, 4), np.float32)
        indirect[..., 3] = 1.0
        direct = np.zeros((h * w, 4), np.float32)
        indirect[pix, :3], indirect[pix, 3], direct[pix, :3] = g.indirect, g.ao, g.direct
        kept = self.ssao.settings
        if kept.ssao_auto:
            # The automatic radius is one cell: the finest level's here (cache gather at 320x240
            # vs Cycles, Combined: atrium 0.0398 -> 0.0386, car 0.0057 -> 0.0056, yard 0.0236 -> 0.0134).
            self.ssao.settings = kept.with_(ssao_radius=float(levels.caches[-1].grid.cell_size))
        try:
            ssao = self.ssao.execute(low, view, proj, irradiance=lit_tex, surfaces=self.gbuffer.bends_normals)
        finally:
            self.ssao.settings = kept
        return (upload_texture_2d(indirect.reshape(h, w, 4), "RGBA32F"),
                upload_texture_2d(direct.reshape(h, w, 4), "RGBA32F"), ssao)

    def _levels(self, system, points, normals, view, warmup, stats) -> None:
        """The finer camera-centred cache levels (`levels.py`) for this view's visible points,
        with as many traced batches as the warm-up gave level 0; with cache_levels = 1 the
        system keeps none (and every reader takes the single-grid path)."""
        if system.settings.cache_levels <= 1:
            system.levels = None
            return
        with stats.step("levels"):
            v = np.asarray(view, np.float32).reshape(4, 4)
            depth = -(points @ v[2, :3] + v[2, 3])
            batches = max(1, round(warmup / UPDATES_PER_BATCH)) if warmup > 0 else 1
            run = system.build_levels(points, normals, depth, batches)
        stats.rays += run.rays
        for k, v_ms in run.steps_ms.items():
            stats.steps_ms[f"levels_{k}"] = stats.steps_ms.get(f"levels_{k}", 0.0) + v_ms

    @staticmethod
    def _frame_lookup(system) -> HitLookup | None:
        """The HitLookup of the level-0 cache that the frame's pixel rays and reflection rays both
        read (each built its own: ~50 ms on a 48^3 grid), or None where the pixel rays read the
        finer levels (`levels.hit_lookup`) or no glossy lobe reflects: each then builds its own."""
        if getattr(system, "levels", None) is not None or not glossy_image.has_glossy(system):
            return None
        return HitLookup(system.cache, bounced=system.settings.indirect_quality == MULTI_BOUNCE)

    def _start_glossy(self, system, view, proj, points, normals, pix, frame, lookup: HitLookup | None,
                      irradiance: np.ndarray, visibility: np.ndarray | None = None,
                      screen: ScreenLight | None = None) -> futures.Future | None:
        """Submit to the stage thread the glossy light of the centre raster's pixels before its
        filters (`glossy_image.begin_glossy`: the lamps', sky's and emitters' reflection by the
        glossy lobes and the light of other surfaces they reflect; `_finish_glossy` filters it on
        the GPU); None without glossy lobes. The G-buffer's
        targets are read here, on the thread that owns the GPU context; the job is numpy only.
        lookup : the cache's HitLookup to reuse (None: the reflection rays build their own).
        irradiance : (n, 3) the pixels' diffuse lamp irradiance: the lamps' glossy light is
        sampled `glossy_samples` times only where it is noisy against the pixels' lamp light
        (`glossy_noise`). visibility : (n, lamps) the lamps' visibility (`CentreLight.visibility`)
        or None. screen : the frame's ScreenLight (the reflection rays' hits the image shows read
        their lamp light there). `_finish_glossy` waits for it and uploads the result."""
        if not glossy_image.has_glossy(system):
            return None
        material = self.gbuffer.read("material").reshape(-1)[pix]
        albedo = self.gbuffer.read("albedo").reshape(-1, 4)[pix]
        tint = None
        if system.glossy_materials.tint_bases:  # textured metals: their texels' coordinates
            tint = np.stack([albedo[:, 3], self.gbuffer.read("emission").reshape(-1, 4)[pix, 3]], axis=-1)
        eye = camera_eye(view, proj)
        shape = (self.height, self.width)

        def job():
            t0 = time.perf_counter()
            draft = glossy_image.begin_glossy(system, points, normals, pix, shape, material, albedo[:, :3],
                                              irradiance, view, eye, frame, self.glossy_samples,
                                              self.settings.reflection_rays, lookup, pool=system.updater.pool,
                                              tint=tint, visibility=visibility, screen=screen)
            return draft, (time.perf_counter() - t0) * 1e3

        return self._stage_thread().submit(job)

    def _finish_glossy(self, job: futures.Future | None, pix, stats: FrameStats):
        """(direct radiance, Glossy Color, bounced light), each (h w, 4) float32, or None without
        glossy lobes: `_start_glossy`'s result laid out over the image, direct + colour x bounced
        uploaded for the deferred pass. Subframes reuse it: a highlight is smooth at the pixel
        scale, and silhouettes are where its share is least. Step "glossy": the job's own time
        (it overlapped the pixel rays), its filters' blends (`glossy_image.finish_glossy`; the
        filters themselves are GPU passes: step "atrous") and the upload."""
        if job is None:
            return None, None, None
        draft, ms = job.result()
        stats.steps_ms["glossy"] = stats.steps_ms.get("glossy", 0.0) + ms

        def gpu_filter(*args, **kwargs):
            with stats.step("atrous"):
                return self.glossy_atrous(*args, **kwargs)

        with stats.step("glossy"):
            atrous_before = stats.steps_ms.get("atrous", 0.0)
            light = glossy_image.finish_glossy(draft, filter=gpu_filter)
            # The step holds the blends only: the filter passes are "atrous"'s.
            stats.steps_ms["glossy"] -= stats.steps_ms.get("atrous", 0.0) - atrous_before
            glossy, colour, indirect = (np.zeros((self.height * self.width, 4), np.float32) for _ in range(3))
            glossy[pix, :3] = light.direct
            colour[pix, :3] = light.colour
            indirect[pix, :3] = light.bounced
            total = glossy + colour * indirect
            self._glossy_total = total
            self._glossy_tex = upload_texture_2d(total.reshape(self.height, self.width, 4), "RGBA32F")
        return glossy, colour, indirect

    def _subframe_glossy(self, centre: CentreSample, hit, same, position, normal, surface, stats: FrameStats):
        """The glossy texture a jittered subframe adds: the centre's, with the pixels where the
        subframe sees a neighbour's surface taking that neighbour's light (`subframe_glossy`).
        Step "glossy"."""
        with stats.step("glossy"):
            moved = subframe_glossy(self._glossy_total, centre, hit, same, position,
                                    compared_normal(centre, normal, surface), self.width)
            if moved is None:
                return self._glossy_tex
            return upload_texture_2d(moved.reshape(self.height, self.width, 4), "RGBA32F")

    def _pixel_gi_full(self, system, gbuf, position_lo, normal_lo, pix, points, normals, visible, view, frame,
                       full, stats, screen=None, full_surfaces=None, lookup: HitLookup | None = None, begun=None):
        """Pixel rays at the GI resolution resolved per full-res pixel (`pixel_gather.full_res_images`):
        (the three full-res textures, the centre G-buffer's copy that guides them, the factor-1
        bilateral pass that reads them)."""
        s = self.settings
        with stats.step("downsample"):  # the G-buffer's factor-1 copy: a GPU pass
            guide, bilateral = self.full_res_guide(gbuf)
        p_full, n_full, pix_full = full
        out = pixel_gather.full_res_images(
            system, position_lo, normal_lo, pix, points, normals, visible, view, frame, s.pixel_rays,
            p_full, n_full, pix_full, (self.width, self.height), passes=s.pixel_filter,
            plane_sigma=s.bilateral_plane_sigma, normal_power=s.bilateral_normal_power, screen=screen,
            full_surfaces=full_surfaces, filter=stats.gpu_pass(self.atrous), upsample=stats.gpu_pass(self.upsample),
            lookup=lookup, begun=begun)
        stats.rays += out.gi.rays
        steps = dict(out.steps_ms)
        stats.steps_ms["atrous"] = stats.steps_ms.get("atrous", 0.0) + steps.pop("filter", 0.0)  # a GPU pass
        stats.steps_ms["upsample"] = stats.steps_ms.get("upsample", 0.0) + steps.pop("upsample_pass", 0.0)  # too
        for k, v in steps.items():
            stats.steps_ms[f"pixel_{k}"] = stats.steps_ms.get(f"pixel_{k}", 0.0) + v
        stats.detail_pixels = out.detail
        log.debug("pixel rays: %d full-res pixels traced their own rays", out.detail)
        neutral = np.zeros(out.indirect.shape, np.float32)
        neutral[..., 3] = 1.0
        self._neutral_tex = upload_texture_2d(neutral, "RGBA16F")
        textures = (upload_texture_2d(out.indirect, "RGBA32F"), upload_texture_2d(out.direct, "RGBA32F"),
                    self._neutral_tex)
        return textures, guide, bilateral, out

    def full_res_guide(self, gbuf):
        """(guide, bilateral) for GI textures at the full resolution (`pixel_gather.full_res_images`):
        a copy of `gbuf`'s targets as a factor-1 "low-res" G-buffer (the guide of those samples,
        as the downsampled G-buffer guides the GI resolution's; jittered subframes overwrite the
        G-buffer, not the copy) and the factor-1 bilateral pass that reads them (`shade(gbuf,
        guide, ..., gi=, bilateral=)`). Made on first use."""
        s = self.settings
        if self._full_copy is None:
            self._full_copy = DownsamplePass(1)
            self._bilateral_full = BilateralPass(s.with_(downsample=1))
        self._bilateral_full.settings = s.with_(downsample=1)
        for p in (self._full_copy, self._bilateral_full):
            p.resize(self.width, self.height)
        return self._full_copy.execute(gbuf), self._bilateral_full

    def _subframe_gi_textures(self, resolved, gbuf, stats):
        """A jittered subframe's full-res GI textures from `subpixel.subframe_gi`'s (indirect,
        direct, rays traced) (the centre's where it sees the centre's surface, resolved at its own
        samples elsewhere) and their guide, a copy of the subframe's own G-buffer: (gi textures,
        guide)."""
        indirect, direct, traced = resolved
        stats.rays += traced
        with stats.step("downsample"):  # the subframe's G-buffer copy: a GPU pass
            guide = self._full_copy.execute(gbuf)
        shape = (self.height, self.width, 4)
        # New textures, not updated in place: an update waits for the previous subframe's passes.
        return (upload_texture_2d(indirect.reshape(shape), "RGBA32F"), upload_texture_2d(direct.reshape(shape), "RGBA32F"),
                self._neutral_tex), guide

    def _pixel_gi(self, system, position_lo, normal_lo, pix, points, normals, visible, view, frame, stats,
                  screen=None):
        """Per-pixel final gather (`pixel_gather.gi_images`) as the textures the gather and the
        screen-space pass would give: the rays already see the near field, so the SSAO slot is
        neutral (no occlusion, no bounce) and nothing is counted twice."""
        s = self.settings
        indirect, direct, pg = pixel_gather.gi_images(
            system, position_lo, normal_lo, pix, points, normals, visible, view, frame, s.pixel_rays,
            passes=s.pixel_filter, plane_sigma=s.bilateral_plane_sigma, normal_power=s.bilateral_normal_power,
            screen=screen)
        stats.rays += pg.rays
        for k, v in pg.steps_ms.items():
            stats.steps_ms[f"pixel_{k}"] = stats.steps_ms.get(f"pixel_{k}", 0.0) + v
        neutral = np.zeros(indirect.shape, np.float32)
        neutral[..., 3] = 1.0
        return (upload_texture_2d(indirect, "RGBA32F"), upload_texture_2d(direct, "RGBA32F"),
                upload_texture_2d(neutral, "RGBA16F"))

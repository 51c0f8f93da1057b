"""Per-pixel final-gather rays at the GI resolution: the first bounce exact per pixel.

The cache gather (`evaluate.gather`) interpolates cells of ~1/48 of the scene, so light that
varies within a cell (contacts, thin posts, under eaves) is smeared, and the screen-space pass
that stood in for the missing near field sees only what the screen shows. Here every GI pixel
traces `rays` cosine-distributed rays of its own (stratified: Hammersley with a per-pixel
Cranley-Patterson rotation, deterministic per frame). Hits are shaded as probe-ray hits are
(`update.py`): lamp light through shadow rays, the cache read at the hit for the further bounces
(`evaluate.HitLookup`), emission; misses read the world (`World.radiance`). So sky light and
emitters (Cycles' Diffuse Direct) get the pixel's own visibility, the first bounce is exact per
pixel, and AO is Cycles' definition (cosine-weighted share of rays unblocked within the World's
AO distance).

Noise: the cache gather's radiance SH at the pixel is a control variate. With cosine sampling,
E = pi/N sum L(w_i) estimates irradiance, and the same sum over the cache's band-limited SH
radiance L_c estimates exactly the cache's own irradiance E_c (the clamped-cosine convolution of
an L2 function is exact in L2). So

    E_hat = E_c + pi/N sum (L(w_i) - L_c(w_i))

is unbiased for the ray-traced irradiance whatever the cache holds, and its noise is only that of
the difference: small where the cache is right (open, smooth light), where the rays add nothing,
and the signal itself where the cache is wrong (a contact's occluder, a post's shadow). The
residual E_hat - E_c is then filtered edge-aware at the GI resolution (`filter_residual`:
a-trous passes guided by the pixels' planes and normals), so the cache's smooth part is never
blurred and the correction stays on the surface it belongs to.

Near hits: the cache cell a hit reads lies HIT_LOOKUP_BIAS of a cell in front of it; in clutter
finer than a cell (a scatter of rocks, a crevice) that is above the clutter, where the sky is more
open and the bounce light other than at the hit. Hits nearer than NEAR_BOUNCE_CELLS cells to their
pixel trace one cosine ray of their own (`_near_bounce`, its own seeded stream) and take pi x its
radiance as their further bounces: a true second bounce per pixel ray where the clutter is.

numpy + embreex only (bpy-free; the raster pipeline uploads the result, `raster/frame.py`).
"""

from __future__ import annotations

import functools
import threading
import time
from collections.abc import Callable
from concurrent import futures
from dataclasses import dataclass, field

import numpy as np

from . import hit_glossy, sh
from .bump import has_normal_maps, irradiance_kernel, shadowing_term, smooth_normals
from .camera import camera_position
from .environment import LUMA as ENV_LUMA
from .evaluate import HitLookup, corner_weights, monomials
from .levels import hit_lookup
from .lights import HIT_LAMP_BUDGET, _onb, concentric_disk, direct_irradiance, stratified_uv
from .rows import mean_over_rays
from .sampling import frame_rng
from .screen_light import ScreenLight
from .settings import AO_ONLY, MULTI_BOUNCE
from .shiny import highlights, shiny_hits, shiny_share
from .sky_ratio import open_share, open_sky_estimate, sky_irradiance
from .tiled_nets import tiled_uv

#: Rec.709 luminance weights (the colour channels' filter guide), as the float32 arrays they weigh.
LUMA = ENV_LUMA.astype(np.float32)

#: The GI pixels' rays stratify with their neighbours' (`tiled_nets`).
TILED_RAYS = True
#: Rays per work item (pixels x rays): fixed, so the result does not depend on the thread count.
#: 128k, not 64k, with the glossy light's work items (`reflection.CHUNK_RAYS`): fewer, longer numpy
#: calls, fewer hand-overs of the GIL, which most numpy calls release and retake; on this 2-core VM
#: a hand-over costs about what a 32k-element call computes (direct light on a pool of two: 0.74 x one thread's speed at 32k rays
#: per item, 1.17 x at 128k, 1.52 x at 512k). 640x360, r16 rung, medians of three alternating runs:
#: -gpu bunny_npm 2.06 -> 1.92 s, dragon_npm 2.28 -> 2.13, morse 1.20 -> 1.10, spheres 1.62 -> 1.46,
#: atrium 1.98 -> 1.85, Cornell 0.95 -> 0.93, car 0.73 -> 0.76; 256k read no better.
CHUNK_RAYS = 131072
#: Seed offset of the pixel rays' stream (the cache uses seed, the direct light seed + 1).
SEED_OFFSET = 2
#: Standard deviations of the noise within which a filter tap counts as the same signal.
NOISE_SIGMA = 2.0
#: Y_0^0, the constant SH basis function: radiance 1 in every direction is 1 / Y00 in coefficient 0.
SH_Y00 = 0.28209479177387814
#: A full-res pixel whose best low-res neighbour's range weight (plane x normal, as the bilateral
#: upsampling weighs it) stays below this lies on no surface the GI resolution sampled near it
#: (a post or bar narrower than a GI pixel, the far side of a silhouette): it traces its own rays.
DETAIL_MATCH = 0.25
#: Relative spread of the residual between a full-res pixel's GI taps above which it traces its
#: own rays (`full_res_images`).
#: 0.05 (car Diffuse Indirect error 0.094 at 0.1 -> 0.091, 2.7% of its pixels refined; 0.02 gained
#: 0.003 more for twice the pixels, and on the trusses 4x the pixels for nothing).
REFINE_SPREAD = 0.05
#: Normals closer than this cosine (8 degrees) count as the same in `upsample_full`: no SH re-evaluation,
#: no refinement for the bend (0.9995 -> 0.99: car and atrium DI equal to 0.0001, fewer SH taps).
FLAT_COS = 0.99
#: At most this share of the GI pixels' count of full-res pixels refine (the atrium's busy surfaces
#: have refinement candidates at a quarter of its GI pixels' count: 0.25 -> 0.15 cost DI 0.0523 ->
#: 0.0525 there for 40% fewer detail rays; the car's 1819 stay under it).
REFINE_BUDGET = 0.15
#: Fewest work items of the detail pixels' rays (a few thousand pixels): enough to feed every
#: worker, each still CHUNK_RAYS at most. Fixed, so the result does not depend on the thread
#: count. Work items of 8192 rays (170 pixels) left the two workers waiting on the GIL for their
#: short numpy calls: Cornell 640x360's 4.8k detail pixels took 196 ms on two threads, 212 on one.
DETAIL_MIN_CHUNKS = 4
#: Fewest rays of a work item that `trace_pixels(min_chunks=)` splits off: a `_chunk` call costs
#: ~2 ms whatever its size (~30 us a pixel of 48 rays on top), so a subframe's few dozen orphan
#: pixels stay one item (four items of them cost dragon_npm's 8 subframes +150 ms).
MIN_SPLIT_RAYS = 16384
#: Share of a pixel's spatial tap weight that must lie on its own surface for it to count as
#: inside a surface (below: near a crease, contact or silhouette; refinement candidate).
REFINE_COVER = 0.85
#: Frame offset of the detail pixels' ray stream (other directions than the GI pixels').
DETAIL_FRAME = 1 << 20
#: Frame offset of a re-shaded pass's shading samples (`reshade_pixels`): a stream apart from the
#: traced passes'.
RESHADE_FRAME = 1 << 21
#: NOISE_SIGMA of `full_res_images`: the per-pixel interpolation already averages over the GI pixels
#: around each pixel, so the filter may stop at smaller differences than NOISE_SIGMA. 1.5, not 1.0
#: (640x360 vs 1024-spp Cycles, Combined, r32 x32 p32 s4 rung: Cornell 0.0220 -> 0.0215, spheres
#: 0.0095 -> 0.0088, bunny_npm 0.0275 -> 0.0266, dragon 0.0528 -> 0.0521, car and atrium equal; r24
#: rung: Cornell 0.0291 -> 0.0270, spheres 0.0119 -> 0.0105; at 320x240 yard, contact, hdri_yard a
#: little better, trusses equal, scatter 0.0125 -> 0.0126): noise, not detail, stopped the taps on
#: the Cornell box's ceiling. 2.0 was better still on the spheres and bunny, worse on the car
#: (Diffuse Indirect 0.0505 -> 0.0543); 1.0 against 2 once won at 320x240 with fewer pixel rays.
FULL_RES_NOISE_SIGMA = 1.5
#: `full_res_images`' filter and its full-res interpolation (`upsample_full`, also a subframe's
#: `GIResolver`) count a tap fully while it lies no farther from the pixel than the same screen
#: step spans on a surface facing the camera, and fall off as exp(-((ratio - 1) / STRETCH)^2) in
#: how many times farther it lies (~1 / cos of the viewing angle, `_stretch_into`). Why: on a
#: ground seen at a grazing angle one pixel spans metres along the view, and the plane and normal
#: terms let taps average light from tens of metres apart (the glow under the yard's pavilion
#: spread over the ground seen beyond it, 10x Cycles' light there). 320x240 vs Cycles 4096 spp,
#: Diffuse Indirect, none -> filter only -> filter and interpolation: hdri_yard 0.1005 -> 0.0978
#: -> 0.0881, yard 0.0757 -> 0.0748 -> 0.0621, sky_yard 0.0755 -> 0.0731 -> 0.0621 (filter only,
#: STRETCH 2: 0.0984 / 0.0756 (hdri_yard / yard); 8: 0.0987 / 0.0749; 1: 0.1002 / 0.0768); 640x360
#: vs 1024 spp, Combined: Cornell 0.0203 -> 0.0202, atrium 0.0229 -> 0.0227.
STRETCH = 4.0
#: Adaptive AO sampling (`_more_ao_rays`): pixels whose AO's relative standard error exceeds
#: AO_RELATIVE_NOISE trace AO_EXTRA x their rays again as occlusion-only AO rays.
AO_EXTRA = 1.0
AO_RELATIVE_NOISE = 0.15
#: Pixel-ray hits nearer than this many level-0 cells trace one more cosine ray of their own (a true
#: second bounce, `_near_bounce`) instead of reading the cache at the hit: in clutter finer than a
#: cell (rocks, crevices) the cell in front of a near hit lies above the clutter and sees more sky and
#: other bounce light than the hit does (module docstring).
#: 0.125: the 320x240 scatter of `bench/fine_detail_scenes.py` vs Cycles 256 spp, Diffuse Indirect bias
#: -7.6% -> -5.5% (0.25: -5.3%, 0.5: -5.4%, 1 and 3 cells the same: its hits are that near); the
#: 640x360 atrium's DI 0.0447 -> 0.0440 (0.25: 0.0437, 0.5: 0.0434). Near-bounce time over the pixel
#: rays' time in the same render: Cornell 1.5%, spheres 3%, animated 4%, car and atrium 8% (at 0.25:
#: Cornell 6%, atrium 12%; at 0.5: Cornell 6-8%, atrium 15-17%, where Cornell gains nothing).
#: 1.0 since: at 640x360 vs Cycles 1024 spp with the pixel rays' cost since then, Combined at the
#: default settings (0.125 -> 1.0) spheres 0.0087 -> 0.0083 (the light between the front sphere's
#: underside and the floor it stands on, DI 0.056 -> 0.052), morse_apartment 0.0490 -> 0.0472,
#: dragon_npm 0.0481 -> 0.0477, car 0.0031 -> 0.0030, atrium 0.0227 -> 0.0225, Cornell 0.0202 ->
#: 0.0201, bunny_npm 0.0250 the same; near-bounce time +25-70 ms (atrium +160 ms, 8% of its pixel
#: rays). 2 cells: the same errors (spheres 0.0083, atrium 0.0226) for twice the time.
NEAR_BOUNCE_CELLS = 1.0
#: Bounces a near hit may trace before reading the cache (1: a near second hit reads the cell in
#: front of it). 2 / 4 on the scatter: bias -8.4% -> -8.1 / -8.0% (1 cm origins); a 0.3 m trench
#: 8.2% -> 2.2% too bright at 3, at more rays where the clutter is deep. 2 since the full-res
#: filter's noise gate rose to 1.5 (`FULL_RES_NOISE_SIGMA`): the gap between the spheres' front
#: sphere and its floor is bounce upon bounce (640x360 Combined, r40 x32 p48 s8 rung: 0.0078 ->
#: 0.0072, below Cycles 16 spp + OIDN's 0.0074; r32 rung: morse 0.0519 -> 0.0514, dragon 0.0521 ->
#: 0.0519, car Diffuse Indirect 0.0522 -> 0.0512, Cornell, bunny, atrium equal) for +50-230 ms of
#: near-bounce work on the two workers.
NEAR_BOUNCE_DEPTH = 2
#: NEAR_BOUNCE_DEPTH of scenes with emissive surfaces. Next to a bright emitter's contact (the
#: spheres' glowing ball on its floor) the light goes back and forth between the two surfaces,
#: each round ~0.5 of the last, and the cache there holds ~1/3 of it (its cells are coarser than
#: the contact; a lamp's light at a near hit is exact, an emitter's comes through rays alone):
#: floor points 1-10 cm from the ball, against an 8-bounce path tracer on the same ray mesh,
#: Diffuse Indirect 3.66 / 3.02 / 2.06 at depth 2, 5.70 / 4.46 / 2.75 at 4, 6.84 / 5.14 / 3.01 at 6
#: (tracer: 6.82 / 5.06 / 3.06). 640x360 r48 x32 p32 s8 rung Combined: spheres 0.0071 -> 0.0069
#: (4) / 0.0068 (8), morse 0.0480 -> 0.0478; elsewhere the same errors for +100 ms of pixel rays
#: (the Cornell box's corners: its cache holds their lamp-lit bounces well), so emitters only.
EMITTER_NEAR_BOUNCE_DEPTH = 6
#: Share of the near hits past NEAR_BOUNCE_DEPTH near bounces that trace one more
#: (`_near_roulette`; the others read the cache, the survivors' difference to it is scaled up).
NEAR_SURVIVAL = 0.5
#: B3-spline taps of one a-trous pass (5 x 5, Dammertz et al. 2010).
_B3 = np.array([1.0, 4.0, 6.0, 4.0, 1.0], np.float32) / 16.0
#: Fewest rows of own pixels a band must add to its halos for the filter to split the image.
BAND_MIN_ROWS = 32
#: Largest share of the image's pixels that `filter_at_pixels` filters by gathering their taps
#: (measured: ~3x faster at 5%, as fast at ~35%, ~2x slower at 100% than the whole image).
SPARSE_FILTER_SHARE = 0.25
#: Fewest kept pixels for which `filter_at_pixels`' sparse path splits a pass over the pool.
SPARSE_SPLIT_PIXELS = 8192


@dataclass
class PixelGI:
    """Irradiance (W/m^2) at n GI pixels from their own rays.

    direct (n, 3): sky and emitters seen straight (Cycles' Diffuse Direct, less lamps);
    indirect (n, 3): light reflected by surfaces (all bounces; further ones from the cache);
    ao (n,): cosine-weighted share of rays unblocked within the AO distance.
    cache_* : the cache gather at the same points (the control variate's own value).
    """

    direct: np.ndarray
    indirect: np.ndarray
    ao: np.ndarray
    cache_direct: np.ndarray
    cache_indirect: np.ndarray
    cache_ao: np.ndarray
    variance: np.ndarray | None = None  # (n, 2) of the means of luminance (direct + indirect) and AO
    #: (n,) variance of the mean of the indirect light's luminance (the second guide of
    #: `full_res_images`' filter; None: one guide).
    indirect_variance: np.ndarray | None = None
    #: (n, K, 7) the cache gather's blended radiance SH at the points (direct rgb | indirect rgb |
    #: AO visibility; a point no valid cell covers holds the constant 1 in AO): what
    #: `upsample_full` re-evaluates at the full-res normals.
    sh: np.ndarray | None = None
    rays: int = 0
    steps_ms: dict[str, float] = field(default_factory=dict)

    def channels(self) -> tuple[np.ndarray, np.ndarray]:
        """((n, 7) estimate, (n, 7) cache) as direct rgb | indirect rgb | ao columns."""
        est = np.concatenate([self.direct, self.indirect, self.ao[:, None]], axis=1)
        cache = np.concatenate([self.cache_direct, self.cache_indirect, self.cache_ao[:, None]], axis=1)
        return est, cache


def cosine_directions(normals: np.ndarray, rays: int, rng: np.random.Generator,
                      uv: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """(n, rays, 3) float32 cosine-distributed unit directions around unit normals (n, 3).

    Each pixel's set is a Hammersley set shifted by its own random offset (`lights.stratified_uv`),
    or the (n, rays) points `uv` given (`tiled_nets.tiled_uv`), mapped to the disc
    area-preserving (`concentric_disk`) and lifted to the hemisphere (Malley).
    """
    n = normals.shape[0]
    u, v = stratified_uv(rng, n, rays) if uv is None else uv
    a, b = concentric_disk(u, v)
    c = np.sqrt(np.maximum(np.float32(1.0) - a * a - b * b, np.float32(0.0)))
    nx, ny, nz = (np.asarray(normals[:, k], np.float32)[:, None] for k in range(3))
    t1, t2 = _onb(nx, ny, nz)
    d = np.empty((n, rays, 3), np.float32)
    for k in range(3):
        d[..., k] = a * t1[k] + b * t2[k] + c * (nx, ny, nz)[k]
    return d


def cache_sh_at(cache, points: np.ndarray, normals: np.ndarray, corner_visible: np.ndarray | None):
    """The cache gather's blended radiance SH at points: (direct (n, K, 3), indirect (n, K, 3),
    ao (n, K), covered (n,) bool), with the gather's own weights (`evaluate.corner_weights`)."""
    flats, w = corner_weights(cache, points, normals, True, corner_visible)
    n, k = flats.shape[0], cache.settings.sh_coeffs
    wr = w[:, None, :]  # (n, 1, 8) @ (n, 8, .): batched GEMMs, far faster than einsum's loops
    # np.take, not fancy indexing: numpy 1.26 gathers whole rows ~5-10x faster through take.
    sh_d = np.matmul(wr, np.take(cache.sh_direct, flats, axis=0).reshape(n, 8, k * 3)).reshape(n, k, 3)
    sh_i = np.matmul(wr, np.take(cache.sh_indirect, flats, axis=0).reshape(n, 8, k * 3)).reshape(n, k, 3)
    sh_a = np.matmul(wr, np.take(cache.ao_sh, flats, axis=0)).reshape(n, k)
    return sh_d, sh_i, sh_a, w.sum(axis=1) > 0


def trace_pixels(system, points: np.ndarray, normals: np.ndarray, rays: int, frame: int,
                 corner_visible: np.ndarray | None = None, lookup: HitLookup | None = None,
                 chunk_rays: int = CHUNK_RAYS, screen: ScreenLight | None = None,
                 surfaces: np.ndarray | None = None, min_chunks: int = 1,
                 pixels: tuple[np.ndarray, int, int] | None = None,
                 stop: Callable[[], bool] | None = None) -> PixelGI:
    """Per-pixel gather at points (n, 3) with unit normals (n, 3) of `system` (a GISystem):
    `rays` rays each, the cache's SH as control variate (module docstring). corner_visible :
    (n, 8) bool occlusion of the 8 neighbour cells (`GISystem.corner_visibility`), as the image
    gather reads the cache. lookup : the cache's HitLookup to reuse (building one reads the whole
    grid); chunk_rays : rays per work item (fixed per caller, so the result does not depend on the
    thread count). min_chunks : fewest work items (a few pixels split finer to use every worker;
    fixed per caller too). screen : the frame's lamp light
    per pixel for the hits the camera sees (`screen_light`). surfaces : (n, 3) the smooth surface
    normals under normals a normal map bent (the G-buffer's `surface`), or None: found by a ray
    each in scenes with normal maps (`bump.smooth_normals`). pixels : (pix (n,), width, key) the
    points' flat indices in an image `width` pixels wide and the pass's key: the pixels of each
    tile of that image draw their rays as one net (`tiled_nets`, unless TILED_RAYS is off); None:
    a random shift each. stop : polled before each work item; once it returns True the items not
    yet begun are skipped (their pixels stay zero: the caller throws the result away); it is
    polled again before each traced item's shading. `begin_pixels` and `finish_pixels` in one
    call."""
    return finish_pixels(begin_pixels(system, points, normals, rays, frame, corner_visible, lookup, chunk_rays,
                                      surfaces, min_chunks, pixels, stop), screen)


#: What `BegunPixels.slim` keeps of a traced work item's state (`_chunk_trace`).
_KEPT = frozenset(("p", "nrm", "smooth", "rays", "dirs", "hits"))
#: The per-point arrays of a work item's cache side (`_cache_part`, `cache_side`).
_SIDE_ARRAYS = ("res", "coeffs", "sh_d", "sh_i", "sh_a", "covered")


@dataclass
class BegunPixels:
    """`begin_pixels`' work in flight: each work item's first half (`_chunk_trace`) on the pool,
    in order, and what `finish_pixels` needs to shade them."""

    system: object
    n: int
    rays: int
    per: int
    jobs: list
    stop: Callable[[], bool] | None = None
    lookup: HitLookup | None = None  # the cache as the hits read it (the resolve's detail rays read it too)
    surfaces: np.ndarray | None = None  # the pixels' smooth surface normals as given, or None
    feeder: _Trickle | None = None  # submits the items one at a time (`begin_pixels(trickle=True)`)

    @property
    def traced(self) -> bool:
        """Every work item's rays are traced (none stopped): what `reshade_pixels` can shade again."""
        return self.rays > 0 and all(j.done() and not j.exception() and "hits" in j.result() for j in self.jobs)

    def slim(self) -> None:
        """Keep of the traced items only what `reshade_pixels` does not make again: each item's
        points, normals and ray count, its rays' directions and hits (28 bytes a ray); not their
        origins (the points pushed off their surfaces), the cache's side or the cache lookup the
        hits read (a table of the whole grid)."""
        for job in self.jobs:
            state = job.result()
            for key in [k for k in state if k not in _KEPT]:
                del state[key]
        self.lookup = None

    def flush(self) -> None:
        """Let every item not yet submitted go to the pool at once."""
        if self.feeder is not None:
            self.feeder.flush()


#: Work items a trickled `begin_pixels` keeps on the pool at once until `flush`.
TRICKLE_ITEMS = 1


class _Trickle:
    """Submits work items to a pool from a thread of its own, at most `TRICKLE_ITEMS` in flight
    until `flush` (then all): each item's result lands in its own future, in order.

    Why: the pool is first in, first out; a frame's pixel rays submitted whole while its centre's
    lamp light still works on the same pool queued that light's later passes behind all of them
    (spheres: the light 0.51 -> 0.74 s, the frame no sooner). A trickle takes what the light
    leaves of the cores and little more (morse_apartment r32: -0.07 s of 1.37; spheres, whose
    light keeps both cores busy: the same)."""

    def __init__(self, pool, calls: list):
        self.futures = [futures.Future() for _ in calls]
        self._pool, self._calls = pool, calls
        self._room = threading.Semaphore(TRICKLE_ITEMS)
        self._thread = threading.Thread(target=self._run, name="hybridgi-trickle", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        for future, (fn, args) in zip(self.futures, self._calls, strict=True):
            self._room.acquire()
            job = self._pool.submit(fn, *args)
            job.add_done_callback(functools.partial(self._landed, future))

    def _landed(self, future: futures.Future, job: futures.Future) -> None:
        self._room.release()
        error = job.exception()
        if error is not None:
            future.set_exception(error)
        else:
            future.set_result(job.result())

    def flush(self) -> None:
        for _ in self._calls:
            self._room.release()


def begin_pixels(system, points: np.ndarray, normals: np.ndarray, rays: int, frame: int,
                 corner_visible: np.ndarray | None = None, lookup: HitLookup | None = None,
                 chunk_rays: int = CHUNK_RAYS, surfaces: np.ndarray | None = None, min_chunks: int = 1,
                 pixels: tuple[np.ndarray, int, int] | None = None,
                 stop: Callable[[], bool] | None = None, trickle: bool = False) -> BegunPixels:
    """The first half of `trace_pixels` (arguments as its own, without `screen`): every work
    item's cache gather and rays traced, submitted to the system's pool now (trickle: one at a
    time until `finish_pixels`, `_Trickle`); `finish_pixels` shades them. Why apart: the rays
    need the cache and the geometry only, the shading the frame's lamp light; a final render
    traces them while its centre's lamp light still runs (morse_apartment: 0.13 s after the
    cache update), then shades them. The same work items and random numbers as one call: the
    result does not change."""
    s = system.settings
    points = np.ascontiguousarray(points, np.float32)
    normals, bad = _usable_normals(normals)
    mended = None
    if surfaces is not None:
        mended = np.array(surfaces, np.float32).reshape(-1, 3)
        mended[bad] = normals[bad]
    n = points.shape[0]
    jobs, per = [], 1
    if n:
        if lookup is None and rays > 0:
            lookup = hit_lookup(system, bounced=s.indirect_quality == MULTI_BOUNCE)
        most = max(1, chunk_rays // max(rays, 8))
        per = min(most, max(-(-n // max(1, min_chunks)), MIN_SPLIT_RAYS // max(rays, 8)))
        starts = range(0, n, per)
        vis = (lambda a: None) if corner_visible is None else (lambda a: corner_visible[a:a + per])
        surf = (lambda a: None) if mended is None else (lambda a: mended[a:a + per])
        tiles = (lambda a: None) if pixels is None or not TILED_RAYS else (
            lambda a: (pixels[0][a:a + per], pixels[1], (s.seed + SEED_OFFSET) * 7919 + pixels[2]))
        trace = _chunk_trace if stop is None else functools.partial(_trace_unless_stopped, stop)
        calls = [(trace, (system, lookup, points[a:a + per], normals[a:a + per], vis(a), rays,
                          frame_rng(s.seed + SEED_OFFSET, frame * 7919 + i), surf(a), tiles(a)))
                 for i, a in enumerate(starts)]
        if trickle:
            feeder = _Trickle(system.updater.pool, calls)
            return BegunPixels(system, n, rays, per, feeder.futures, stop, lookup, surfaces, feeder)
        jobs = [system.updater.pool.submit(fn, *args) for fn, args in calls]
    return BegunPixels(system, n, rays, per, jobs, stop, lookup, surfaces)


def _usable_normals(normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """((n, 3) float32 copy of normals, (n,) bool which were replaced): rays are built from the
    normal without checks (`trusted`), so a pixel without a usable normal (a degenerate
    triangle's zero) gathers around +Z rather than sending zero directions."""
    normals = np.array(normals, np.float32).reshape(-1, 3)
    length = np.linalg.norm(normals, axis=1)
    bad = ~(np.abs(length - 1.0) < 0.1)
    if bad.any():
        normals[bad] = (0.0, 0.0, 1.0)
    return normals, bad


def finish_pixels(begun: BegunPixels, screen: ScreenLight | None = None) -> PixelGI:
    """`trace_pixels`' result from its first half (`begin_pixels`): each work item's rays shaded
    on the pool once traced, with the frame's lamp light per pixel `screen`."""
    begun.flush()
    system, n, per = begun.system, begun.n, begun.per
    steps: dict[str, float] = {}
    # Columns: residual direct rgb, indirect rgb, AO | luminance and AO variances | the cache's
    # direct rgb, indirect rgb, AO. Everything per chunk of pixels on the worker pool, so no
    # per-pixel (n, 8, K, 3) temporaries exist for the whole image at once.
    out = np.zeros((n, 17), np.float32)
    sh_all = np.zeros((n, system.cache.settings.sh_coeffs, 7), np.float32)
    pool = system.updater.pool
    shade = _chunk_shade if begun.stop is None else functools.partial(_shade_unless_stopped, begun.stop)
    shaded = [pool.submit(shade, job.result(), screen) for job in begun.jobs]
    for i, job in enumerate(shaded):
        values, coeffs, times = job.result()
        out[i * per:(i + 1) * per] = values
        sh_all[i * per:(i + 1) * per] = coeffs
        for key, v in times.items():
            steps[key] = steps.get(key, 0.0) + v
    # Residual means (estimate - the cache along the same rays) plus the cache's exact integrals.
    cd, ci, ca = out[:, 9:12], out[:, 12:15], out[:, 15]
    return PixelGI(out[:, 0:3] + cd, out[:, 3:6] + ci, out[:, 6] + ca, cd, ci, ca, variance=out[:, 7:9],
                   indirect_variance=out[:, 16], sh=sh_all, rays=n * begun.rays, steps_ms=steps)


def reshade_pixels(begun: BegunPixels, system, frame: int, corner_visible: np.ndarray | None = None,
                   lookup: HitLookup | None = None, screen: ScreenLight | None = None,
                   stop: Callable[[], bool] | None = None, side: dict | None = None) -> PixelGI:
    """An earlier pass's rays shaded again over the system's current cache and lamp light, none
    of them traced again (their hits' shadow and near-bounce rays are): `trace_pixels`' result
    for the same points and directions, from `begun`, that pass's traced work items
    (`BegunPixels.traced`). For a lamp edit of a still view, whose geometry and pixels hold: the
    trace of the rays is a third of a pass (atrium 640x360: 350 of ~1000 ms of the pool's
    threads). frame : seeds the shading's random numbers (a stream apart from the traced rays');
    corner_visible : (n, 8) as `trace_pixels` takes it; lookup : the current cache as the hits
    read it (None: built here); screen, stop : as `trace_pixels`'. side : the current cache's
    `cache_side` at the pass's points, if made already (pixels without smooth normals only: a
    normal map's kernel is the pass's own). The result counts no rays."""
    s = system.settings
    if lookup is None and begun.rays > 0 and begun.n:
        lookup = hit_lookup(system, bounced=s.indirect_quality == MULTI_BOUNCE)
    pool = system.updater.pool
    per = begun.per
    jobs = []
    for i, job in enumerate(begun.jobs):
        state = job.result()
        vis = None if corner_visible is None else corner_visible[i * per:(i + 1) * per]
        if "hits" not in state:
            raise ValueError("reshade_pixels: a work item without traced rays (keep passes that ran to their end)")
        rng = frame_rng(s.seed + SEED_OFFSET, RESHADE_FRAME + frame * 7919 + i)
        part = None
        if side is not None and state["smooth"] is None:
            part = {key: side[key][i * per:(i + 1) * per] for key in _SIDE_ARRAYS}
            part.update(k=side["k"], times={})
        jobs.append(pool.submit(_restate, state, system, lookup, vis, rng, part))
    again = BegunPixels(system, begun.n, begun.rays, per, jobs, stop, lookup, begun.surfaces)
    gi = finish_pixels(again, screen)
    gi.rays = 0
    return gi


def cache_side(system, points: np.ndarray, normals: np.ndarray, corner_visible: np.ndarray | None = None,
               chunk: int = 8192) -> dict:
    """The cache's side of `trace_pixels` at points (n, 3) with normals (n, 3), without rays: per
    point its gather (`_cache_part`: res[:, 9:16] the cache's direct rgb, indirect rgb and AO, as
    `PixelGI.channels()[1]`; the blended SH), in blocks of `chunk` points on the system's pool. A
    lamp edit's carry reads it and the re-shade of the view's kept rays over the same cache takes
    it (`reshade_pixels(side=)`) instead of gathering again."""
    points = np.ascontiguousarray(points, np.float32)
    normals = _usable_normals(normals)[0]  # as `begin_pixels` mends them
    pool = system.updater.pool
    jobs = [pool.submit(_cache_part, system, points[a:a + chunk], normals[a:a + chunk],
                        None if corner_visible is None else corner_visible[a:a + chunk], None)
            for a in range(0, points.shape[0], chunk)]
    parts = [j.result() for j in jobs]
    if not parts:
        parts = [_cache_part(system, points, normals, corner_visible, None)]
    side = {key: np.concatenate([part[key] for part in parts]) for key in _SIDE_ARRAYS}
    side["k"] = parts[0]["k"]
    return side


def _shade_unless_stopped(stop: Callable[[], bool], state: dict, screen: ScreenLight | None = None):
    """`_chunk_shade`, or zeros for the pixels once stop() holds (polled only for an item whose
    rays were traced): a pass dropped after its rays were traced skips their shading, the larger
    part of its work (a viewport's lamp edit waited for it: Cornell's image after a light move
    1.0 -> 1.5 s)."""
    if "hits" in state and stop():
        m, k = state["p"].shape[0], state["coeffs"].shape[1]
        return np.zeros((m, 17), np.float32), np.zeros((m, k, 7), np.float32), {}
    return _chunk_shade(state, screen)


def _trace_unless_stopped(stop: Callable[[], bool], system, lookup, p, *args):
    """`_chunk_trace`, or, once stop() holds, a state without rays whose shading is zeros for the
    pixels (`trace_pixels(stop=)`: the caller throws them away)."""
    if not stop():
        return _chunk_trace(system, lookup, p, *args)
    return dict(res=np.zeros((p.shape[0], 17), np.float32),
                coeffs=np.zeros((p.shape[0], system.cache.settings.sh_coeffs, 7), np.float32), times={})


def _chunk_trace(system, lookup: HitLookup | None, p, nrm, corner_visible, rays, rng, surf=None, tiles=None) -> dict:
    """Worker, a work item's first half: the cache's gather at the pixels and their rays traced
    (what needs the cache and the geometry, not the frame's lamp light). Its state for
    `_chunk_shade`, whose random numbers follow on from the same generator.

    Bent normals (a normal map's): the rays bring their light times Cycles' bump shadowing term,
    so the cache's part is the same lobe's (`bump.irradiance_kernel`: nothing from below the
    smooth surface) and the control variate is weighed by the same term, ray by ray: the
    residual is then what the cache misses, not the light under the surface the cosine of the
    bent normal would read (3.2 x the ridges' Diffuse Indirect)."""
    s = system.settings
    m = p.shape[0]
    tracer = system.tracer
    eps = np.float32(tracer.epsilon)
    # A normal map bends the shading normal away from the surface: rays leave along the smooth
    # normal, and each brings its light times Cycles' bump shadowing term (none from below).
    smooth = surf
    if smooth is None and has_normal_maps(system.scene) and m:
        smooth = smooth_normals(system.surfaces, tracer, p, nrm, float(eps))
    state = _cache_part(system, p, nrm, corner_visible, smooth)
    if rays <= 0:
        return state
    times = state["times"]
    tic = time.perf_counter()
    uv = None if tiles is None else tiled_uv(tiles[0], tiles[1], rays, tiles[2])
    dirs = cosine_directions(nrm, rays, rng, uv).reshape(-1, 3)
    origins = _ray_origins(p, nrm, smooth, eps, rays)
    tfar = np.float32(s.ray_length) if s.ray_length > 0 else np.float32(np.inf)
    hits = tracer.intersect(origins, dirs, tfar, trusted=True)
    times["trace"] = (time.perf_counter() - tic) * 1e3
    state.update(system=system, lookup=lookup, p=p, nrm=nrm, rays=rays, rng=rng, smooth=smooth, dirs=dirs,
                 origins=origins, hits=hits)
    return state


def _ray_origins(p: np.ndarray, nrm: np.ndarray, smooth: np.ndarray | None, eps: np.float32, rays: int) -> np.ndarray:
    """(m rays, 3) origins of the `rays` rays of each pixel p (m, 3): pushed off along the smooth
    surface normal (`nrm` where no normal map bends it) by eps. One formula for `_chunk_trace`
    and `_restate`, whose re-shade must start its rays where the trace started them."""
    return np.repeat(p + (nrm if smooth is None else smooth) * eps, rays, axis=0)


def _cache_part(system, p, nrm, corner_visible, smooth) -> dict:
    """The cache's side of a work item (`_chunk_trace`): its SH gathered at the pixels p (m, 3)
    with normals nrm, their irradiance (the control variate's exact integral, res[:, 9:16]) and
    the blended SH (coeffs); `smooth` the smooth normals under bent ones (or None)."""
    times = {}
    tic = time.perf_counter()
    m = p.shape[0]
    res = np.zeros((m, 17), np.float32)
    levels = getattr(system, "levels", None)
    sh_d, sh_i, sh_a, covered = (cache_sh_at(system.cache, p, nrm, corner_visible) if levels is None
                                 else levels.sh_at(p, nrm, corner_visible))
    k = sh_d.shape[1]
    kernel = None if smooth is None else irradiance_kernel(smooth, nrm, 2 if k == 9 else 1)
    # The cache's own irradiance at the pixels, what the GPU gather reads (unclamped here: the
    # control variate must be the exact integral of the SH used below).
    if kernel is None:
        res[:, 9:12] = sh.irradiance(sh_d, nrm)
        res[:, 12:15] = sh.irradiance(sh_i, nrm)
    else:
        res[:, 9:12] = np.einsum("mk,mkc->mc", kernel, sh_d)
        res[:, 12:15] = np.einsum("mk,mkc->mc", kernel, sh_i)
    if kernel is None:
        ao = sh.irradiance(sh_a[..., None], nrm)[:, 0] / np.float32(np.pi)
    else:  # the bent lobe's visibility above the smooth surface (`_ao_rays`)
        ao = np.einsum("mk,mk->m", kernel, sh_a) * _ao_norm(kernel)
    res[:, 15] = np.where(covered, ao, np.float32(1.0))
    coeffs = np.concatenate([sh_d, sh_i, sh_a[..., None]], axis=2)
    coeffs[~covered, :, 6] = 0.0
    coeffs[~covered, 0, 6] = np.float32(1.0 / SH_Y00)  # open: constant visibility 1
    times["cache_sh"] = (time.perf_counter() - tic) * 1e3
    return dict(res=res, coeffs=coeffs, times=times, sh_d=sh_d, sh_i=sh_i, sh_a=sh_a, covered=covered, k=k)


def _restate(state: dict, system, lookup: HitLookup | None, corner_visible, rng, part: dict | None = None) -> dict:
    """Worker: a traced work item's state (`_chunk_trace`) over the system's current cache: its
    rays and hits as they were, the cache's side gathered again (or `part`, its rows of a
    `cache_side` over the same cache), the hits to read `lookup` and draw their shading's random
    numbers from `rng` (`reshade_pixels`). The arrays of `part` are copied: the shading writes
    into res."""
    if part is None:
        fresh = _cache_part(system, state["p"], state["nrm"], corner_visible, state["smooth"])
    else:
        fresh = {key: (v.copy() if isinstance(v, np.ndarray) else v) for key, v in part.items()}
    if "origins" not in state:  # slimmed (`BegunPixels.slim`): made again as `_chunk_trace` made them
        fresh["origins"] = _ray_origins(state["p"], state["nrm"], state["smooth"],
                                        np.float32(system.tracer.epsilon), state["rays"])
    return {**state, **fresh, "system": system, "lookup": lookup, "rng": rng}


def _chunk_shade(state: dict, screen: ScreenLight | None = None):
    """Worker, a work item's second half: the traced rays' hits shaded (with the frame's lamp light
    per pixel, `screen`): (m, 17) of m pixels: mean residuals pi/N sum (L - L_cache) (direct rgb,
    indirect rgb, AO as 1/N sum (v - V_cache)), the variances of the luminance and AO means, the
    cache gather's direct rgb, indirect rgb and AO, the variance of the indirect luminance mean;
    (m, K, 7) the blended SH; and step times."""
    res, coeffs, times = state["res"], state["coeffs"], state["times"]
    if "hits" not in state:
        return res, coeffs, times  # no rays
    system, lookup, p, nrm, rays, rng = (state[k] for k in ("system", "lookup", "p", "nrm", "rays", "rng"))
    sh_d, sh_i, sh_a, covered, smooth, k = (state[k] for k in ("sh_d", "sh_i", "sh_a", "covered", "smooth", "k"))
    dirs, origins, hits = state["dirs"], state["origins"], state["hits"]
    s = system.settings
    m = p.shape[0]
    tic = time.perf_counter()
    near = np.float32(NEAR_BOUNCE_CELLS * system.cache.grid.cell_size)
    # A sky that varies with direction: where it is open, its exact light less what the rays
    # found blocked (`sky_ratio`), which needs the sky in every ray's direction, blocked or not.
    world = system.updater.scene.world
    sky_open = sky_irradiance(world) if smooth is None and s.indirect_quality != AO_ONLY else None
    sky = unshadowed = share = None
    if sky_open is not None:
        # The sky's unshadowed light and the open-sky estimate's weight against the cache's
        # direct light (res[:, 9:12]), which the rays do not change.
        unshadowed = sky_open.irradiance(nrm)
        share = open_share(res[:, 9:12], unshadowed)
        sky = _sky_along(world, dirs, hits, share, rays)
    radiance = hit_radiance(system, lookup, origins, dirs, hits, rng, times, screen=screen, near=near,
                            near_rng=np.random.default_rng(rng.bit_generator.seed_seq.spawn(1)[0]), sky=sky,
                            sampled_emitters=screen is not None and screen.emitters_sampled)
    visible = (hits.t > s.ao_distance).astype(np.float32)
    # Control variate: the cache's radiance SH along the same rays. Linear in the SH, so its mean
    # over a pixel's rays is the SH of the pixel's mean basis vector (no per-ray products).
    y = sh.basis(dirs, 2 if k == 9 else 1).reshape(m, rays, k)
    y_mean = mean_over_rays(y)  # (m, K)
    y_lit = y
    if smooth is not None:
        term = shadowing_term(np.repeat(smooth, rays, axis=0), np.repeat(nrm, rays, axis=0), dirs)
        radiance *= term[:, None]
        y_lit = y * term.reshape(m, rays, 1)
    y_lit_mean = y_mean if smooth is None else mean_over_rays(y_lit)
    cv_d = np.einsum("mk,mkc->mc", y_lit_mean, sh_d)
    cv_i = np.einsum("mk,mkc->mc", y_lit_mean, sh_i)
    # AO as the smooth surface's where a map bends the normal (`_ao_rays`).
    ao_w, y_ao = _ao_rays(smooth, nrm, dirs, y, y_mean, m, rays)
    cv_a = np.where(covered, np.einsum("mk,mk->m", y_ao, sh_a), np.float32(1.0))  # uncovered: ao_c = 1
    r = radiance.reshape(m, rays, 6)
    r_mean = mean_over_rays(r)  # one reduction over the rays for both bands
    res[:, 0:3] = (r_mean[:, 0:3] - cv_d) * np.float32(np.pi)
    res[:, 3:6] = (r_mean[:, 3:6] - cv_i) * np.float32(np.pi)
    ao_mean = mean_over_rays(visible.reshape(m, rays)) if ao_w is None else (
        (visible.reshape(m, rays) * ao_w).sum(axis=1) / np.maximum(ao_w.sum(axis=1), np.float32(1e-6)))
    res[:, 6] = ao_mean - cv_a
    # Variance of the two filter guides' means (luminance of all light, AO), from the rays' own
    # spread around their control variate: what the filter may average away as noise.
    lum_d = r[..., 0:3] @ LUMA - np.matmul(y_lit, (sh_d @ LUMA)[..., None])[..., 0]
    if sky_open is not None:
        lum_d = _open_sky_band(res, lum_d, unshadowed, share, sky, hits, radiance, rays)
    lum_i = r[..., 3:6] @ LUMA - np.matmul(y_lit, (sh_i @ LUMA)[..., None])[..., 0]
    ao = visible.reshape(m, rays) - np.where(covered[:, None], np.matmul(y, sh_a[..., None])[..., 0], np.float32(1.0))
    of_mean = np.float32(1.0 / max(rays - 1, 1))  # sample variance / N
    res[:, 7] = (lum_d + lum_i).var(axis=1) * np.float32(np.pi**2) * of_mean
    res[:, 16] = lum_i.var(axis=1) * np.float32(np.pi**2) * of_mean
    res[:, 8] = ao.var(axis=1) * of_mean
    _more_ao_rays(system, res, p, nrm, ao_mean, sh_a, covered, rays, rng, times, smooth)
    times["shade"] = (time.perf_counter() - tic) * 1e3 - times.get("shadow", 0.0)
    return res, coeffs, times


def _ao_norm(kernel: np.ndarray) -> np.ndarray:
    """(n,) float32 1 / the integral of a lobe `kernel` (n, K) (`bump.irradiance_kernel`) over a
    visibility of 1 everywhere (the constant's SH is 1 / SH_Y00 in its first coefficient): its
    kernel . sh_a times this is the lobe's mean visibility, 1 under an open sky."""
    return (np.float32(SH_Y00) / np.maximum(kernel[:, 0].astype(np.float32), np.float32(1e-6))).astype(np.float32)


def _ao_rays(smooth: np.ndarray | None, nrm: np.ndarray, dirs: np.ndarray, y: np.ndarray, y_mean: np.ndarray,
             m: int, rays: int):
    """((m, rays) float32 weights of the rays in the AO pass's mean, or None: equal; (m, K) their
    weighted mean SH basis, the AO control variate's). Where a normal or bump map bends a pixel's
    normal, the bent lobe's rays that dive under the surface find the surface itself: counted,
    they darkened the AO (a floor bumped by Wave bands, 128x96: 0.679, Cycles 0.740 as unbumped).
    Cycles' AO does not count them, so AO is the mean over the bent lobe's rays above the smooth
    surface, and the cache's part the same lobe's mean visibility (`_ao_norm`)."""
    if smooth is None:
        return None, y_mean
    d = dirs.reshape(m, rays, 3)
    cos_s = np.einsum("mrc,mc->mr", d, smooth)
    w = (cos_s > 0.0).astype(np.float32)
    total = np.maximum(w.sum(axis=1), np.float32(1e-6))
    return w, np.einsum("mr,mrk->mk", w, y) / total[:, None]


def _sky_along(world, dirs: np.ndarray, hits, share: np.ndarray, rays: int) -> np.ndarray:
    """(m rays, 3) float32 the world's radiance along the rays `_open_sky_band` and `hit_radiance`
    read it on: every ray of the pixels that take the open-sky estimate (its weight `share` (m,),
    `open_share`, above 0), and the rays that escape; 0 along the rest, which the band weighs by
    0. Why: a room's pixels see the sky through a window only, and the map's lookups along all
    of their blocked rays were ~0.3 s of CPU per 320x180 frame."""
    need = np.repeat(share > 0, rays) | (hits.prim < 0)
    if need.all():
        return world.radiance(dirs)
    sky = np.zeros((dirs.shape[0], 3), np.float32)
    sel = np.flatnonzero(need)
    if sel.size:
        sky[sel] = world.radiance(dirs[sel])
    return sky


def _open_sky_band(res: np.ndarray, lum_cv: np.ndarray, unshadowed: np.ndarray, share: np.ndarray, sky: np.ndarray,
                   hits, radiance: np.ndarray, rays: int) -> np.ndarray:
    """The direct band of m pixels under a sky map (`_chunk`): where the cache finds the sky mostly
    open, its exact unshadowed light less what the rays found blocked, plus the emitters they hit
    (`sky_ratio`), blended into the control-variate estimate by that openness (a weight the rays
    do not set: unbiased). Writes res[:, 0:3] (the residual against the cache's res[:, 9:12]) and
    returns the (m, rays) per-ray luminance terms of the blend (lum_cv: the control variate's).
    unshadowed : (m, 3) the sky's unshadowed irradiance at the pixels (`SkyIrradiance`); share :
    (m,) the open estimate's weight (`open_share`)."""
    m = res.shape[0]
    escaped = hits.prim < 0
    emitted = np.where(escaped[:, None], np.float32(0.0), radiance[:, 0:3]).reshape(m, rays, 3)
    sky_light, sky_terms = open_sky_estimate(unshadowed, sky, escaped, rays)
    share = share[:, None]
    open_res = sky_light + emitted.mean(axis=1) * np.float32(np.pi) - res[:, 9:12]
    res[:, 0:3] = share * open_res + (1 - share) * res[:, 0:3]
    return share * (sky_terms + emitted @ LUMA) + (1 - share) * lum_cv


def hit_radiance(system, lookup: HitLookup | None, origins: np.ndarray, dirs: np.ndarray, hits, rng,
                 times: dict | None = None, glossy_lamps: bool = True, screen: ScreenLight | None = None,
                 near: float = 0.0, near_rng: np.random.Generator | None = None, depth: int | None = None,
                 sky: np.ndarray | None = None, sampled_emitters: bool = False, level: int = 0) -> np.ndarray:
    """(N, 6) float32 radiance coming back along rays (origins, dirs (N, 3)) from their `hits`:
    rgb straight from the world or an emitter (what Cycles counts as direct light) | rgb the hit
    surface reflects (its lamp light through shadow rays, plus the cache read at the hit for the
    further bounces), as probe-ray hits are shaded (`update.py`). Zero with AO-only quality.
    times : step times to add the shadow rays' ("shadow") to. glossy_lamps : False lights a hit's
    glossy share (which the cache reflects as diffuse, `shading.SurfaceTable.set_materials`) by
    the cache's light only, not the lamps': a reflection ray sees a glossy surface from one
    direction, where a lamp shows only in the highlight, not spread over the surface. screen :
    the frame's lamp irradiance per pixel, read at hits the camera sees instead of their own
    shadow rays (`screen_light`). near : hits nearer than this (world units) take their further
    bounces from one ray of their own drawn from near_rng (`_near_bounce`), not from the cache, up
    to `depth` bounces (None: NEAR_BOUNCE_DEPTH, EMITTER_NEAR_BOUNCE_DEPTH with emissive surfaces).
    sky : (N, 3) the world's radiance along the rays if the caller has it (`World.radiance`).
    sampled_emitters : the rays leave pixels whose direct light samples the emissive triangles
    (`emitters.py`): what they find of those is not counted again (further bounces still are).
    level : near bounces already traced before these rays (from NEAR_BOUNCE_DEPTH on, the near
    hits go on by Russian roulette, `_near_roulette`)."""
    s, scene = system.settings, system.updater.scene
    if depth is None:
        depth = EMITTER_NEAR_BOUNCE_DEPTH if scene.surfaces.emissive else NEAR_BOUNCE_DEPTH
    radiance = np.zeros((dirs.shape[0], 6), np.float32)
    if s.indirect_quality == AO_ONLY:
        return radiance
    hit = np.flatnonzero(hits.prim >= 0)
    if scene.world.any:
        if sky is not None:
            radiance[:, 0:3] = sky
        elif hit.size == 0:
            radiance[:, 0:3] = scene.world.radiance(dirs)
        elif hit.size < dirs.shape[0]:
            # Only along the rays that miss (a sky map's lookup is ~1/5 of the hits' shading).
            miss = np.flatnonzero(hits.prim < 0)
            radiance[miss, 0:3] = scene.world.radiance(np.take(dirs, miss, axis=0))
    if hit.size:
        # np.take: row gathers ~5x faster than fancy indexing (numpy 1.26).
        prim, hit_dirs = np.take(hits.prim, hit), np.take(dirs, hit, axis=0)
        hit_u, hit_v = np.take(hits.u, hit), np.take(hits.v, hit)
        surf = scene.surfaces.probe_hits(prim, hit_u, hit_v, hit_dirs)
        radiance[hit, 0:3] = (scene.surfaces.diffuse_emission(surf.emission, prim) if sampled_emitters
                              else surf.emission)
        position = hit_dirs * np.take(hits.t, hit)[:, None]
        position += np.take(origins, hit, axis=0)
        ts = time.perf_counter()
        e_in, seen = _lamp_light_at_hits(system, screen, position, surf.normal, rng)
        if seen is not None and seen.size and scene.surfaces.bends:
            # Read from the image, the light of a normal-mapped hit is its bent normals' already:
            # the brdf's share for the bend (`SurfaceTable.bend`) must not take it twice.
            e_in[seen] /= scene.surfaces.bend_of(np.take(prim, seen))[:, None]
        if times is not None:
            times["shadow"] = times.get("shadow", 0.0) + (time.perf_counter() - ts) * 1e3
        brdf = surf.brdf
        lamp, lamp_rows = None, None  # lamp light the hits reflect apart from `brdf` (at lamp_rows; None: all)
        if not glossy_lamps:
            glossy_part = scene.surfaces.glossy_brdf(prim, hit_u, hit_v)
            lamp = e_in * (brdf - glossy_part)
            e_in = np.zeros_like(e_in)
            _add_shiny_highlights(system, lamp, glossy_part, brdf, prim, position, surf.normal, hit_dirs, rng)
        else:
            shiny = shiny_hits(scene.surfaces, prim, hit_u, hit_v, brdf)
            if shiny is not None:
                # Metals show a lamp only in their highlight, as a reflection ray's hit does.
                lamp_rows, glossy_part = shiny
                sub = [np.take(a, lamp_rows, axis=0) for a in (brdf, prim, position, surf.normal, hit_dirs)]
                lamp = np.take(e_in, lamp_rows, axis=0) * (sub[0] - glossy_part)
                e_in[lamp_rows] = 0.0
                _add_shiny_highlights(system, lamp, glossy_part, *sub, rng)
        # Further bounces read the cache at the hit, as probe-ray hits do; hits nearer than
        # `near` trace them one ray further instead (`_near_bounce`).
        # The lamp light alone, to tell the cache's from it (`hit_glossy`, at the first hits only:
        # near bounces' own hits, level > 0, keep the lobes' diffuse stand-in).
        lamp_only = e_in.copy() if lookup is not None and level == 0 else None
        cells = cache_light = None  # the cache cells the hits read and their light, where all of them do
        if lookup is not None:
            close = np.take(hits.t, hit) < near if near > 0 and near_rng is not None else None
            if (close is None or not close.any()) and isinstance(lookup, HitLookup):
                cells = lookup.cells(position, surf.normal)
                cache_light = lookup.evaluate(cells, monomials(surf.normal, lookup.terms)).T
                e_in += cache_light
            elif close is None or not close.any():
                e_in += lookup.irradiance(position, surf.normal).T
            elif level < NEAR_BOUNCE_DEPTH:
                far, close = np.flatnonzero(~close), np.flatnonzero(close)
                if far.size:
                    e_in[far] += lookup.irradiance(np.take(position, far, axis=0), np.take(surf.normal, far, axis=0)).T
                e_in[close] += _near_bounce(system, lookup, np.take(position, close, axis=0),
                                            np.take(surf.normal, close, axis=0), near_rng, times, screen, near, depth,
                                            level)
            else:
                _near_roulette(system, lookup, e_in, position, surf.normal, close, near_rng, times, screen, near,
                               depth, level)
        shift = None  # what the glossy lobes reflect of the cache's light towards the ray, less their stand-in's
        if lamp_only is not None:
            shift = e_in - lamp_only
            shift *= scene.surfaces.glossy_brdf(prim, hit_u, hit_v)
            shift *= hit_glossy.view_ratio(system, lookup, prim, position, surf.normal, hit_dirs, cells,
                                           cache_light) - np.float32(1.0)
        e_in *= brdf
        if shift is not None:
            e_in += shift
        if lamp is not None and lamp_rows is None:
            e_in += lamp
        elif lamp is not None:
            e_in[lamp_rows] += lamp
        radiance[hit, 3:6] = e_in  # one scatter (`+=` on fancy indices gathers and scatters)
    return radiance


def _add_shiny_highlights(system, lamp: np.ndarray, glossy_part: np.ndarray, brdf: np.ndarray, prim: np.ndarray,
                          position: np.ndarray, normal: np.ndarray, dirs: np.ndarray, rng) -> None:
    """lamp (m, 3) += the lamps' light that the glossy lobes of the shiny hits (those whose glossy
    share is most of their brdf: metals) reflect back along the rays `dirs` (m, 3), with its
    shadow rays (`shiny.highlights`). Why: a reflection ray that meets
    a metal sees the lamps in its highlight, not spread over it; without this its lamp light was
    dropped whole (a rough metal floor reflecting a rough metal wall under a sun: Glossy Indirect
    0.100 against Cycles' 0.291). Dielectric coats keep the cache's light only: their highlight
    is a few percent of what they reflect."""
    shiny = np.flatnonzero(shiny_share(glossy_part, brdf))
    if shiny.size == 0 or not system.scene.lights:
        return
    lamp[shiny] += highlights(system.scene.lights, system.glossy_materials, system.tracer,
                              system.updater.scene.surfaces.material_index, np.take(prim, shiny),
                              np.take(position, shiny, axis=0), np.take(normal, shiny, axis=0),
                              np.take(dirs, shiny, axis=0), rng)


def _near_bounce(system, lookup, position: np.ndarray, normal: np.ndarray, rng: np.random.Generator,
                 times: dict | None, screen: ScreenLight | None, near: float = 0.0, depth: int = 1,
                 level: int = 0) -> np.ndarray:
    """(m, 3) irradiance of the further bounces at hits (position, normal (m, 3)) from one cosine
    ray each: pi x the radiance it brings back (world or emitter; with Multi Bounce also its hit's
    lamp light and the cache read there), the one-sample estimate of what `lookup` reads from the
    cell in front of the hit. Unbiased against the cache's smoothing where the clutter is finer
    than a cell; its noise goes into the pixel's ray spread, which the residual filter weighs."""
    tic = time.perf_counter()
    eps = np.float32(system.tracer.epsilon)
    dirs = cosine_directions(normal, 1, rng).reshape(-1, 3)
    origins = position + normal * eps
    s = system.settings
    tfar = np.float32(s.ray_length) if s.ray_length > 0 else np.float32(np.inf)
    hits = system.tracer.intersect(origins, dirs, tfar, trusted=True)
    if s.indirect_quality == MULTI_BOUNCE:
        rad = hit_radiance(system, lookup, origins, dirs, hits, rng, times, screen=screen, near=near,
                           near_rng=rng if depth > 1 else None, depth=depth - 1, level=level + 1)
        e = rad[:, 0:3] + rad[:, 3:6]
    else:  # one bounce: the hit's sky and emitters only, as the direct-only lookup holds
        e = hit_radiance(system, None, origins, dirs, hits, rng, None, screen=screen)[:, 0:3]
    e *= np.float32(np.pi)
    if times is not None:
        times["near_bounce"] = times.get("near_bounce", 0.0) + (time.perf_counter() - tic) * 1e3
    return e


def _near_roulette(system, lookup, e_in: np.ndarray, position: np.ndarray, normal: np.ndarray, close: np.ndarray,
                   rng: np.random.Generator, times: dict | None, screen: ScreenLight | None, near: float, depth: int,
                   level: int) -> None:
    """e_in (m, 3) += the further bounces at hits (position, normal) past NEAR_BOUNCE_DEPTH near
    bounces (an emitter's contact, `EMITTER_NEAR_BOUNCE_DEPTH`): every hit reads the cache, and a
    near hit (close (m,) bool) traces its `_near_bounce` with probability NEAR_SURVIVAL, adding
    (traced - cache) / NEAR_SURVIVAL: unbiased against the traced estimate, as a path tracer's
    roulette is. Why: the rays between a sphere and its floor keep meeting near hits (spheres:
    78k, 48k, 32k, 24k, 18k, 15k over the six levels), and the deep levels cost as much as the first
    two while each round brings back ~0.5 of the last."""
    cache = lookup.irradiance(position, normal).T
    e_in += cache
    traced = np.flatnonzero(close & (rng.random(close.size, dtype=np.float32) < np.float32(NEAR_SURVIVAL)))
    if traced.size:
        bounce = _near_bounce(system, lookup, np.take(position, traced, axis=0), np.take(normal, traced, axis=0), rng,
                              times, screen, near, depth, level)
        e_in[traced] += (bounce - np.take(cache, traced, axis=0)) * np.float32(1.0 / NEAR_SURVIVAL)


def _lamp_light_at_hits(system, screen: ScreenLight | None, position: np.ndarray, normal: np.ndarray,
                        rng) -> tuple[np.ndarray, np.ndarray | None]:
    """((m, 3) lamp irradiance at hits (position, normal (m, 3)), the indices of the hits it was
    read for from `screen` or None): read from `screen` where the camera sees the hit's surface,
    from the hit's own light samples and shadow rays elsewhere."""
    scene, tracer, s = system.updater.scene, system.tracer, system.settings
    eps = float(np.float32(tracer.epsilon))
    if screen is None or not scene.lights:
        return direct_irradiance(scene.lights, position, normal, tracer, rng, samples=s.light_samples,
                                 epsilon=eps, sun_disc=False, lamp_budget=HIT_LAMP_BUDGET), None
    found, light = screen.lookup(position, normal)
    e_in = np.empty((position.shape[0], 3), np.float32)
    e_in[found] = light
    rest = np.ones(position.shape[0], bool)
    rest[found] = False
    rest = np.flatnonzero(rest)
    if rest.size:
        e_in[rest] = direct_irradiance(scene.lights, np.take(position, rest, axis=0), np.take(normal, rest, axis=0),
                                       tracer, rng, samples=s.light_samples, epsilon=eps, sun_disc=False,
                                       lamp_budget=HIT_LAMP_BUDGET)
    return e_in, found


def _more_ao_rays(system, res, p, nrm, ao_mean, sh_a, covered, rays, rng, times, smooth=None) -> None:
    """Adaptive AO sampling: pixels whose AO estimate is noisy relative to its value (the rays'
    standard error over the AO above AO_RELATIVE_NOISE: low, partly occluded AO, what a relative
    error weighs most; open pixels are left alone) trace AO_EXTRA x rays more occlusion-only rays
    (short, no shading); their AO residual and its variance become those of all their rays.
    smooth : the smooth surface normals where maps bend `nrm` (rays below it are not counted,
    `_ao_rays`), else None."""
    extra = int(round(AO_EXTRA * rays))
    rel = np.sqrt(np.maximum(res[:, 8], 0.0)) / np.maximum(ao_mean, np.float32(1e-3))
    sel = np.flatnonzero((rel > AO_RELATIVE_NOISE) & (ao_mean > 0.0))
    if extra <= 0 or sel.size == 0:
        return
    tic = time.perf_counter()
    tracer, s = system.tracer, system.settings
    k = sh_a.shape[1]
    eps = np.float32(tracer.epsilon)
    dirs = cosine_directions(nrm[sel], extra, rng)
    origins = np.repeat(p[sel] + nrm[sel] * eps, extra, axis=0)
    blocked = tracer.occluded(origins, dirs.reshape(-1, 3), np.float32(s.ao_distance), trusted=True)
    vis = (~np.asarray(blocked, bool)).astype(np.float32).reshape(sel.size, extra)
    y = sh.basis(dirs.reshape(-1, 3), 2 if k == 9 else 1).reshape(sel.size, extra, k)
    if smooth is None:
        vis_mean, y_mean = vis.mean(axis=1), y.mean(axis=1)
    else:
        w, y_mean = _ao_rays(smooth[sel], nrm[sel], dirs.reshape(-1, 3), y, None, sel.size, extra)
        vis_mean = (vis * w).sum(axis=1) / np.maximum(w.sum(axis=1), np.float32(1e-6))
    cv = np.where(covered[sel], np.einsum("mk,mk->m", y_mean, sh_a[sel]), np.float32(1.0))
    share = np.float32(extra / (rays + extra))
    res[sel, 6] = (1 - share) * res[sel, 6] + share * (vis_mean - cv)
    res[sel, 8] *= 1 - share  # the variance of a mean over rays + extra rays
    times["ao_rays"] = (time.perf_counter() - tic) * 1e3


def filter_residual(residual: np.ndarray, position: np.ndarray, normal: np.ndarray, valid: np.ndarray,
                    camera: np.ndarray, passes: int = 3, plane_sigma: float = 0.02,
                    normal_power: float = 8.0, variance: np.ndarray | None = None,
                    noise_sigma: float = NOISE_SIGMA, pool=None, stretch: float | None = None) -> np.ndarray:
    """Edge-aware a-trous filter of an (h, w, 7) image of residuals (direct rgb, indirect rgb, AO)
    at the GI resolution; without a variance, of an (h, w, c) image of any c channels (one
    weight for all of them).

    position (h, w, 3) world, normal (h, w, 3) unit, valid (h, w) bool (background pixels are
    neither read nor written), camera (3,) the eye (plane distances are measured as a share of
    the view distance, as the bilateral upsampling does). Pass i uses taps 2^i pixels apart;
    a tap's weight is the B3 spline x exp(-(plane distance / (plane_sigma x view distance))^2)
    x max(0, n_p . n_q)^normal_power: a tap on another surface, or on the same surface's other
    side of a crease, does not count. normal_power : one exponent, or an (h, w) float32 image of
    each pixel's own (its taps' weight).

    variance : (h, w, 2) variances of the pixels' luminance (of direct + indirect) and AO, or
    (h, w, 3) of the luminance of all light, of the indirect light alone and AO (a second guide
    for the colour channels: a tap must agree in both, so a contact's faint bounce light is not
    averaged away as noise of the far brighter sky light beside it, while direct and indirect
    still share one weight: their noise is anticorrelated, a ray that sees the sky sees no wall,
    and split weights would leave Combined noisier), or None. Given, taps also stop where the residual differs by more than noise_sigma standard deviations of the noise (SVGF, Schied et al. 2017; the variance filtered along with the
    image): a contact's correction on a plane stays at the contact instead of spreading over
    the plane, while the noise around it averages out.

    pool : an executor; given, bands of rows are filtered on it side by side (each with a halo
    of the rows the passes reach, so the result is the same as in one piece).

    stretch : given, a tap's weight also falls off where it lies farther from the pixel than the
    same screen step spans on a surface facing the camera (`_stretch_into`, STRETCH): a grazing
    surface's pixels span far more of it than a facing one's. None: no such term.
    """
    h, w = valid.shape
    halo = 2 * ((1 << max(passes, 0)) - 1)
    if pool is not None and passes > 0 and h >= 4 * halo + BAND_MIN_ROWS:
        return _filter_in_bands(pool, halo, residual, position, normal, valid, camera, passes, plane_sigma,
                                normal_power, variance, noise_sigma, stretch)
    out = np.where(valid[..., None], residual, 0.0).astype(np.float32)
    if passes <= 0:
        return out
    # Channel-first planes: every tap is a few whole-image multiply-adds on contiguous rows.
    pos = np.ascontiguousarray(np.moveaxis(np.asarray(position, np.float32), -1, 0))
    nrm = np.ascontiguousarray(np.moveaxis(np.asarray(normal, np.float32), -1, 0))
    img = np.ascontiguousarray(np.moveaxis(out, -1, 0))
    var = None
    if variance is not None:
        var = np.ascontiguousarray(np.moveaxis(np.where(valid[..., None], variance, 0.0), -1, 0), np.float32)
    dist = np.sqrt(sum((pos[k] - np.float32(camera[k])) ** 2 for k in range(3)))
    inv_sigma = np.where(valid, 1.0 / np.maximum(plane_sigma * dist, 1e-12), 0.0).astype(np.float32)
    view = None
    if stretch is not None:
        # Unit view directions: the chord between two pixels' directions is their angle on screen.
        inv_dist = np.where(valid, np.float32(1.0) / np.maximum(dist, np.float32(1e-30)), np.float32(0.0))
        view = np.stack([(pos[k] - np.float32(camera[k])) * inv_dist for k in range(3)]).astype(np.float32)
        dist2 = (dist * dist).astype(np.float32)
    # p . n_p once: the plane distance of a tap q is q . n_p - p . n_p.
    own = pos[0] * nrm[0] + pos[1] * nrm[1] + pos[2] * nrm[2]
    vf = valid.astype(np.float32)
    k2 = np.float32(noise_sigma**2)
    for i in range(passes):
        step = 1 << i
        pad = 2 * step
        widths = ((0, 0), (pad, pad), (pad, pad))
        pr, pp, pn = (np.pad(a, widths) for a in (img, pos, nrm))
        pv = np.pad(vf, pad)
        pu = None if view is None else np.pad(view, widths)
        acc = np.zeros_like(img)
        split = var is not None and var.shape[0] == 3
        wsum = np.zeros((2, h, w), np.float32)  # the colour channels' and AO's weight sums
        if var is not None:
            if split:
                guide = np.stack([(img[0:3] + img[3:6]).transpose(1, 2, 0) @ LUMA, img[3:6].transpose(1, 2, 0) @ LUMA,
                                  img[6]])
            else:
                guide = np.stack([(img[0:3] + img[3:6]).transpose(1, 2, 0) @ LUMA, img[6]])
            pg, pvar = np.pad(guide, widths), np.pad(var, widths)
            acc_var = np.zeros_like(var)
        # Per-tap temporaries, reused: the same operations in the same order as whole-array
        # expressions, without a fresh allocation for every intermediate plane.
        plane, cos, wt, tmp = (np.empty((h, w), np.float32) for _ in range(4))
        scratch = None if pu is None else np.empty((2, h, w), np.float32)
        if var is None:
            tap = np.empty_like(img)
        else:
            acc6 = np.empty((6, h, w), np.float32)
            diff, den = np.empty_like(var), np.empty_like(var)
            wt2 = np.empty((2, h, w), np.float32)
            sq = np.empty((2, h, w), np.float32)
        for dy in range(5):
            for dx in range(5):
                ys = slice(pad + (dy - 2) * step, pad + (dy - 2) * step + h)
                xs = slice(pad + (dx - 2) * step, pad + (dx - 2) * step + w)
                qp, qn = pp[:, ys, xs], pn[:, ys, xs]
                _dot3(qp, nrm, plane, tmp)
                plane -= own
                plane *= inv_sigma
                _dot3(qn, nrm, cos, tmp)
                np.maximum(cos, np.float32(0.0), out=cos)
                _power_into(cos, normal_power, wt)
                np.multiply(pv[ys, xs], np.float32(_B3[dy] * _B3[dx]), out=tmp)
                wt *= tmp
                if pu is not None and (dx != 2 or dy != 2):
                    _stretch_into(qp, pos, pu[:, ys, xs], view, dist2, stretch, wt, tmp, scratch)
                if var is None:
                    np.multiply(plane, plane, out=tmp)
                    np.negative(tmp, out=tmp)
                    np.exp(tmp, out=tmp)
                    wt *= tmp
                    np.multiply(wt, pr[:, ys, xs], out=tap)
                    acc += tap
                    wsum[0] += wt
                    continue
                # One weight for the colour channels (luminance guide), one for AO; the plane
                # and range terms share one exp.
                np.subtract(pg[:, ys, xs], guide, out=diff)
                np.multiply(diff, diff, out=diff)
                np.negative(diff, out=diff)
                np.add(var, pvar[:, ys, xs], out=den)
                den *= k2
                den += np.float32(1e-12)
                np.divide(diff, den, out=diff)  # the range terms' exponents
                if split:
                    # The colour channels' tap must agree in both luminance guides: one spatial
                    # weight times the stricter of the two range terms (not their product: where
                    # all light is indirect, e.g. under a black world, the guides are one and the
                    # same, and the product would halve the noise allowance; Cornell 640x360
                    # Combined 0.0216 -> 0.0226).
                    np.minimum(diff[0], diff[1], out=wt2[0])
                    wt2[1] = diff[2]
                else:
                    wt2[:] = diff
                np.multiply(plane, plane, out=tmp)
                wt2 -= tmp
                np.exp(wt2, out=wt2)
                wt2 *= wt  # (2, h, w): the colour channels', AO's weights
                np.multiply(wt2[0], pr[0:6, ys, xs], out=acc6)
                acc[0:6] += acc6
                np.multiply(wt2[1], pr[6, ys, xs], out=tmp)
                acc[6] += tmp
                np.multiply(wt2, wt2, out=sq)
                if split:  # both luminance guides' variances go with the colour weight
                    np.multiply(sq[0], pvar[0:2, ys, xs], out=den[0:2])
                    np.multiply(sq[1], pvar[2, ys, xs], out=den[2])
                else:
                    np.multiply(sq, pvar[:, ys, xs], out=den)
                acc_var += den
                wsum += wt2
        total = np.maximum(wsum, np.float32(1e-12))
        if var is None:  # one weight for every channel (any number of them)
            np.divide(acc, total[0], out=img)
        else:
            img[0:6] = acc[0:6] / total[0]
            img[6] = acc[6] / total[1]
        img *= vf
        if var is not None:
            if split:
                total = total[[0, 0, 1]]
            var = acc_var / (total * total) * vf
    return np.ascontiguousarray(np.moveaxis(img, 0, -1))


def _squared_distance_into(x: np.ndarray, y: np.ndarray, out: np.ndarray, tmp: np.ndarray) -> None:
    """out = |x - y|^2 of component planes x, y (3, ...), in place (tmp: scratch of out's shape)."""
    np.subtract(x[0], y[0], out=out)
    np.multiply(out, out, out=out)
    for k in (1, 2):
        np.subtract(x[k], y[k], out=tmp)
        np.multiply(tmp, tmp, out=tmp)
        out += tmp


def _stretch_into(qp: np.ndarray, pos: np.ndarray, qu: np.ndarray, view: np.ndarray, dist2: np.ndarray,
                  stretch: float, wt: np.ndarray, a: np.ndarray, scratch: np.ndarray) -> None:
    """wt *= the stretch weight of taps at qp (3, h, w) for pixels at pos (3, h, w), in place
    (a (h, w), scratch (2, h, w): float32 scratch). qu / view : the taps' and the pixels' unit view directions,
    dist2 : the pixels' squared view distances. The tap's distance over the distance the same
    step on screen spans on a surface facing the camera (view distance x the chord between the
    two view directions) is ~1 / cos of the viewing angle; the weight is 1 up to 1 and
    exp(-((ratio - 1) / stretch)^2) beyond (`filter_residual`)."""
    b, chord = scratch[0], scratch[1]
    _squared_distance_into(qp, pos, a, b)
    _squared_distance_into(qu, view, chord, b)
    chord *= dist2
    np.maximum(chord, np.float32(1e-30), out=chord)
    np.divide(a, chord, out=a)
    np.sqrt(a, out=a)
    a -= np.float32(1.0)
    np.maximum(a, np.float32(0.0), out=a)
    a *= np.float32(1.0 / stretch)
    np.multiply(a, a, out=a)
    np.negative(a, out=a)
    np.exp(a, out=a)
    wt *= a


def filter_at_pixels(values: np.ndarray, keep: np.ndarray, points: np.ndarray, normals: np.ndarray, pix: np.ndarray,
                     shape: tuple[int, int], camera, passes: int, pool=None, plane_sigma: float = 0.02,
                     normal_power: float = 8.0, filter=None) -> np.ndarray:
    """`filter_residual` of per-pixel values (n, c <= 7) at flat pixels `pix` of an image of
    `shape`, only the pixels `keep` (n,) read and written (others keep their value); points,
    normals : (n, 3) the pixels' surfaces, camera (3,) the eye; normal_power : one exponent or
    (n,) each pixel's own (`filter_residual`). Returns (n, c) float32.

    Up to SPARSE_FILTER_SHARE of the image kept (a penumbra, a glossy surface: Cornell 640x360's
    penumbra is 12k of 230k pixels) the taps are gathered at the kept pixels only
    (`_filter_sparse`, bit-identical; Cornell's penumbra filter 127 -> ~10 ms on one thread);
    beyond it the whole-image filter's contiguous planes are faster. filter : a callable with
    `filter_residual`'s signature and answer for that whole-image filter (a final render's GPU
    pass, `raster.atrous.AtrousPass`); None: `filter_residual`."""
    if np.count_nonzero(keep) <= SPARSE_FILTER_SHARE * shape[0] * shape[1]:
        return _filter_sparse(values, keep, points, normals, pix, shape, camera, passes, plane_sigma, normal_power,
                              pool)
    return _filter_dense(values, keep, points, normals, pix, shape, camera, passes, plane_sigma, normal_power, pool,
                         filter)


def _filter_dense(values: np.ndarray, keep: np.ndarray, points: np.ndarray, normals: np.ndarray, pix: np.ndarray,
                  shape: tuple[int, int], camera, passes: int, plane_sigma: float = 0.02, normal_power: float = 8.0,
                  pool=None, filter=None) -> np.ndarray:
    """`filter_at_pixels` through the whole-image `filter_residual` (the values scattered into
    image planes, filtered, gathered back)."""
    h, w = shape
    c = values.shape[1]
    # Only the values' own channels: without a variance every channel shares one weight.
    image = np.zeros((h * w, c), np.float32)
    image[pix] = values
    valid = np.zeros(h * w, bool)
    valid[pix] = keep
    pos = np.zeros((h * w, 3), np.float32)
    pos[pix] = points
    nrm = np.zeros((h * w, 3), np.float32)
    nrm[pix] = normals
    if isinstance(normal_power, np.ndarray):
        power = np.full(h * w, np.float32(1.0), np.float32)
        power[pix] = normal_power
        normal_power = power.reshape(h, w)
    out = (filter or filter_residual)(image.reshape(h, w, c), pos.reshape(h, w, 3), nrm.reshape(h, w, 3),
                                      valid.reshape(h, w), np.asarray(camera, np.float32), passes, plane_sigma,
                                      normal_power, pool=pool).reshape(h * w, c)
    return np.where(keep[:, None], out[pix], values).astype(np.float32)


def _dot3(a: np.ndarray, b: np.ndarray, out: np.ndarray, tmp: np.ndarray) -> None:
    """out = a[0] * b[0] + a[1] * b[1] + a[2] * b[2] for (3, ...) planes, in that order, into out."""
    np.multiply(a[0], b[0], out=out)
    np.multiply(a[1], b[1], out=tmp)
    out += tmp
    np.multiply(a[2], b[2], out=tmp)
    out += tmp


def _power_into(x: np.ndarray, exponent, out: np.ndarray) -> None:
    """out = x ** exponent, by squarings in place when the exponent is a power of two (the default
    8: three multiplies instead of a transcendental pow per tap); an array exponent (x's shape)
    per element."""
    if isinstance(exponent, np.ndarray):
        np.power(x, exponent, out=out)
        return
    e = float(exponent)
    if e >= 1 and e == int(e) and int(e) & (int(e) - 1) == 0:
        np.copyto(out, x)
        for _ in range(int(e).bit_length() - 1):
            np.multiply(out, out, out=out)
        return
    np.power(x, np.float32(e), out=out)


def _filter_sparse(values: np.ndarray, keep: np.ndarray, points: np.ndarray, normals: np.ndarray, pix: np.ndarray,
                   shape: tuple[int, int], camera, passes: int, plane_sigma: float, normal_power: float,
                   pool=None) -> np.ndarray:
    """`filter_at_pixels` with every tap gathered for the kept pixels only, from compact
    channel-first columns: `filter_residual`'s float32 arithmetic in its order, so the same
    bits (a tap off the kept pixels reads a zero column: no weight, as an invalid pixel has).
    pool : an executor; given and SPARSE_SPLIT_PIXELS kept or more, each pass's pixels are
    filtered in two halves side by side (per-pixel arithmetic: the same bits)."""
    h, w = shape
    rows = np.flatnonzero(keep)
    m = rows.size
    out = np.array(values, np.float32).reshape(values.shape[0], -1)
    if m == 0 or passes <= 0:
        return out
    flat = np.asarray(pix)[rows]
    y, x = np.divmod(flat, w)
    # Column m is a zero pixel (no weight, no light) that taps off the kept pixels read.
    index = np.full(h * w, m, np.intp)
    index[flat] = np.arange(m)

    def planes(a: np.ndarray) -> np.ndarray:
        """(c, m + 1) float32: the kept rows' channels, then the zero column."""
        a = np.asarray(a, np.float32).reshape(a.shape[0], -1)
        return np.concatenate([a[rows].T, np.zeros((a.shape[1], 1), np.float32)], axis=1)

    img, pos, nrm = planes(out), planes(points), planes(normals)
    vf = np.zeros(m + 1, np.float32)
    vf[:m] = 1.0
    own_p, own_n = pos[:, :m], nrm[:, :m]
    dist = np.sqrt(sum((own_p[k] - np.float32(camera[k])) ** 2 for k in range(3)))
    inv_sigma = (1.0 / np.maximum(plane_sigma * dist, 1e-12)).astype(np.float32)
    own = own_p[0] * own_n[0] + own_p[1] * own_n[1] + own_p[2] * own_n[2]
    own_power = np.asarray(normal_power, np.float32)[rows] if isinstance(normal_power, np.ndarray) else None

    def one_pass(step: int, part: slice) -> np.ndarray:
        """(c, k) the filtered values of the kept pixels `part` for taps `step` pixels apart."""
        py, px, pn, po, ps = y[part], x[part], own_n[:, part], own[part], inv_sigma[part]
        acc = np.zeros((img.shape[0], py.size), np.float32)
        wsum = np.zeros(py.size, np.float32)
        for dy in range(5):
            qy = py + (dy - 2) * step
            inside_y = (qy >= 0) & (qy < h)
            for dx in range(5):
                qx = px + (dx - 2) * step
                inside = inside_y & (qx >= 0) & (qx < w)
                q = np.where(inside, index[np.where(inside, qy * w + qx, 0)], m)
                qp, qn = pos[:, q], nrm[:, q]
                plane = (qp[0] * pn[0] + qp[1] * pn[1] + qp[2] * pn[2] - po) * ps
                cos = np.maximum(qn[0] * pn[0] + qn[1] * pn[1] + qn[2] * pn[2], 0.0)
                wt = np.empty_like(cos)
                _power_into(cos, normal_power if own_power is None else own_power[part], wt)
                wt *= vf[q] * np.float32(_B3[dy] * _B3[dx])
                wt *= np.exp(-plane * plane)
                acc += wt * img[:, q]
                wsum += wt
        return acc / np.maximum(wsum, np.float32(1e-12))

    halves = [slice(0, m // 2), slice(m // 2, m)] if pool is not None and m >= SPARSE_SPLIT_PIXELS else None
    for i in range(passes):
        if halves is None:
            img[:, :m] = one_pass(1 << i, slice(0, m))
            continue
        jobs = [pool.submit(one_pass, 1 << i, part) for part in halves]
        img[:, :m] = np.concatenate([job.result() for job in jobs], axis=1)
    out[rows] = img[:, :m].T
    return out


def _filter_in_bands(pool, halo, residual, position, normal, valid, camera, passes, plane_sigma, normal_power,
                     variance, noise_sigma, stretch=None):
    """`filter_residual` over two bands of rows on the pool, each with `halo` extra rows."""
    h = valid.shape[0]
    cuts = [0, h // 2, h]
    jobs = []
    for a, b in zip(cuts[:-1], cuts[1:], strict=True):
        lo, hi = max(a - halo, 0), min(b + halo, h)
        rows = slice(lo, hi)
        jobs.append((a - lo, b - lo, pool.submit(
            filter_residual, residual[rows], position[rows], normal[rows], valid[rows], camera, passes,
            plane_sigma, normal_power[rows] if isinstance(normal_power, np.ndarray) else normal_power,
            None if variance is None else variance[rows], noise_sigma, None, stretch)))
    return np.concatenate([job.result()[i:j] for i, j, job in jobs], axis=0)


def gi_images(system, position_lo: np.ndarray, normal_lo: np.ndarray, pix: np.ndarray, points: np.ndarray,
              normals: np.ndarray, corner_visible: np.ndarray, view: np.ndarray, frame: int, rays: int,
              passes: int = 3, plane_sigma: float = 0.02, normal_power: float = 8.0,
              screen: ScreenLight | None = None):
    """The GI resolution's textures from pixel rays: (gi_indirect (h, w, 4) rgb indirect + a AO,
    gi_direct (h, w, 4) rgb sky/emitter irradiance, PixelGI), rows as the read-back's (pix indexes
    its flattened pixels), background as the GPU gather writes it (indirect 0 with AO 1)."""
    h, w = position_lo.shape[:2]
    gi = trace_pixels(system, points, normals, rays, frame, corner_visible, screen=screen)
    tic = time.perf_counter()
    est, cache, valid, res, pos, nrm, camera, var = image_planes(gi, pix, points, normals, view, h, w)
    filtered = filter_residual(res.reshape(h, w, 7), pos.reshape(h, w, 3), nrm.reshape(h, w, 3),
                               valid.reshape(h, w), camera, passes, plane_sigma, normal_power,
                               variance=var.reshape(h, w, 2), pool=system.updater.pool).reshape(h * w, 7)
    gi.steps_ms["filter"] = (time.perf_counter() - tic) * 1e3
    indirect, direct = textures(cache + filtered[pix], pix, h, w)
    return indirect, direct, gi


def image_planes(gi: PixelGI, pix: np.ndarray, points: np.ndarray, normals: np.ndarray, view: np.ndarray,
                 h: int, w: int):
    """The GI pixels' rays scattered into (h * w, .) image planes for the filter: (estimate (n, 7),
    cache (n, 7), valid, residual, position, normal, camera eye (3,), variance); pix indexes the
    flattened image."""
    est, cache = gi.channels()
    valid = np.zeros(h * w, bool)
    valid[pix] = True
    res = np.zeros((h * w, 7), np.float32)
    res[pix] = est - cache
    pos = np.zeros((h * w, 3), np.float32)
    pos[pix] = points
    nrm = np.zeros((h * w, 3), np.float32)
    nrm[pix] = normals
    camera = camera_position(view).astype(np.float32)
    var = np.zeros((h * w, 2), np.float32)
    var[pix] = gi.variance
    return est, cache, valid, res, pos, nrm, camera, var


def textures(value: np.ndarray, pix: np.ndarray, h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    """(gi_indirect, gi_direct) (h, w, 4) from the GI pixels' values (n, 7: direct rgb, indirect
    rgb, AO), background as the GPU gather writes it (indirect 0 with AO 1)."""
    indirect = np.zeros((h * w, 4), np.float32)
    indirect[:, 3] = 1.0
    direct = np.zeros((h * w, 4), np.float32)
    write_texels(indirect, direct, pix, value)
    return indirect.reshape(h, w, 4), direct.reshape(h, w, 4)


def write_texels(indirect: np.ndarray, direct: np.ndarray, pix: np.ndarray, value: np.ndarray) -> None:
    """Write values (n, 7) at flat pixels pix into flat (h * w, 4) `textures` arrays, in place."""
    indirect[pix, 0:3] = np.maximum(value[:, 3:6], 0.0)
    indirect[pix, 3] = np.clip(value[:, 6], 0.0, 1.0)
    direct[pix, 0:3] = np.maximum(value[:, 0:3], 0.0)


@dataclass
class FullResGI:
    """Pixel-ray GI resolved at the full resolution (`full_res_images`): the textures, the PixelGI
    of the GI pixels, how many full-res pixels traced their own rays (`detail`), step times."""

    indirect: np.ndarray  # (H, W, 4) rgb indirect irradiance + a AO
    direct: np.ndarray  # (H, W, 4) rgb sky / emitter irradiance
    gi: PixelGI
    detail: int = 0
    steps_ms: dict[str, float] = field(default_factory=dict)
    #: What resolves the GI again at other samples (a jittered subframe's surfaces).
    resolver: GIResolver | None = None


def sample_pixels(position_lo: np.ndarray, full_points: np.ndarray, full_pix: np.ndarray, width: int, height: int,
                  factor: int) -> np.ndarray:
    """(h*w, 2) float32 full-res pixel (x, y) whose sample each GI pixel holds: the downsample copies
    one full-res sample of its factor x factor block (the nearest to the camera), found here as
    the block's pixel at the GI pixel's position; the block centre where none is (background)."""
    h, w = position_lo.shape[:2]
    lo = np.asarray(position_lo, np.float32).reshape(h * w, -1)[:, :3]
    full = np.full((height * width, 3), np.inf, np.float32)
    full[full_pix] = full_points
    grid = np.arange(h * w)
    bi, bj = grid % w, grid // w
    best = np.full(h * w, np.inf, np.float32)
    xy = np.stack([(bi + 0.5) * factor - 0.5, (bj + 0.5) * factor - 0.5], axis=1).astype(np.float32)
    for b in range(factor):
        for a in range(factor):
            x, y = bi * factor + a, bj * factor + b
            inside = (x < width) & (y < height)
            c = np.where(inside, x + width * y, 0)
            gap = np.abs(np.take(full, c, axis=0) - lo)
            # The largest axis of the gap: two maxima of columns, not a reduction over 3 per row.
            d = np.where(inside, np.maximum(np.maximum(gap[:, 0], gap[:, 1]), gap[:, 2]), np.inf)
            closer = d < best
            best = np.where(closer, d, best)
            np.copyto(xy[:, 0], x, where=closer, casting="unsafe")
            np.copyto(xy[:, 1], y, where=closer, casting="unsafe")
    return xy


def upsample_full(sh_lo: np.ndarray, cache_lo: np.ndarray, residual_lo: np.ndarray, position_lo: np.ndarray,
                  normal_lo: np.ndarray, valid_lo: np.ndarray, points: np.ndarray, normals: np.ndarray, pix: np.ndarray, width: int,
                  factor: int, camera: np.ndarray, plane_sigma: float = 0.02, normal_power: float = 8.0,
                  sigma: float = 1.0, rep_xy: np.ndarray | None = None, offset=(0.0, 0.0),
                  records: np.ndarray | None = None, surfaces: np.ndarray | None = None,
                  stretch: float | None = STRETCH) -> Upsampled:
    """Interpolate the GI resolution at the full-res pixels `pix` (flat, rows of `width`) with
    points / unit normals (n, 3), from the GI pixels' blended cache SH sh_lo (h*w, K, 7), its
    irradiance at their own normals cache_lo (h*w, 7) and their filtered residuals residual_lo
    (h*w, 7).

    Why: the bilateral upsampling interpolates *irradiance*, which on a curved or bevelled surface
    changes with the normal faster than a GI pixel resolves. Here each pixel interpolates the
    cache's radiance SH and the rays' residual over the 3 x 3 GI pixels around it (weights: a
    Gaussian of sigma GI pixels x the bilateral's plane / normal range weight) and evaluates the SH
    at its own normal: the cache's part of the light follows every pixel's normal. The residual is
    interpolated; how much it differs between the taps (`Upsampled.spread`) says where that
    interpolation cannot be trusted (`full_res_images` traces those pixels' own rays).

    rep_xy : (h*w, 2) the full-res pixel (x, y) each GI pixel's sample was taken at (`sample_pixels`);
    the spatial weight measures from there. None = the block centres; the downsample's
    nearest-depth pick is not the centre, and on a slope it is the same corner in every block, which
    shifts a gradient by half a full-res pixel the same way everywhere (a bias, not noise).
    offset : (x, y) full-res pixels from the pixel centres to where the points were sampled (a
    jittered subframe's, `GIResolver`); the spatial weights measure from there.
    records : `tap_records` of these GI-resolution inputs, made once by a caller that resolves
    many sets of points against them (None: made here).
    surfaces : (n, 3) the pixels' smooth surface normals where a normal map bends `normals` (the
    records' normals are then the GI pixels' surfaces, rows 26-28 their shading normals,
    `tap_records(shading=)`): the range weights compare surfaces, the cache's part is read with
    the bent lobe (`bump.irradiance_kernel`).
    stretch : the taps' weight falls off where they lie farther from the pixel than their screen
    step spans on a surface facing the camera (`_stretch_into`; STRETCH); None: no such term.
    """
    h, w = valid_lo.shape
    n = points.shape[0]
    k = sh_lo.shape[1]
    x = (pix % width).astype(np.int64)
    y = (pix // width).astype(np.int64)
    i0, j0 = x // factor, y // factor
    xf, yf = x.astype(np.float32) + np.float32(offset[0]), y.astype(np.float32) + np.float32(offset[1])
    if rep_xy is None:
        grid = np.arange(h * w)
        rep_xy = np.stack([(grid % w + 0.5) * factor - 0.5, (grid // w + 0.5) * factor - 0.5], axis=1)
    inv2s2 = np.float32(0.5 / (sigma * factor) ** 2)
    rec = tap_records(cache_lo, residual_lo, position_lo, normal_lo, valid_lo, rep_xy) if records is None else records
    points = np.asarray(points, np.float32)
    normals = np.asarray(normals, np.float32)
    guide = normals if surfaces is None else np.asarray(surfaces, np.float32)
    nx, ny, nz = guide[:, 0], guide[:, 1], guide[:, 2]
    sx, sy, sz = normals[:, 0], normals[:, 1], normals[:, 2]
    shading_rows = surfaces is not None and rec.shape[0] > 26
    cam = np.asarray(camera, np.float32)
    dist = np.linalg.norm(points - cam, axis=1)
    inv_sigma = (1.0 / np.maximum(plane_sigma * dist, 1e-12)).astype(np.float32)
    own_plane = nx * points[:, 0] + ny * points[:, 1] + nz * points[:, 2]
    if stretch is not None:  # the pixels' unit view directions and squared view distances
        view = ((points - cam) / np.maximum(dist, np.float32(1e-30))[:, None]).T.astype(np.float32)
        dist2 = (dist * dist).astype(np.float32)
        stretch_a, stretch_scratch = np.empty(n, np.float32), np.empty((2, n), np.float32)  # every tap's
    taps, weights = [], []
    best = np.zeros(n, np.float32)
    turned = np.zeros(n, bool)  # some tap's normal differs from the pixel's
    acc = np.zeros((17, n), np.float32)  # weighted sums of cache (7), residual (7), lum, lum^2, AO^2
    total = np.zeros(n, np.float32)
    spatial = np.zeros(n, np.float32)
    power = np.float32(normal_power)
    for dj in (-1, 0, 1):
        for di in (-1, 0, 1):
            qi, qj = i0 + di, j0 + dj
            inside = (qi >= 0) & (qi < w) & (qj >= 0) & (qj < h)
            q = np.where(inside, qi + w * qj, 0)
            r = np.take(rec, q, axis=1)  # (26, n), or (29, n) with the shading normals
            ws = np.exp(-(np.square(r[6] - xf) + np.square(r[7] - yf)) * inv2s2)
            plane = (nx * r[0] + ny * r[1] + nz * r[2] - own_plane) * inv_sigma
            cos = np.maximum(nx * r[3] + ny * r[4] + nz * r[5], np.float32(0.0))
            wr = np.exp(-plane * plane) * cos**power
            wr *= inside * r[8]
            if stretch is not None:
                to_tap = r[0:3] - cam[:, None]
                tap_view = to_tap / np.maximum(np.sqrt(np.einsum("kn,kn->n", to_tap, to_tap)), np.float32(1e-30))
                _stretch_into(r[0:3], points.T, tap_view, view, dist2, stretch, wr, stretch_a, stretch_scratch)
            np.maximum(best, wr, out=best)
            if shading_rows:  # the cache's part follows the shading normals
                cos = sx * r[26] + sy * r[27] + sz * r[28]
            turned |= (wr > 0) & (cos < np.float32(FLAT_COS))
            wt = ws * wr
            taps.append(q)
            weights.append(wt)
            acc += wt * r[9:26]
            total += wt
            spatial += ws * inside
    inv = np.where(total > 0, np.float32(1.0) / np.maximum(total, np.float32(1e-30)), np.float32(0.0))
    acc *= inv
    cache = np.ascontiguousarray(acc[0:7].T)
    res = np.ascontiguousarray(acc[7:14].T)
    ao_mean = acc[13]
    spread = np.maximum(np.stack([acc[15] - acc[14] ** 2, acc[16] - ao_mean**2], axis=1), np.float32(0.0))
    # Where some tap's normal differs from the pixel's (curved surfaces, creases), the cache's part
    # is the taps' SH evaluated at the pixel's own normal, one tap at a time (a (n, 9, K, 7) gather
    # would be ~20x the image's SH in memory); elsewhere it equals the taps' own cache irradiance.
    bent = np.flatnonzero(turned)
    if bent.size:
        order = 1 if k == 4 else 2
        yk = (sh.basis(np.take(normals, bent, axis=0), order) * sh.cosine_scale(order)).astype(np.float32)
        lobe = None
        if surfaces is not None:  # light and AO through the bent lobe (`_ao_rays`)
            lobe = irradiance_kernel(np.take(guide, bent, axis=0), np.take(normals, bent, axis=0), order)
            ao_lobe = lobe * (_ao_norm(lobe) * np.float32(np.pi))[:, None]  # /pi below
        own = np.zeros((bent.size, 7), np.float32)
        inv_bent = np.take(inv, bent)
        for q, wt in zip(taps, weights, strict=True):
            tap_sh = np.take(sh_lo, np.take(q, bent), axis=0)
            share = (np.take(wt, bent) * inv_bent)[:, None]
            if lobe is None:
                own += np.einsum("nk,nkc->nc", yk * share, tap_sh)
            else:
                own[:, 0:6] += np.einsum("nk,nkc->nc", lobe * share, tap_sh[..., 0:6])
                own[:, 6] += np.einsum("nk,nk->n", ao_lobe * share, tap_sh[..., 6])
        own[:, 6] /= np.float32(np.pi)
        cache[bent] = own
    cover = (total / np.maximum(spatial, np.float32(1e-30))).astype(np.float32)
    return Upsampled(cache, res, spread.astype(np.float32), best, cover, turned)


def tap_records(cache_lo: np.ndarray, residual_lo: np.ndarray, position_lo: np.ndarray, normal_lo: np.ndarray,
                valid_lo: np.ndarray, rep_xy: np.ndarray, shading: np.ndarray | None = None) -> np.ndarray:
    """(26, h*w) float32 planes, one column per GI pixel that `upsample_full` gathers once per tap:
    position, normal, sample pixel (x, y), validity, cache (7), residual (7), residual luminance
    and its square, AO residual squared. Why a function: a jittered subframe resolves a few
    thousand samples against the same GI pixels, and making the records costs more than that.
    Why planes: each tap's weights and sums then run on contiguous (n,) rows (the row-major
    (n, 26) gather's column reads and (n, 17) broadcasts cost ~2x the whole upsample).
    shading : the GI pixels' shading normals where a normal map bends them (`normal_lo` is then
    their smooth surfaces): three more rows, 26-28."""
    n = valid_lo.size
    residual_lo = np.asarray(residual_lo, np.float32)
    lum_lo = (residual_lo[:, 0:3] + residual_lo[:, 3:6]) @ LUMA
    rec = np.empty((26 if shading is None else 29, n), np.float32)
    rec[0:3] = np.asarray(position_lo, np.float32).reshape(n, -1)[:, :3].T
    rec[3:6] = np.asarray(normal_lo, np.float32).reshape(n, -1)[:, :3].T
    rec[6:8] = np.asarray(rep_xy, np.float32).T
    rec[8] = valid_lo.reshape(n)
    rec[9:16] = np.asarray(cache_lo, np.float32).T
    rec[16:23] = residual_lo.T
    rec[23] = lum_lo
    rec[24] = lum_lo * lum_lo
    rec[25] = np.square(residual_lo[:, 6])
    if shading is not None:
        rec[26:29] = np.asarray(shading, np.float32).reshape(n, -1)[:, :3].T
    return rec


@dataclass
class Upsampled:
    """`upsample_full`'s answer at n full-res pixels: cache (n, 7) the cache's irradiance (direct
    rgb, indirect rgb, AO) from the interpolated SH at each pixel's normal; residual (n, 7) the
    interpolated filtered residual; spread (n, 2) the taps' weighted variance of the residual
    (luminance, AO) around it; best (n,) the best tap's range weight (0: no GI pixel near shares
    the pixel's surface); cover (n,) the share of the spatial tap weight the range weights keep
    (1 inside a surface, lower near a crease, contact or silhouette); turned (n,) bool whether a
    tap's normal differs from the pixel's (a curved surface)."""

    cache: np.ndarray
    residual: np.ndarray
    spread: np.ndarray
    best: np.ndarray
    cover: np.ndarray
    turned: np.ndarray


#: Full-res pixels per `upsample_full` job on the worker pool (fixed: the answer does not depend on it;
#: 32k, not 16k: fewer GIL hand-overs, see CHUNK_RAYS).
UPSAMPLE_CHUNK = 32768


def _upsample_parallel(pool, sh_lo, cache_lo, residual_lo, position_lo, normal_lo, valid_lo, points, normals, pix,
                       width, factor, camera, plane_sigma, normal_power, rep_xy, offset=(0.0, 0.0),
                       records=None, surfaces=None) -> Upsampled:
    """`upsample_full` over chunks of pixels on a worker pool (numpy releases the GIL); a single
    chunk, or no pool, runs in line."""
    if records is None:
        records = tap_records(cache_lo, residual_lo, position_lo, normal_lo, valid_lo, rep_xy)
    if points.shape[0] <= UPSAMPLE_CHUNK or pool is None:
        return upsample_full(sh_lo, cache_lo, residual_lo, position_lo, normal_lo, valid_lo, points, normals, pix,
                             width, factor, camera, plane_sigma, normal_power, rep_xy=rep_xy, offset=offset,
                             records=records, surfaces=surfaces)
    starts = range(0, points.shape[0], UPSAMPLE_CHUNK)
    jobs = [pool.submit(upsample_full, sh_lo, cache_lo, residual_lo, position_lo, normal_lo, valid_lo,
                        points[a:a + UPSAMPLE_CHUNK], normals[a:a + UPSAMPLE_CHUNK], pix[a:a + UPSAMPLE_CHUNK],
                        width, factor, camera, plane_sigma, normal_power, rep_xy=rep_xy, offset=offset,
                        records=records, surfaces=None if surfaces is None else surfaces[a:a + UPSAMPLE_CHUNK])
            for a in starts]
    parts = [job.result() for job in jobs]
    return Upsampled(*(np.concatenate([getattr(p, f) for p in parts])
                       for f in ("cache", "residual", "spread", "best", "cover", "turned")))


def full_res_images(system, position_lo: np.ndarray, normal_lo: np.ndarray, pix: np.ndarray, points: np.ndarray,
                    normals: np.ndarray, corner_visible: np.ndarray, view: np.ndarray, frame: int, rays: int,
                    full_points: np.ndarray, full_normals: np.ndarray, full_pix: np.ndarray,
                    full_size: tuple[int, int], passes: int = 3, plane_sigma: float = 0.02,
                    normal_power: float = 8.0, refine: float = REFINE_SPREAD,
                    screen: ScreenLight | None = None, full_surfaces: np.ndarray | None = None,
                    filter=None, upsample=None, lookup: HitLookup | None = None,
                    begun: BegunPixels | None = None) -> FullResGI:
    """Pixel rays at the GI resolution, resolved at the full resolution (W, H = full_size).

    The GI pixels trace as `gi_images` does; their estimates (not only the residuals) are filtered
    with FULL_RES_NOISE_SIGMA; every full-res pixel then takes the cache's SH at its own normal
    plus the interpolated residual of the filtered estimate (`upsample_full`). Adaptive: a
    full-res pixel traces `rays` rays of its own where that interpolation is not to be trusted:

    - no GI pixel near it shares its surface (best range weight < DETAIL_MATCH: a post or bar
      narrower than a GI pixel, the far side of a crease or silhouette that lost its block's
      nearest-depth pick): it takes its own estimate (its own cache gather + its rays' residual);
    - near a crease, contact or silhouette (under REFINE_COVER of its spatial tap weight on its
      own surface) or on a curved surface, the taps' residuals differ by more than `refine` x the
      pixel's light (relative standard deviation of the luminance, or `refine` in AO): the
      correction changes within a GI pixel (a contact, the shadowed side of a bevel). Its own residual and the interpolated one are
      then averaged by their inverse variances (its rays' sample variance, the taps' spread), so
      the refinement adds detail where the taps disagree and little noise where they do not. At
      most REFINE_BUDGET x the GI pixels' count refine, the most disagreeing first.

    full_surfaces : (n, 3) the full-res pixels' smooth surface normals where a material bends
    `full_normals` (the G-buffer's `surface`), else None. Given, the GI pixels take theirs from
    the full-res pixels they sampled (`sample_pixels`), and the surfaces guide the filter and the
    interpolation (differently bent neighbours are one surface) while the light is read with the
    bent lobe (`bump.irradiance_kernel`).

    filter : a callable with `filter_residual`'s signature and answer to filter the GI pixels'
    estimates with (a final render's GPU pass, `raster.atrous.AtrousPass`); None: `filter_residual`.
    upsample : likewise for `upsample_full` over the whole image (`raster.upsample.UpsamplePass`);
    its time is the step "upsample_pass". None: `upsample_full` on the worker pool.
    lookup : the cache's HitLookup the hits read (None: `levels.hit_lookup`'s, built here).
    begun : the GI pixels' rays already traced (`begin_full_res`), shaded here with `screen`.
    """
    if begun is None:
        begun = begin_full_res(system, position_lo, pix, points, normals, corner_visible, frame, rays, full_points,
                               full_pix, full_size, full_surfaces, lookup)
    gi = finish_pixels(begun, screen)
    lookup, surfaces = begun.lookup, begun.surfaces
    return full_res_resolve(system, gi, position_lo, pix, points, normals, view, frame, rays, full_points,
                            full_normals, full_pix, full_size, passes, plane_sigma, normal_power, refine, lookup,
                            screen, surfaces=surfaces, full_surfaces=full_surfaces, filter=filter,
                            upsample=upsample)


def begin_full_res(system, position_lo: np.ndarray, pix: np.ndarray, points: np.ndarray, normals: np.ndarray,
                   corner_visible: np.ndarray, frame: int, rays: int, full_points: np.ndarray, full_pix: np.ndarray,
                   full_size: tuple[int, int], full_surfaces: np.ndarray | None = None,
                   lookup: HitLookup | None = None, trickle: bool = False) -> BegunPixels:
    """`full_res_images`' GI pixel rays traced (`begin_pixels`: their shading waits for the
    frame's lamp light; trickle: as its), with the lookup and smooth surface normals it reads."""
    surfaces = None
    if full_surfaces is not None:
        surfaces = low_res_surfaces(position_lo, pix, normals, full_points, full_surfaces, full_pix, full_size)
    if lookup is None and rays > 0:
        lookup = hit_lookup(system, bounced=system.settings.indirect_quality == MULTI_BOUNCE)
    return begin_pixels(system, points, normals, rays, frame, corner_visible, lookup=lookup, surfaces=surfaces,
                        pixels=(pix, position_lo.shape[1], frame), trickle=trickle)


def low_res_surfaces(position_lo: np.ndarray, pix: np.ndarray, normals: np.ndarray, full_points: np.ndarray,
                     full_surfaces: np.ndarray, full_pix: np.ndarray, full_size: tuple[int, int]) -> np.ndarray:
    """(n, 3) float32 the smooth surface normals of the GI pixels `pix`: those of the full-res
    pixels whose samples the downsample copied (`sample_pixels`); their shading `normals` where
    none is found."""
    width, height = full_size
    h, w = position_lo.shape[:2]
    factor = max(1, int(round(width / w)))
    xy = sample_pixels(position_lo, full_points, full_pix, width, height, factor)[pix]
    flat = np.clip(np.rint(xy[:, 0]).astype(np.int64) + width * np.rint(xy[:, 1]).astype(np.int64), 0,
                   width * height - 1)
    image = np.zeros((width * height, 3), np.float32)
    image[full_pix] = full_surfaces
    out = image[flat]
    missing = np.einsum("ij,ij->i", out, out) < 0.25
    out[missing] = np.asarray(normals, np.float32)[missing]
    return out


@dataclass
class _Interpolated:
    """A resolve's GI at every full-res pixel before its detail pixels (`_interpolate`): the
    upsampled taps `up`, their value (cache + residual, (n, 7)) and what the detail pixels and
    the `GIResolver` read."""

    up: Upsampled
    value: np.ndarray
    sh_lo: np.ndarray
    cache_lo: np.ndarray
    filtered: np.ndarray
    pos: np.ndarray
    nrm: np.ndarray
    valid: np.ndarray
    rep_xy: np.ndarray
    records: np.ndarray
    camera: np.ndarray
    factor: int
    steps: dict


def _interpolate(gi: PixelGI, position_lo: np.ndarray, pix: np.ndarray, points: np.ndarray, normals: np.ndarray,
                 view: np.ndarray, full_points: np.ndarray, full_normals: np.ndarray, full_pix: np.ndarray,
                 full_size: tuple[int, int], passes: int, plane_sigma: float, normal_power: float, pool=None,
                 surfaces: np.ndarray | None = None, full_surfaces: np.ndarray | None = None, filter=None,
                 upsample=None) -> _Interpolated:
    """`full_res_resolve`'s first half: the GI pixels' estimates filtered and interpolated at every
    full-res pixel (`filter` / `upsample`: GPU passes, or None: numpy on `pool`). Step times
    "planes", "filter", "upsample_pass" (the `upsample` callable's) and "upsample" (the rest)."""
    width, height = full_size
    h, w = position_lo.shape[:2]
    factor = max(1, int(round(width / w)))
    tic = time.perf_counter()
    est, cache, valid, res, pos, nrm, camera, var = image_planes(gi, pix, points,
                                                                 normals if surfaces is None else surfaces, view, h, w)
    shading = None
    if surfaces is not None:
        shading = np.zeros((h * w, 3), np.float32)
        shading[pix] = normals
    # The estimate itself is filtered, not only its residual: the cache's own structure finer than
    # the filter (cell seams and streaks where cells are a few pixels across, the far field) would
    # otherwise pass through untouched (cache + F(residual) = F(estimate) + cache - F(cache)).
    # At 320x240 vs Cycles: trusses AO 0.057 -> 0.053, contact AO 0.011 -> 0.010, car DI 0.083 -> 0.081.
    est_img = np.zeros((h * w, 7), np.float32)
    # Bent normals: the residual alone. The cache's part follows each pixel's bent normal, which a
    # filter over one surface would average away.
    est_img[pix] = est if surfaces is None else est - cache
    guides = var  # all light, AO; with the indirect light's variance: all light, indirect light, AO
    if gi.indirect_variance is not None:
        guides = np.zeros((h * w, 3), np.float32)
        guides[pix, 1] = gi.indirect_variance
        guides[:, 0] = var[:, 0]
        guides[:, 2] = var[:, 1]
    steps = {"planes": (time.perf_counter() - tic) * 1e3}
    tic = time.perf_counter()
    smooth = (filter or filter_residual)(est_img.reshape(h, w, 7), pos.reshape(h, w, 3), nrm.reshape(h, w, 3),
                                         valid.reshape(h, w), camera, passes, plane_sigma, normal_power,
                                         variance=guides.reshape(h, w, -1), noise_sigma=FULL_RES_NOISE_SIGMA,
                                         pool=pool, stretch=STRETCH).reshape(h * w, 7)
    steps["filter"] = (time.perf_counter() - tic) * 1e3
    tic = time.perf_counter()
    filtered = (smooth - (est_img - res)) * valid[:, None]  # as a residual of each GI pixel's own cache
    sh_lo = np.zeros((h * w,) + gi.sh.shape[1:], np.float32)
    sh_lo[pix] = gi.sh
    full_points = np.ascontiguousarray(full_points, np.float32)
    full_normals = np.ascontiguousarray(full_normals, np.float32)
    rep_xy = sample_pixels(position_lo, full_points, full_pix, width, height, factor)
    cache_lo = np.zeros((h * w, 7), np.float32)
    cache_lo[pix] = cache
    records = tap_records(cache_lo, filtered, pos, nrm, valid, rep_xy, shading)
    if full_surfaces is not None:
        full_surfaces = np.ascontiguousarray(full_surfaces, np.float32)
    pass_tic = time.perf_counter()
    if upsample is not None and full_surfaces is None:
        up = upsample(sh_lo, cache_lo, filtered, pos.reshape(h, w, 3), nrm.reshape(h, w, 3), valid.reshape(h, w),
                      full_points, full_normals, full_pix, width, factor, camera, plane_sigma, normal_power,
                      rep_xy=rep_xy, records=records)
        steps["upsample_pass"] = (time.perf_counter() - pass_tic) * 1e3
    else:
        up = _upsample_parallel(pool, sh_lo, cache_lo, filtered, pos.reshape(h, w, 3), nrm.reshape(h, w, 3),
                                valid.reshape(h, w), full_points, full_normals, full_pix, width, factor, camera,
                                plane_sigma, normal_power, rep_xy, records=records, surfaces=full_surfaces)
    steps["upsample"] = (time.perf_counter() - tic) * 1e3 - steps.get("upsample_pass", 0.0)
    return _Interpolated(up, up.cache + up.residual, sh_lo, cache_lo, filtered, pos.reshape(h, w, 3),
                         nrm.reshape(h, w, 3), valid.reshape(h, w), rep_xy, records, camera, factor, steps)


def full_res_preview(gi: PixelGI, position_lo: np.ndarray, pix: np.ndarray, points: np.ndarray, normals: np.ndarray,
                     view: np.ndarray, full_points: np.ndarray, full_normals: np.ndarray, full_pix: np.ndarray,
                     full_size: tuple[int, int], passes: int = 3, plane_sigma: float = 0.02,
                     normal_power: float = 8.0, filter=None, upsample=None) -> tuple[np.ndarray, np.ndarray]:
    """(indirect, direct) (H, W, 4) textures of `full_res_resolve` without its detail pixels' rays:
    the filtered GI pixels interpolated at every full-res pixel. The pixels no GI pixel around
    shares a surface with (a thin post, the far side of a crease: the orphans, which trace their
    own rays there) take the cache's light of their taps read at their own normal (`_orphan_light`)
    instead of nothing. Reads the arrays only (no system, no rays): the viewport's draw makes it
    with the GPU's filter and upsample passes the moment a pixel pass's rays are in, while its
    worker resolves the same rays with their detail pixels (car 640x360: 0.4 s of numpy)."""
    inter = _interpolate(gi, position_lo, pix, points, normals, view, full_points, full_normals, full_pix, full_size,
                         passes, plane_sigma, normal_power, filter=filter, upsample=upsample)
    width, height = full_size
    orphan = np.flatnonzero(inter.up.best < DETAIL_MATCH)
    if orphan.size:
        inter.value[orphan] = _orphan_light(inter, full_points, full_normals, full_pix, orphan, width)
    return textures(inter.value, full_pix, height, width)


def _orphan_light(inter: _Interpolated, full_points: np.ndarray, full_normals: np.ndarray, full_pix: np.ndarray,
                  orphan: np.ndarray, width: int) -> np.ndarray:
    """(m, 7) the light of the full-res pixels `orphan` without their own rays: their taps' cache
    SH read at the pixel's own normal, the taps weighed by distance only (a wall pixel among
    ground taps reads the ground's radiance towards the wall's normal: half the open sky where
    the ground sees all of it), without the taps' residuals, which belong to their surface."""
    points = np.ascontiguousarray(np.take(full_points, orphan, axis=0), np.float32)
    normals = np.ascontiguousarray(np.take(full_normals, orphan, axis=0), np.float32)
    up = upsample_full(inter.sh_lo, inter.cache_lo, inter.filtered, inter.pos, inter.nrm, inter.valid, points,
                       normals, np.take(full_pix, orphan), width, inter.factor, inter.camera, plane_sigma=1e6,
                       normal_power=0.0, rep_xy=inter.rep_xy, records=inter.records, stretch=None)
    return up.cache


def full_res_resolve(system, gi: PixelGI, position_lo: np.ndarray, pix: np.ndarray, points: np.ndarray,
                     normals: np.ndarray, view: np.ndarray, frame: int, rays: int, full_points: np.ndarray,
                     full_normals: np.ndarray, full_pix: np.ndarray, full_size: tuple[int, int], passes: int = 3,
                     plane_sigma: float = 0.02, normal_power: float = 8.0, refine: float = REFINE_SPREAD,
                     lookup: HitLookup | None = None, screen: ScreenLight | None = None,
                     surfaces: np.ndarray | None = None, full_surfaces: np.ndarray | None = None,
                     filter=None, upsample=None) -> FullResGI:
    """`full_res_images` after its GI pixels' rays `gi` (`trace_pixels` at points, frame, rays):
    the filter, the per-pixel resolve and the detail pixels' own rays (frame + DETAIL_FRAME; lookup:
    the HitLookup the GI pixels' rays read, None builds one). The viewport's worker traces `gi` on
    a thread of its own and resolves it here. screen : as `trace_pixels`', for the detail
    pixels' rays and the resolver's. surfaces, full_surfaces : the GI pixels' and the full-res
    pixels' smooth surface normals where a material bends normals (`full_res_images`), or None.
    filter, upsample : as `full_res_images`'. Step times: "planes" (the filter's input images),
    "filter" (the filter alone), "upsample" (without "upsample_pass", the `upsample` callable's),
    "detail" and the GI pixels' own."""
    width, height = full_size
    if lookup is None and rays > 0:
        lookup = hit_lookup(system, bounced=system.settings.indirect_quality == MULTI_BOUNCE)
    inter = _interpolate(gi, position_lo, pix, points, normals, view, full_points, full_normals, full_pix, full_size,
                         passes, plane_sigma, normal_power, system.updater.pool, surfaces, full_surfaces, filter,
                         upsample)
    steps = inter.steps
    up, value = inter.up, inter.value
    full_points = np.ascontiguousarray(full_points, np.float32)
    full_normals = np.ascontiguousarray(full_normals, np.float32)
    if full_surfaces is not None:
        full_surfaces = np.ascontiguousarray(full_surfaces, np.float32)
    resolver = GIResolver(system, inter.sh_lo, inter.cache_lo, inter.filtered, inter.pos, inter.nrm, inter.valid,
                          inter.rep_xy, width, inter.factor, inter.camera, plane_sigma, normal_power, lookup, rays,
                          inter.records, screen)
    tic = time.perf_counter()
    orphan = up.best < DETAIL_MATCH
    light = np.maximum((value[:, 0:3] + value[:, 3:6]) @ LUMA, np.float32(1e-6))
    # How far the taps disagree, in units of the threshold, at pixels whose taps span a crease, a
    # contact or a silhouette (part of the spatial weight on another surface: the interpolation
    # is one-sided there) or a curved surface: flat open surfaces are left to the filter, whose
    # blotches of residual noise would otherwise spend the budget (contact: 4231 -> 1139 refined
    # pixels for the same error).
    score = np.maximum(up.spread[:, 0] / (refine * light) ** 2, up.spread[:, 1] / refine**2)
    geometric = (up.cover < np.float32(REFINE_COVER)) | up.turned
    varying = np.flatnonzero((score > 1.0) & ~orphan & geometric)
    budget = int(REFINE_BUDGET * points.shape[0])
    if varying.size > budget:
        varying = varying[np.argsort(-score[varying], kind="stable")[:budget]]
    detail = np.union1d(np.flatnonzero(orphan), varying)
    steps["upsample"] += (time.perf_counter() - tic) * 1e3
    if detail.size and rays > 0:
        tic = time.perf_counter()
        dp, dn = np.take(full_points, detail, axis=0), np.take(full_normals, detail, axis=0)
        ds = None if full_surfaces is None else np.take(full_surfaces, detail, axis=0)
        own = trace_pixels(system, dp, dn, rays, frame + DETAIL_FRAME, system.corner_visibility(dp, dn),
                           lookup=lookup, min_chunks=DETAIL_MIN_CHUNKS, screen=screen, surfaces=ds)
        own_est, own_cache = own.channels()
        own_res = own_est - own_cache
        # Inverse-variance average of the two residuals, per guide (luminance: colour channels).
        v_own = np.maximum(own.variance, np.float32(1e-12))
        v_int = up.spread[detail]
        t = np.where(orphan[detail, None], np.float32(1.0), v_int / (v_int + v_own))  # the own residual's weight
        mix = np.empty_like(own_res)
        mix[:, 0:6] = t[:, 0:1] * own_res[:, 0:6] + (1 - t[:, 0:1]) * up.residual[detail, 0:6]
        mix[:, 6] = t[:, 1] * own_res[:, 6] + (1 - t[:, 1]) * up.residual[detail, 6]
        value[detail] = own_cache + mix
        steps["detail"] = (time.perf_counter() - tic) * 1e3
        for key, v in own.steps_ms.items():
            steps[f"detail_{key}"] = v
        gi.rays += own.rays
    indirect, direct = textures(value, full_pix, height, width)
    steps.update(gi.steps_ms)
    return FullResGI(indirect, direct, gi, int(detail.size), steps, resolver)


@dataclass
class GIResolver:
    """The GI resolution's filtered state (`full_res_images`), kept to resolve the GI at other
    full-res samples than the centre raster's: a jittered subframe's pixels that see another
    surface than the pixel centre (a thin post's edge, the ground behind it, a bar the centre
    missed).

    Why: Cycles' Diffuse Indirect is sum(colour x light) / sum(colour) over a pixel's samples, so
    each sample's surface must bring its own light; the centre's GI, upsampled to the subframe's
    surface, has no tap on a surface the centre raster did not see (a 4 cm bar between pixel
    centres) and takes a neighbour's light, or none."""

    system: object
    sh_lo: np.ndarray
    cache_lo: np.ndarray
    residual_lo: np.ndarray
    position_lo: np.ndarray
    normal_lo: np.ndarray
    valid_lo: np.ndarray
    rep_xy: np.ndarray
    width: int
    factor: int
    camera: np.ndarray
    plane_sigma: float
    normal_power: float
    lookup: HitLookup | None
    rays: int
    records: np.ndarray | None = None  # `tap_records` of the inputs above (None: made per call)
    screen: ScreenLight | None = None  # the centre frame's lamp light per pixel (`screen_light`)

    def at(self, points: np.ndarray, normals: np.ndarray, pix: np.ndarray, offset, frame: int,
           rays: int | None = None, surfaces: np.ndarray | None = None) -> tuple[np.ndarray, int]:
        """((n, 7) GI values, rays traced) at samples (points, unit normals (n, 3)) of full-res
        pixels pix taken at pixel centre + offset (pixels): the interpolated cache SH and residual,
        as `full_res_images` resolves every pixel; samples no GI pixel near shares a surface with
        take their own estimate from `rays` rays (default: the GI pixels' count). surfaces : the
        samples' smooth surface normals where a material bends `normals` (as `full_res_images`')."""
        points = np.ascontiguousarray(points, np.float32)
        normals = np.ascontiguousarray(normals, np.float32)
        if points.shape[0] == 0:
            return np.zeros((0, 7), np.float32), 0
        up = _upsample_parallel(self.system.updater.pool, self.sh_lo, self.cache_lo, self.residual_lo,
                                self.position_lo, self.normal_lo, self.valid_lo, points, normals, pix, self.width,
                                self.factor, self.camera, self.plane_sigma, self.normal_power, self.rep_xy,
                                offset=offset, records=self.records, surfaces=surfaces)
        value = up.cache + up.residual
        orphan = np.flatnonzero(up.best < DETAIL_MATCH)
        rays = self.rays if rays is None else int(rays)
        traced = 0
        if orphan.size and rays > 0:
            dp, dn = np.take(points, orphan, axis=0), np.take(normals, orphan, axis=0)
            ds = None if surfaces is None else np.take(surfaces, orphan, axis=0)
            own = trace_pixels(self.system, dp, dn, rays, frame + DETAIL_FRAME, self.system.corner_visibility(dp, dn),
                               lookup=self.lookup, min_chunks=DETAIL_MIN_CHUNKS, screen=self.screen,
                               surfaces=ds)
            value[orphan] = own.channels()[0]
            traced = own.rays
        return value, traced

"""Step 6 on the GPU: the 3D cache gathered into image space at the low resolution.

Reproduces `hybridgi_core.evaluate.gather` (see `gather_frag.glsl`) from textures packed from the
cache arrays. Cache data goes into 2D float textures addressed by a linear texel index rather
than 3D textures: 2K slots per cell (18 for L2) along one axis of a 3D texture would exceed the
2048-texel 3D limit already at 114 cells, and texelFetch keeps the result bit-for-bit the numpy
formula (no filtering).

Outputs (low res, RGBA32F), the layouts BilateralPass expects:
    gi_indirect : rgb = indirect irradiance (W/m^2), a = ray AO (1 = open / no cell)
    gi_direct   : rgb = direct-from-cache irradiance (sky + emissive surfaces), a = 0
"""

from __future__ import annotations

import logging
import weakref

import numpy as np

from ..bump import lobe_moments
from ..errors import LimitError
from .glsl import load_glsl
from .passes import RasterError, RasterPass, check_size, compile_spec, fullscreen_spec, make_target
from .readback import read_framebuffer, upload_texture_2d

log = logging.getLogger(__name__)

#: Width of the packed cache textures (texels) while the rows fit; larger caches widen them to the
#: GPU's limit. OpenGL guarantees 8192 at least; desktop GPUs and llvmpipe allow 16384.
PACK_WIDTH = 4096
#: Texture size assumed when no GPU can be asked (bpy-free callers of check_cache_textures).
DEFAULT_MAX_TEXTURE_SIZE = 16384

MODE_PLAIN, MODE_CHEBYSHEV, MODE_MASK = 0, 1, 2


def max_texture_size() -> int:
    """The GPU's 2D texture size limit (texels per side)."""
    try:
        import gpu  # noqa: PLC0415

        return int(gpu.capabilities.max_texture_size_get())
    except (ImportError, AttributeError, SystemError):
        return DEFAULT_MAX_TEXTURE_SIZE


def _layout(texels: int, max_size: int) -> tuple[int, int]:
    """(rows, width) of a texture holding `texels` row-major; width PACK_WIDTH unless the rows
    would not fit, then the GPU's maximum."""
    texels = max(int(texels), 1)
    width = min(PACK_WIDTH, texels, max_size)
    if -(-texels // width) > max_size:
        width = max_size
    return -(-texels // width), width


def check_cache_textures(cell_count: int, sh_coeffs: int, depth_texels: int, max_size: int | None = None) -> None:
    """Raise LimitError when a cache of `cell_count` cells cannot be packed into textures of at
    most `max_size` texels per side (the GPU's limit when None). Cheap: call it before the
    cache is built or warmed up."""
    max_size = max_size or max_texture_size()
    for what, texels in (("SH", cell_count * 2 * sh_coeffs), ("depth", cell_count * depth_texels**2)):
        rows, _width = _layout(texels, max_size)
        if rows > max_size:
            fits = int(cell_count * (max_size * max_size / texels)) if texels else 0
            raise LimitError(
                f"the cache's {what} texture needs {rows} rows of {max_size} texels, over the GPU's "
                f"texture size limit of {max_size}: {cell_count} cells, at most about {fits} fit; "
                "lower the HybridGI Resolution"
            )


def _pack_rows(texels: np.ndarray, max_size: int) -> np.ndarray:
    """(n, c) texels -> (rows, width, c) zero-padded, linear index = row * width + column."""
    n, c = texels.shape
    rows, width = _layout(n, max_size)
    out = np.zeros((rows * width, c), np.float32)
    out[:n] = texels
    return out.reshape(rows, width, c)


def pack_cache(cache, max_size: int = DEFAULT_MAX_TEXTURE_SIZE) -> tuple[np.ndarray, np.ndarray]:
    """The cache arrays as texture data (see gather_frag.glsl for the layout).

    Returns sh (rows, w, 4) float32: per cell K texels (sh_direct rgb, ao_sh) then K texels
    (sh_indirect rgb, valid in the first one's alpha); depth (rows, w, 2) float32: per cell the
    D*D octahedral (mean, mean square) distances. Raises LimitError (before
    packing) when the textures would exceed `max_size` texels per side.
    """
    n, k = cache.sh_direct.shape[:2]
    check_cache_textures(n, k, cache.settings.depth_texels, max_size)
    return pack_sh(cache, max_size), pack_depth(cache, max_size)


def pack_sh(cache, max_size: int = DEFAULT_MAX_TEXTURE_SIZE) -> np.ndarray:
    """The SH texture data of `pack_cache` alone."""
    n, k = cache.sh_direct.shape[:2]
    # Written straight into the padded texture (one pass over the cache, no second copy); every
    # texel of the n cells is set below, so only the padding is zeroed.
    rows, width = _layout(n * 2 * k, max_size)
    out = np.empty((rows * width, 4), np.float32)
    out[n * 2 * k :] = 0.0
    sh_tex = out[: n * 2 * k].reshape(n, 2 * k, 4)
    sh_tex[:, :k, :3] = cache.sh_direct
    sh_tex[:, :k, 3] = cache.ao_sh
    sh_tex[:, k:, :3] = cache.sh_indirect
    sh_tex[:, k, 3] = cache.valid
    sh_tex[:, k + 1 :, 3] = 0.0
    return out.reshape(rows, width, 4)


def pack_depth(cache, max_size: int = DEFAULT_MAX_TEXTURE_SIZE) -> np.ndarray:
    """The depth-moment texture data of `pack_cache` alone."""
    return _pack_rows(np.ascontiguousarray(cache.depth, np.float32).reshape(-1, 2), max_size)


def pack_corner_mask(corner_visible: np.ndarray) -> np.ndarray:
    """(h, w, 8) bool -> (h, w) float32 bit masks (bit c = corner c visible; exact in float)."""
    bits = (np.asarray(corner_visible, bool) * (1 << np.arange(8))).sum(axis=-1)
    return bits.astype(np.float32)


class GatherPass(RasterPass):
    """`upload(cache)` when it changed; `resize(low_w, low_h)`;
    `execute(low, visibility=True, corner_visible=None) -> (gi_indirect, gi_direct)`.

    The depth moments (the larger texture: D*D texels per cell against 2K) are only read by the
    Chebyshev test, so they are packed and uploaded on the first execute that needs them; final
    renders pass a corner mask and never do (at resolution 128 that saves a 1 GiB texture).
    """

    name = "gather"

    def __init__(self) -> None:
        super().__init__()
        self._targets = None
        self._fb = None
        self._cache_tx = None
        self._depth_tx = None
        self._depth_source = None  # weakref to the cache whose depth is not uploaded yet
        self._no_depth = None
        self._uploaded = None  # (id(cache), version) of the textures
        self._grid = None
        self._settings = None
        self._no_mask = None
        self._lobe_tx = None  # bump.lobe_moments as a texture, made on the first bent gather

    def _build_shaders(self) -> dict:
        spec = fullscreen_spec(
            "hybridgi_gather",
            load_glsl("common_lib.glsl", "gather_frag.glsl"),
            samplers=((0, "FLOAT_2D", "position_tx"), (1, "FLOAT_2D", "normal_tx"),
                      (2, "FLOAT_2D", "cache_tx"), (3, "FLOAT_2D", "depth_tx"), (4, "FLOAT_2D", "mask_tx"),
                      (5, "FLOAT_2D", "surface_tx"), (6, "FLOAT_2D", "lobe_tx")),
            push=(("VEC4", "grid_lo_cell"), ("IVEC4", "grid_dims"), ("FLOAT", "normal_bias"),
                  ("INT", "depth_texels"), ("INT", "mode"), ("INT", "bent_lobes")),
            outputs=((0, "VEC4", "out_indirect"), (1, "VEC4", "out_direct")),
        )
        return {"main": compile_spec(spec)}

    def _allocate(self, width: int, height: int) -> None:
        import gpu  # noqa: PLC0415

        self._targets = [make_target(width, height, "RGBA32F") for _ in range(2)]
        self._fb = gpu.types.GPUFrameBuffer(color_slots=tuple(self._targets))
        self._no_mask = upload_texture_2d(np.zeros((height, width), np.float32), "R32F")
        self._no_depth = upload_texture_2d(np.zeros((1, 1, 2), np.float32), "RG32F")

    def _release_targets(self) -> None:
        self._targets = None
        self._fb = None
        self._no_mask = None
        self._no_depth = None

    def free(self) -> None:
        super().free()
        self._cache_tx = self._depth_tx = self._lobe_tx = None
        self._depth_source = None
        self._uploaded = None

    def upload(self, cache) -> bool:
        """Upload the cache's arrays unless this cache version is already on the GPU.

        Returns True when it uploaded. (`IrradianceCache.version` is bumped on every blend.)
        """
        key = self._key(cache)
        if self._uploaded == key:
            return False
        max_size = max_texture_size()
        n, k = cache.sh_direct.shape[:2]
        check_cache_textures(n, k, cache.settings.depth_texels, max_size)
        self._cache_tx = upload_texture_2d(pack_sh(cache, max_size), "RGBA32F")
        self._depth_tx = None
        self._depth_source = weakref.ref(cache)
        self._grid = cache.grid
        self._settings = cache.settings
        self._uploaded = key
        return True

    def upload_packed(self, key, grid, settings, sh_texels: np.ndarray, depth_texels: np.ndarray | None,
                      depth_tx=None) -> bool:
        """Upload textures already in the `pack_cache` layout (packed on another thread), unless
        `key` (any hashable naming this version of the cache) is the one on the GPU already.
        depth_tx : the texture of these depth texels, already uploaded (skips that upload).
        depth_texels None: no depth moments (only a corner mask may test visibility: `has_depth`).
        Returns True when it uploaded."""
        if self._uploaded == key:
            return False
        self._cache_tx = upload_texture_2d(sh_texels, "RGBA32F")
        if depth_tx is None and depth_texels is not None:
            depth_tx = upload_texture_2d(depth_texels, "RG32F")
        self._depth_tx = depth_tx
        self._depth_source = None
        self._grid = grid
        self._settings = settings
        self._uploaded = key
        return True

    @property
    def has_depth(self) -> bool:
        """Whether the Chebyshev test can read depth moments (uploaded, or to pack from the cache)."""
        return self._depth_tx is not None or self._depth_source is not None

    @staticmethod
    def _key(cache):
        # IrradianceCache.reset() restarts `version` at 0 with new arrays: the arrays' identity
        # tells a reset cache from an unchanged one.
        return (id(cache), cache.version, id(cache.sh_direct))

    def _require_depth(self) -> None:
        """Upload the depth moments of the uploaded cache (the Chebyshev test reads them)."""
        if self._depth_tx is not None:
            return
        cache = self._depth_source() if self._depth_source is not None else None
        if cache is None:
            raise RasterError("gather: the uploaded cache is gone; upload(cache) again")
        if self._key(cache) != self._uploaded:
            # The cache moved on since upload(): take both textures from its current state.
            self.upload(cache)
        self._depth_tx = upload_texture_2d(pack_depth(cache, max_texture_size()), "RG32F")

    def execute(self, low, visibility: bool = True, corner_visible=None, surfaces: bool = False):
        """Gather at the low-res G-buffer `low` (LowResGBuffer of the resize size).

        visibility : False = plain trilinear x valid (evaluate's visibility=False)
        corner_visible : optional (h, w, 8) bool (rows bottom-up, like the read-back the CPU traced
            from) or an R32F bit-mask texture; replaces the Chebyshev test as in evaluate.
        surfaces : the G-buffer's normals are bent by normal maps (`GBufferPass.bends_normals`):
            the light is read through the bent lobe over `low.material`'s smooth surface normal
            (evaluate.gather(surfaces=)), not the cosine of the bent normal, which reads light from
            below the surface (a ridged normal-mapped floor's indirect light 3.2x too bright).
        Returns (gi_indirect, gi_direct) RGBA32F textures.
        """
        self._require()
        if self._cache_tx is None:
            raise RasterError("gather: upload(cache) before execute()")
        check_size(low.position, self.width, self.height, "low-res gbuffer")
        mask_tx = self._no_mask
        mode = MODE_CHEBYSHEV if visibility else MODE_PLAIN
        if visibility and corner_visible is not None:
            mode = MODE_MASK
            if isinstance(corner_visible, np.ndarray):
                if corner_visible.shape != (self.height, self.width, 8):
                    raise RasterError(f"corner_visible {corner_visible.shape}, expected {(self.height, self.width, 8)}")
                mask_tx = upload_texture_2d(pack_corner_mask(corner_visible), "R32F")
            else:
                check_size(corner_visible, self.width, self.height, "corner mask")
                mask_tx = corner_visible
        if mode == MODE_CHEBYSHEV:
            self._require_depth()
        g, s = self._grid, self._settings
        shader = self._shader()
        shader.uniform_sampler("position_tx", low.position)
        shader.uniform_sampler("normal_tx", low.normal)
        shader.uniform_sampler("cache_tx", self._cache_tx)
        shader.uniform_sampler("depth_tx", self._depth_tx if self._depth_tx is not None else self._no_depth)
        shader.uniform_sampler("mask_tx", mask_tx)
        bent = bool(surfaces) and getattr(low, "material", None) is not None
        shader.uniform_sampler("surface_tx", low.material if bent else low.normal)
        if bent and self._lobe_tx is None:  # the table's quadrature costs ~0.2 s: only with normal maps
            self._lobe_tx = upload_texture_2d(lobe_texels(), "RGBA32F")
        shader.uniform_sampler("lobe_tx", self._lobe_tx if bent else self._no_depth)
        shader.uniform_int("bent_lobes", 1 if bent else 0)
        shader.uniform_float("grid_lo_cell", (*np.asarray(g.lo, np.float32).tolist(), float(g.cell_size)))
        shader.uniform_int("grid_dims", (*[int(d) for d in g.dims], int(s.sh_coeffs)))
        shader.uniform_float("normal_bias", float(s.normal_bias))
        shader.uniform_int("depth_texels", int(s.depth_texels))
        shader.uniform_int("mode", mode)
        self._draw_fullscreen(self._fb, shader, (self.width, self.height))
        return tuple(self._targets)

    def read(self, slot: int, out: np.ndarray | None = None) -> np.ndarray:
        """Output `slot` (0 gi_indirect, 1 gi_direct) as (h, w, 4) float32, rows bottom-up."""
        return read_framebuffer(self._fb, slot, self.width, self.height, 4, out=out)


def lobe_texels() -> np.ndarray:
    """(2, LOBE_ANGLES, 4) float32 `bump.lobe_moments` as the gather's lobe_tx: row 0 (m0, mx, mz,
    mxx), row 1 (myy, mzz, mxz, 0)."""
    m = lobe_moments().astype(np.float32)
    out = np.zeros((2, m.shape[0], 4), np.float32)
    out[0] = m[:, 0:4]
    out[1, :, 0:3] = m[:, 4:7]
    return out


def gather_levels(gather: GatherPass, levels, low, points: np.ndarray, normals: np.ndarray, pix: np.ndarray,
                  visible: np.ndarray, surfaces: bool = False):
    """The gather of each cache level on the GPU (each with its own corner mask: columns
    8k .. 8k + 7 of `visible`, (n, 8 x levels) at the low-res pixels `pix`), read back at `pix`
    and joined by `CacheLevels.blend` -> `evaluate.Gathered` at the n points (the numpy reference
    is `CacheLevels.gather`). `gather` is left holding the finest level's textures."""
    h, w = low.height, low.width
    parts = []
    for k, cache in enumerate(levels.caches):
        mask = np.zeros((h * w, 8), bool)
        mask[pix] = visible[:, 8 * k:8 * k + 8]
        gather.upload(cache)
        gather.execute(low, corner_visible=mask.reshape(h, w, 8), surfaces=surfaces)
        ind = gather.read(0).reshape(-1, 4)[pix]
        direct = gather.read(1).reshape(-1, 4)[pix]
        parts.append((direct[:, :3], ind[:, :3], ind[:, 3]))
    return levels.blend(parts, levels.level_shares(points, normals, visible))

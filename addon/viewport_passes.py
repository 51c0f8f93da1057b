"""GPU passes of the viewport: the gather fed with worker-packed cache textures, the resolve of
the worker's direct light onto the current camera, the present pass, and a fullscreen draw.

Main thread only (they use `gpu`); their GLSL lives beside this module.
"""

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hybridgi_core.raster import gather as _gather
from hybridgi_core.raster import glsl as _glsl
from hybridgi_core.raster import passes as _passes
from hybridgi_core.raster import readback as _readback
from hybridgi_core.raster import subpixel as _subpixel

from . import worker

log = logging.getLogger(__name__)


#: Present-pass modes.
PRESENT_COLOR, PRESENT_CELLS = 0, 1


def load_addon_glsl(name: str) -> str:
    """GLSL source of a `.glsl` file beside this module."""
    return (Path(__file__).parent / name).read_text()



class PackedGatherPass(_gather.GatherPass):
    """The gather pass fed with `worker.CacheFrame`s: the worker packed the textures already, the
    main thread only uploads them (a plain cache still works, for the final-render path)."""

    _depth_texels = None  # the depth texels on the GPU (the worker reuses the array while they hold)

    def upload(self, cache) -> bool:
        if not isinstance(cache, worker.CacheFrame):
            self._depth_texels = None
            return super().upload(cache)
        same = cache.depth_texels is not None and cache.depth_texels is self._depth_texels
        uploaded = self.upload_packed(("frame", cache.serial), cache.grid, cache.settings,
                                      cache.sh_texels, cache.depth_texels, depth_tx=self._depth_tx if same else None)
        self._depth_texels = cache.depth_texels
        return uploaded

    def execute(self, low, visibility: bool = True, corner_visible=None, surfaces: bool = False):
        """As `GatherPass.execute`; a frame the worker sent without depth moments (a still view
        with its corner mask does not read them: `ViewportWorker._depth_wanted`) is read without
        the Chebyshev test by a view without its mask, until the moments follow (a worker step)."""
        if visibility and corner_visible is None and not self.has_depth:
            visibility = False
        return super().execute(low, visibility=visibility, corner_visible=corner_visible, surfaces=surfaces)




class DirectResolvePass(_passes.RasterPass):
    """`resize(w, h)`; `execute(position, normal, source) -> RGBA16F texture` (rgb W/m^2, a = trust).

    source : `DirectSource` (the worker's direct light, its positions and normals, its camera).
    """

    name = "direct resolve"

    def __init__(self, fmt: str = "RGBA16F"):
        super().__init__()
        self.format = fmt
        self._target = None
        self._fb = None

    def _build_shaders(self) -> dict:
        spec = _passes.fullscreen_spec(
            "hybridgi_direct_resolve",
            f"#define EDGE_LIST_WIDTH {EDGE_LIST_WIDTH}\n#define SAME_PLANE {_subpixel.SAME_PLANE!r}\n"
            f"#define SAME_REACH {_subpixel.SAME_REACH!r}\n" + _glsl.load_glsl("common_lib.glsl")
            + load_addon_glsl("direct_resolve_frag.glsl"),
            samplers=((0, "FLOAT_2D", "position_tx"), (1, "FLOAT_2D", "normal_tx"),
                      (2, "FLOAT_2D", "src_position_tx"), (3, "FLOAT_2D", "src_normal_tx"),
                      (4, "FLOAT_2D", "src_direct_tx"), (5, "FLOAT_2D", "edge_index_tx"),
                      (6, "FLOAT_2D", "edge_light_tx"), (7, "FLOAT_2D", "edge_point_tx"),
                      (8, "FLOAT_2D", "edge_normal_tx")),
            # 64 + 16 + 16 + 16 + 16 = 128 bytes: the push-constant limit. flags: (nearest, the
            # subframe's index among the edge light's subframes or -1, their count, 0).
            push=(("MAT4", "src_view_proj"), ("VEC4", "src_view_z"), ("VEC4", "src_footprint"),
                  ("IVEC4", "src_size"), ("IVEC4", "flags")),
            outputs=((0, "VEC4", "out_direct"),),
        )
        return {"main": _passes.compile_spec(spec)}

    def _allocate(self, width: int, height: int) -> None:
        import gpu  # noqa: PLC0415

        self._target = _passes.make_target(width, height, self.format)
        self._fb = gpu.types.GPUFrameBuffer(color_slots=(self._target,))

    def _release_targets(self) -> None:
        self._target = self._fb = None

    def execute(self, position, normal, source, nearest: bool = False, subframe: int = -1):
        """subframe : the jittered subframe drawn, its index in the source's edge light
        (`DirectSource.edge_textures`: its light traced at its own point where a light edge
        crosses a source pixel, taken where the subframe sees that pixel's surface); -1: none."""
        self._require()
        shader = self._shader()
        shader.uniform_sampler("position_tx", position)
        shader.uniform_sampler("normal_tx", normal)
        shader.uniform_sampler("src_position_tx", source.position)
        shader.uniform_sampler("src_normal_tx", source.normal)
        shader.uniform_sampler("src_direct_tx", source.direct)
        edges = source.edge_textures() if subframe >= 0 else None  # (subframe: `source.edge_subframe`'s)
        if edges is None:
            edges, subframe = (source.direct,) * 4, -1  # (bound, never read)
        for name, texture in zip(("edge_index_tx", "edge_light_tx", "edge_point_tx", "edge_normal_tx"), edges,
                                 strict=True):
            shader.uniform_sampler(name, texture)
        view_proj = source.proj @ source.view
        # A flat list is read column-major, as GLSL stores a mat4.
        shader.uniform_float("src_view_proj", view_proj.T.ravel().astype(np.float32).tolist())
        shader.uniform_float("src_view_z", [float(v) for v in source.view[2]])
        shader.uniform_float("src_footprint", (*source.footprint, 0.0, 0.0))
        shader.uniform_int("src_size", (source.width, source.height, 0, 0))
        count = 0 if subframe < 0 else int(source.edges.light.shape[0])
        shader.uniform_int("flags", (1 if nearest else 0, subframe, count, 0))
        self._draw_fullscreen(self._fb, shader, (self.width, self.height))
        return self._target

    def read(self) -> np.ndarray:
        return _readback.read_framebuffer(self._fb, 0, self.width, self.height, 4)


@dataclass
class DirectSource:
    """Textures of one `worker.ViewResult` (uploaded once per result): its direct light, or
    (`cells_of`) its Cache Cells colours, with the positions and normals they were made at."""

    serial: int
    direct: object
    position: object
    normal: object
    view: np.ndarray
    proj: np.ndarray
    width: int
    height: int
    footprint: tuple  # (a, b): a source pixel spans a * view depth + b world units
    #: The result's light of the jittered subframes at its light edges (`worker.EdgeLight`), or None
    edges: object = None
    _edge_textures: tuple | None = None

    def edge_textures(self) -> tuple | None:
        """(index, light, point, normal) textures of the edge light, uploaded once: index (h, w)
        R32F, the row of each source pixel in the lists or -1; the lists, EDGE_LIST_WIDTH texels
        a line (row r, subframe k at texel r * K + k): the lamps' light (a = 1 where the
        subframe's ray met a surface), the point it met (a = 1) and its normal. Sparse: a few %
        of the pixels, where K full-size textures would take K x 16 bytes a pixel each (a 4K
        view's 8 subframes, 1 GB). None without edge light."""
        edges = self.edges
        if edges is None or edges.pix.size == 0:
            return None
        if self._edge_textures is None:
            index = np.full(self.height * self.width, -1.0, np.float32)
            index[edges.pix] = np.arange(edges.pix.size, dtype=np.float32)
            k, m = edges.light.shape[:2]
            lines = -(-m * k // EDGE_LIST_WIDTH)
            hit = np.linalg.norm(edges.normal, axis=2) > 0.5  # (K, m): the ray met a surface

            def listed(values: np.ndarray, alpha: np.ndarray) -> np.ndarray:
                flat = np.zeros((lines * EDGE_LIST_WIDTH, 4), np.float32)
                flat[: m * k, :3] = values.transpose(1, 0, 2).reshape(-1, 3)  # row-major: r, then k
                flat[: m * k, 3] = alpha.T.reshape(-1)
                return flat.reshape(lines, EDGE_LIST_WIDTH, 4)

            up = _readback.upload_texture_2d
            self._edge_textures = (up(index.reshape(self.height, self.width, 1), "R32F"),
                                   up(listed(edges.light, hit), "RGBA32F"),
                                   up(listed(edges.point, hit), "RGBA32F"),
                                   up(listed(edges.normal, hit), "RGBA16F"))
        return self._edge_textures

    def edge_subframe(self, index: int, offsets: np.ndarray) -> int:
        """The draw's subframe `index` (of its pattern `offsets` (K, 2)) as an index into the
        edge light, or -1 when the result has none for this pattern."""
        edges = self.edges
        if (edges is None or not 0 <= index < edges.light.shape[0] or edges.pix.size == 0
                or edges.offsets.shape != np.shape(offsets)
                or not np.allclose(edges.offsets, np.asarray(offsets, np.float32), atol=1e-6)):
            return -1
        return index

    @classmethod
    def upload(cls, result: worker.ViewResult) -> "DirectSource":
        source = cls._of(result, result.direct, "RGBA32F", result.position, result.normal)
        source.edges = result.edges
        return source

    @classmethod
    def glossy_of(cls, result: worker.ViewResult, direct: "DirectSource | None" = None) -> "DirectSource":
        """The result's glossy light; reuses `direct`'s position and normal textures when they
        were uploaded from the same arrays of the same result."""
        if direct is not None and direct.serial == result.serial and result.glossy_position is result.position:
            h, w = result.glossy.shape[:2]
            return cls(result.serial, _readback.upload_texture_2d(result.glossy, "RGBA32F"), direct.position,
                       direct.normal, result.view, result.proj, w, h, direct.footprint)
        return cls._of(result, result.glossy, "RGBA32F", result.glossy_position, result.glossy_normal)

    @classmethod
    def cells_of(cls, result: worker.ViewResult) -> "DirectSource":
        return cls._of(result, result.cells, "RGBA16F", result.gi_position, result.gi_normal)

    @classmethod
    def _of(cls, result, colour, colour_format, position, normal) -> "DirectSource":
        h, w = colour.shape[:2]
        up = _readback.upload_texture_2d
        return cls(result.serial, up(colour, colour_format), up(position, "RGBA32F"), up(normal, "RGBA16F"),
                   result.view, result.proj, w, h, pixel_footprint(result.proj, h))

    @classmethod
    def empty(cls) -> "DirectSource":
        up = _readback.upload_texture_2d
        zero = np.zeros((1, 1, 4), np.float32)
        eye = np.eye(4)
        return cls(-1, up(zero, "RGBA32F"), up(zero, "RGBA32F"), up(zero, "RGBA16F"), eye, eye, 1, 1, (1.0, 0.0))


#: Texels a line of the edge light's list texture (`DirectSource.edge_textures`).
EDGE_LIST_WIDTH = 4096


def pixel_footprint(proj: np.ndarray, height: int) -> tuple[float, float]:
    """(a, b) with a pixel's height in world units = a * view depth + b (perspective: b = 0,
    orthographic: a = 0), from the projection matrix and the image height in pixels."""
    scale = 2.0 / (max(abs(float(proj[1, 1])), 1e-12) * max(height, 1))
    orthographic = abs(float(proj[3, 3]) - 1.0) < 1e-6
    return (0.0, scale) if orthographic else (scale, 0.0)




#: Pixels each way the present pass's filter reaches (Blackman-Harris up to a 3.5 px Filter Width).
MAX_TAP_RADIUS = 3


def present_taps(taps) -> tuple[tuple[float, float, float, float], int]:
    """((centre, 1, 2, 3 px) weights, radius) of a symmetric separable filter (odd length, or None:
    none) for the present shader: cut at MAX_TAP_RADIUS and renormalised to sum 1."""
    if taps is None or len(taps) <= 1:
        return (1.0, 0.0, 0.0, 0.0), 0
    taps = np.asarray(taps, np.float64)
    r = taps.size // 2
    half = taps[r : r + MAX_TAP_RADIUS + 1]
    half = half / (half[0] + 2.0 * half[1:].sum())
    out = np.zeros(4)
    out[: half.size] = half
    return tuple(float(x) for x in out), int(half.size - 1)


class PresentPass(_passes.RasterPass):
    """Combined -> the texture drawn into the viewport (RGBA16F, scene linear)."""

    name = "present"

    def __init__(self):
        super().__init__()
        self._target = None
        self._fb = None

    def _build_shaders(self) -> dict:
        spec = _passes.fullscreen_spec(
            "hybridgi_present",
            load_addon_glsl("present_frag.glsl"),
            samplers=((0, "FLOAT_2D", "combined_tx"), (1, "FLOAT_2D", "position_tx"), (2, "FLOAT_2D", "cells_tx")),
            push=(("INT", "mode"), ("INT", "opaque"), ("FLOAT", "scale"), ("VEC4", "taps"), ("INT", "radius")),
            outputs=((0, "VEC4", "out_color"),),
        )
        return {"main": _passes.compile_spec(spec)}

    def _allocate(self, width: int, height: int) -> None:
        import gpu  # noqa: PLC0415

        self._target = _passes.make_target(width, height, "RGBA16F")
        self._fb = gpu.types.GPUFrameBuffer(color_slots=(self._target,))

    def _release_targets(self) -> None:
        self._target = self._fb = None

    def execute(self, combined, gbuf, mode: int, opaque: bool, cells=None, scale: float = 1.0, taps=None):
        """cells : full-res RGBA texture of Cache Cells colours (mode PRESENT_CELLS); scale :
        multiplies Combined (Cycles' Film Exposure / the count of a sum of anti-aliasing subframes);
        taps : the separable pixel filter over the neighbours (`subpixel.reconstruction_taps`),
        at most MAX_TAP_RADIUS pixels each way (wider ones are cut there and renormalised), or
        None: each pixel as it is."""
        self._require()
        centre, radius = present_taps(taps)
        shader = self._shader()
        shader.uniform_sampler("combined_tx", combined)
        shader.uniform_sampler("position_tx", gbuf.position)
        shader.uniform_sampler("cells_tx", cells if cells is not None else combined)
        shader.uniform_int("mode", int(mode) if cells is not None else PRESENT_COLOR)
        shader.uniform_int("opaque", 1 if opaque else 0)
        shader.uniform_float("scale", float(scale))
        shader.uniform_float("taps", centre)
        shader.uniform_int("radius", radius)
        self._draw_fullscreen(self._fb, shader, (self.width, self.height))
        return self._target

    @property
    def output(self):
        return self._target

    def read(self) -> np.ndarray:
        return _readback.read_framebuffer(self._fb, 0, self.width, self.height, 4)


_SCREEN_BATCH = {}


def software_renderer() -> bool:
    """Whether the GPU module draws on the CPU (Mesa's llvmpipe or softpipe, SwiftShader): its
    raster passes then take the worker's cores, so extra redraws are not free."""
    import gpu  # noqa: PLC0415

    try:
        name = gpu.platform.renderer_get().lower()
    except Exception:  # noqa: BLE001  (a backend without the query: assume real hardware)
        return False
    return any(s in name for s in ("llvmpipe", "softpipe", "swiftshader", "software"))


def draw_texture_fullscreen(texture) -> None:
    """Draw `texture` over the whole bound framebuffer with Blender's IMAGE shader (the one
    `bind_display_space_shader` binds), whatever the matrix stack and depth test hold (Blender 4.2
    leaves a depth test on in an offscreen's framebuffer)."""
    import gpu  # noqa: PLC0415
    from gpu_extras.batch import batch_for_shader  # noqa: PLC0415
    from mathutils import Matrix  # noqa: PLC0415

    shader = gpu.shader.from_builtin("IMAGE")
    batch = _SCREEN_BATCH.get("image")
    if batch is None:
        corners = ((-1.0, -1.0), (1.0, -1.0), (-1.0, 1.0), (1.0, 1.0))
        uvs = ((0.0, 0.0), (1.0, 0.0), (0.0, 1.0), (1.0, 1.0))
        batch = _SCREEN_BATCH["image"] = batch_for_shader(shader, "TRI_STRIP", {"pos": corners, "texCoord": uvs})
    with gpu.matrix.push_pop(), gpu.matrix.push_pop_projection():
        gpu.matrix.load_identity()
        gpu.matrix.load_projection_matrix(Matrix.Identity(4))
        shader.uniform_sampler("image", texture)
        depth_test = gpu.state.depth_test_get()
        gpu.state.depth_test_set("NONE")
        batch.draw(shader)
        gpu.state.depth_test_set(depth_test)

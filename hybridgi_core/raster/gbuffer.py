"""Step 1: rasterize the snapshot into a full-resolution G-buffer (MRT).

Targets (all bottom-up rows, world space, scene-linear):

| slot | name     | format  | content                                                      |
|------|----------|---------|--------------------------------------------------------------|
| 0    | albedo   | RGBA16F | diffuse colour (base x texture x the specular layer's        |
|      |          |         | diffuse weight at the view angle), a = 1 on geometry         |
| 1    | normal   | RGBA16F | unit shading normal, flipped to face the camera and bent by  |
|      |          |         | the material's tangent-space normal map and bump, a = 1      |
| 2    | position | RGBA32F | world position xyz, w = 1 on geometry, 0 on the background   |
| 3    | emission | RGBA16F | emitted radiance W/(m^2 sr) (the material's emission texture |
|      |          |         | at the pixel's UV where it has one), a = 1                   |
| 4    | depth    | R32F    | view-axis distance (Cycles' Depth pass), 1e10 on background  |
| 5    | material | RGBA32F | r: material index + 1 (0 on the background): the CPU's glossy    |
|      |          |         | lobes; gba: the unit smooth surface normal (interpolated vertex  |
|      |          |         | normal facing the camera, not bent by maps; `read_surface`)      |

Everything else is 0 on the background. Geometry is uploaded once (`upload`); animated vertices
replace only the position buffer (`update_positions`). One draw call per material.
"""

from __future__ import annotations

import logging
from contextlib import contextmanager
from dataclasses import dataclass, replace

import numpy as np

from .. import glossy, sheen
from ..camera import camera_position
from ..rows import finite_rows
from ..snapshot import fit_texture
from ..specular import WEIGHT_SAMPLES, diffuse_weight_row
from .glsl import ShaderSpec, load_glsl
from .passes import (
    BACKGROUND_DEPTH,
    CAMERA_TYPEDEF,
    RasterError,
    RasterPass,
    camera_block,
    compile_spec,
    draw_state,
    make_target,
)
from .readback import read_framebuffer, upload_texture_2d

log = logging.getLogger(__name__)

#: (name, format, channels) of the colour targets, in framebuffer slot order.
GBUFFER_TARGETS = (
    ("albedo", "RGBA16F", 4),
    ("normal", "RGBA16F", 4),
    ("position", "RGBA32F", 4),
    ("emission", "RGBA16F", 4),
    ("depth", "R32F", 1),
    ("material", "RGBA32F", 4),
)
#: Channels `read(name)` returns where fewer than the target holds: the material index alone
#: (the smooth surface normal in the material target's gba comes from `read_surface`).
READ_CHANNELS = {"material": 1}
#: Blender's framebuffers take at most 6 colour attachments: the smooth normal shares a target.
SURFACE_TARGET = "material"


@dataclass
class GBuffer:
    """The G-buffer textures of one frame (owned by the pass; valid until the next resize/free)."""

    albedo: object
    normal: object
    position: object
    emission: object
    depth: object
    width: int
    height: int
    material: object = None


#: `has_texture` bits of the G-buffer shader: the texture's rgb is the colour / its alpha cuts.
#: Pixels of screen footprint a pixel's texture taps cover in one unjittered raster: Cycles'
#: default 1.5-pixel filter, which the single sample per pixel otherwise lacks.
TEXTURE_FILTER = 1.5

TEXTURE_COLOR = 1
TEXTURE_ALPHA = 2
#: The material's `normal_tx` holds a tangent-space normal map (`snapshot.NormalMap`).
TEXTURE_NORMAL = 4
#: The material's `bump_tx` holds a Bump node's height (`snapshot.BumpMap`), in red.
TEXTURE_BUMP = 8
#: With TEXTURE_BUMP: the height lies on a bake's atlas (`BumpMap.on_atlas`): its differences
#: step half a texel, as a footprint's step would read the next triangle's cell.
TEXTURE_BUMP_ATLAS = 256
#: The material's `emission_tx` holds its emitted radiance per texel (`Material.emission_texture`).
TEXTURE_EMISSION = 16
#: The alpha of `emission_tx` holds the Metallic per texel (`Material.metallic_map`): the material
#: target's r adds half of it to the index (`glossy_image.material_rows` picks the lobes by it).
TEXTURE_METALLIC = 32
#: A holdout's triangles: drawn as a hole (the background's zeros, depth HOLDOUT_DEPTH), so the
#: film can tell them from the world (`holdout_mask`) and Cycles' zero Combined and alpha show.
TEXTURE_HOLDOUT = 64
#: The material's `rough_tx` holds its Roughness per texel (`Material.roughness_map`), in red:
#: the material target's fraction then codes the pixel's glossy variant, `rough_range` = (lo, hi,
#: metallic steps, roughness steps) of `glossy.GlossyMaterials` (`glossy_image.material_rows`).
TEXTURE_ROUGHNESS = 128
#: A shadow catcher's triangles (`ObjectInfo.shadow_catcher`): drawn as any surface, position w 2
#: (`catcher_mask`), which the final render's film composes as Cycles does (`catcher.py`).
TEXTURE_CATCHER = 512
#: Depth a hole writes: beyond the background's (never the nearest of a downsampled block).
HOLDOUT_DEPTH = 1.5 * BACKGROUND_DEPTH


def catcher_mask(position: np.ndarray) -> np.ndarray:
    """bool mask of the pixels whose raster saw a shadow catcher (TEXTURE_CATCHER: position w 2)."""
    return np.asarray(position)[..., 3] > 1.5


def holdout_mask(depth: np.ndarray) -> np.ndarray:
    """bool mask of the pixels whose centre raster saw a holdout (Depth pass values)."""
    return np.asarray(depth) > 1.25 * BACKGROUND_DEPTH


def _nearest(values: np.ndarray, shape) -> np.ndarray:
    """(h, w) float32 `values` (h', w') at another size, nearest texels (the same UVs)."""
    h, w = shape
    if values.shape == (h, w):
        return np.asarray(values, np.float32)
    ys = (np.arange(h) * values.shape[0]) // h
    xs = (np.arange(w) * values.shape[1]) // w
    return np.asarray(values, np.float32)[ys][:, xs]


def _texture_rgba(material) -> np.ndarray:
    """(h, w, 4) float32: the material's colour texture (or white) with its alpha (or 1)."""
    colour, alpha = material.texture, material.alpha
    if colour is None:
        colour = np.ones((*alpha.shape, 3), np.float32)
    h, w = colour.shape[:2]
    if alpha is None:
        alpha = np.ones((h, w), np.float32)
    elif alpha.shape != (h, w):
        # Another image than the colour's: nearest texels at the colour's size.
        ys = (np.arange(h) * alpha.shape[0]) // h
        xs = (np.arange(w) * alpha.shape[1]) // w
        alpha = alpha[ys][:, xs]
    return np.ascontiguousarray(np.concatenate([colour, alpha[..., None]], axis=-1), np.float32)


@dataclass
class _MaterialDraw:
    batch: object
    ibo: object
    base_color: tuple
    fallback_albedo: tuple
    emission: tuple
    texture: object  # GPUTexture or None
    flags: int = 0  # TEXTURE_COLOR | TEXTURE_ALPHA | TEXTURE_NORMAL: what `texture`, `normal` hold
    row: int = 0  # the material's row of the diffuse weight table
    normal: object = None  # GPUTexture of the normal map, or None
    normal_strength: float = 1.0
    bump: object = None  # GPUTexture of the bump height, or None
    bump_strength: float = 1.0
    bump_distance: float = 0.0
    glow: object = None  # GPUTexture of the emission texture, or None
    rough: object = None  # GPUTexture of the roughness texture, or None
    rough_range: tuple = (0.0, 1.0, 1.0, 1.0)  # TEXTURE_ROUGHNESS's (lo, hi, metallic steps, roughness steps)
    metal: object = None  # GPUTexture of `Material.metal_texture`, or None


def view_mirrors(view: np.ndarray) -> bool:
    """Whether `view` (4, 4) world->camera mirrors (a camera under a negative scale): its
    triangles then wind the other way on screen."""
    return float(np.linalg.det(np.asarray(view, np.float64).reshape(4, 4)[:3, :3])) < 0.0


@contextmanager
def mirrored_winding(view: np.ndarray):
    """Clockwise triangles are front faces while `view` mirrors, so that gl_FrontFacing still
    tells the side a triangle's normal points to (a camera under a mirroring parent, which
    Cycles renders mirrored, had every normal flipped away from it: a dark image without shadows)."""
    import gpu  # noqa: PLC0415

    mirrors = view_mirrors(view)
    if mirrors:
        gpu.state.front_facing_set(True)
    try:
        yield
    finally:
        if mirrors:
            gpu.state.front_facing_set(False)


def camera_eye(view: np.ndarray, proj: np.ndarray) -> tuple:
    """(x, y, z, w) the G-buffer derives view directions from: the camera's position with w = 1
    (perspective), or the unit direction towards the camera with w = 0 (orthographic)."""
    view = np.asarray(view, np.float64).reshape(4, 4)
    proj = np.asarray(proj, np.float64).reshape(4, 4)
    if abs(proj[3, 3] - 1.0) < 1e-9 and abs(proj[3, 2]) < 1e-9:
        back = view[2, :3] / max(np.linalg.norm(view[2, :3]), 1e-30)
        return (*back.tolist(), 0.0)
    return (*camera_position(view).tolist(), 1.0)


#: Rows of diffuse weights a material with a Roughness texture adds to `weight_table`, at
#: roughnesses spread over its `glossy.roughness_range`: the G-buffer interpolates them by the
#: pixel's roughness texel (a checker of roughness 0 and 1 on a floor: Cycles' Diffuse Color
#: differs ~8% between its squares at grazing views, which the mean roughness's row missed).
ROUGH_WEIGHT_ROWS = 8


def weight_table(materials) -> np.ndarray:
    """(rows, WEIGHT_SAMPLES, 4) float32: row m < n_materials holds, at cosines
    i / (WEIGHT_SAMPLES - 1) between the normal and the view, the factor on material m's diffuse
    colour in red (its specular layer's diffuse weight, 1 without one, times a layered sheen's)
    and the colour its sheen adds in green-blue-alpha (`sheen.weight_row`; zeros without one).
    After them, ROUGH_WEIGHT_ROWS rows per material with a roughness texture, its layer at
    roughnesses spread over its range (`rough_weight_rows` says where they start)."""
    if not materials:
        empty = np.zeros((1, WEIGHT_SAMPLES, 4), np.float32)
        empty[..., 0] = 1.0
        return empty
    mu = np.linspace(0.0, 1.0, WEIGHT_SAMPLES)
    table = np.stack([sheen.weight_row(m, mu) for m in materials])
    table[:, :, 0] *= np.stack([diffuse_weight_row(getattr(m, "specular", None)) for m in materials])
    extra = []
    for m, material in enumerate(materials):
        span = glossy.roughness_range(material)
        if span is None:
            continue
        for r in np.linspace(span[0], span[1], ROUGH_WEIGHT_ROWS):
            row = table[m].copy()
            layer = replace(material.specular, roughness=float(r))
            row[:, 0] *= diffuse_weight_row(layer) / np.maximum(diffuse_weight_row(material.specular), 1e-6)
            extra.append(row)
    if extra:
        table = np.concatenate([table, np.stack(extra)])
    return table.astype(np.float32)


def rough_weight_rows(materials) -> np.ndarray:
    """(n_materials,) float32 the `weight_table` row where each material's roughness rows start,
    -1 for a material without them."""
    first = np.full(max(len(materials), 1), -1.0, np.float32)
    at = len(materials)
    for m, material in enumerate(materials):
        if glossy.roughness_range(material) is not None:
            first[m] = at
            at += ROUGH_WEIGHT_ROWS
    return first


def metal_texels(material) -> np.ndarray:
    """(h, w, 4) float32 the `metal_tx` of a material with a Metallic texture: its colour texture
    (`Material.metal_texture`) times the Metallic per texel in rgb, the Metallic in alpha, so that
    a pixel's footprint average over alpha is the colour of the metal under it, not of every texel
    there (the G-buffer divides). Why: a metal's colour read over dielectric texels as well was
    their mean: red metal stripes (a tenth of a base-colour texture) reflected 0.62 in red where
    Cycles' Glossy Color is 0.89, the dielectric pixels beside them 0.13 for 0.22."""
    colour = np.asarray(material.metal_texture, np.float32)
    h, w = colour.shape[:2]
    metal = np.asarray(material.metallic_map, np.float32)
    if metal.shape[:2] != (h, w):
        metal = fit_texture(np.repeat(metal[..., None], 3, axis=-1), max(h, w), quiet=True)[..., 0]
    if metal.shape[:2] != (h, w):  # not an integer multiple: the nearest texel
        rows = np.minimum(((np.arange(h) + 0.5) * metal.shape[0] / h).astype(np.int64), metal.shape[0] - 1)
        cols = np.minimum(((np.arange(w) + 0.5) * metal.shape[1] / w).astype(np.int64), metal.shape[1] - 1)
        metal = metal[rows[:, None], cols[None, :]]
    metal = np.clip(metal, 0.0, 1.0)[..., None]
    return np.ascontiguousarray(np.concatenate([colour * metal, metal], axis=-1), np.float32)


def tint_table(materials) -> np.ndarray:
    """(n_materials, 4, 4) float32: row m holds material m's `glossy.metal_tint_basis` (mean
    texel, first axis, second axis) in rgb of its first three texels, alpha 1 where it has one
    and its colour texture is the one drawn, 2 where it is `Material.metal_texture` (`metal_tx`),
    0 without (the G-buffer writes zeros for its texel coordinates); its fourth texel's red is
    where its roughness rows of `weight_table` start (`rough_weight_rows`, -1: none)."""
    table = np.zeros((max(len(materials), 1), 4, 4), np.float32)
    table[:, 3, 0] = rough_weight_rows(materials)
    for m, material in enumerate(materials):
        basis = glossy.metal_tint_basis(material)
        if basis is not None:
            table[m, :3, :3] = basis
            table[m, :3, 3] = 2.0 if getattr(material, "metallic_map", None) is not None else 1.0
    return table


class GBufferPass(RasterPass):
    """Rasterizes a `SceneSnapshot`'s triangles into the G-buffer.

    Usage: `create()`, `upload(snapshot)`, `resize(w, h)`, then per frame
    `execute(view, proj) -> GBuffer`; `update_positions(p)` for moving vertices.
    """

    name = "gbuffer"

    def __init__(self) -> None:
        super().__init__()
        self._targets = None
        self._depth_buffer = None
        self._fb = None
        self._fb_depth_only = None
        self._ubo = None
        self._pos_vbo = None
        self._attr_vbo = None
        self._layout = "main"  # the vertex layout of the uploaded scene (`upload`)
        self._draws: list[_MaterialDraw] = []
        self._dummy_texture = None
        self._weight_texture = None
        self._tint_texture = None
        self._vertex_count = 0
        #: Whether a drawn material bends its normals (normal map, bump): only then does the
        #: smooth surface normal differ from `normal` (`read_surface`).
        self.bends_normals = False

    # -- lifecycle ---------------------------------------------------------------------------
    def _build_shaders(self) -> dict:
        return {}  # one per vertex layout, compiled when a scene first draws with it (`_shader`)

    def _shader(self, key: str = "main"):
        if key not in self._shaders:
            self._shaders[key] = compile_spec(self._spec(key))
        return self._shaders[key]

    def _spec(self, layout: str) -> ShaderSpec:
        """The G-buffer shader of vertex layout "main" (tangents and the maps' own UVs) or "plain"
        (`upload`: neither; gbuffer_vert.glsl's PLAIN_LAYOUT)."""
        plain = layout == "plain"
        vertex_in = ((0, "VEC3", "pos"), (1, "VEC3", "nor"), (2, "VEC2", "uv"), (3, "FLOAT", "uv_valid"))
        return ShaderSpec(
            name=f"hybridgi_gbuffer_{layout}",
            vertex=("#define PLAIN_LAYOUT\n" if plain else "") + load_glsl("common_lib.glsl", "gbuffer_vert.glsl"),
            fragment=f"#define ROUGH_WEIGHT_ROWS {ROUGH_WEIGHT_ROWS}\n" + load_glsl("common_lib.glsl", "gbuffer_frag.glsl"),
            vertex_in=vertex_in if plain else vertex_in + ((4, "VEC4", "tangent"), (5, "VEC2", "nuv")),
            varyings=(("smooth", "VEC3", "world_pos"), ("smooth", "VEC3", "world_nor"),
                      ("smooth", "VEC2", "tex_uv"), ("smooth", "FLOAT", "uv_ok"), ("smooth", "VEC4", "world_tan"),
                      ("smooth", "VEC2", "map_uv")),
            samplers=((0, "FLOAT_2D", "albedo_tx"), (1, "FLOAT_2D", "weight_tx"), (2, "FLOAT_2D", "normal_tx"),
                      (3, "FLOAT_2D", "bump_tx"), (4, "FLOAT_2D", "emission_tx"), (5, "FLOAT_2D", "rough_tx"),
                      (6, "FLOAT_2D", "tint_tx"), (7, "FLOAT_2D", "metal_tx")),
            # 108 bytes of push constants per material; the camera (80 bytes) is a UBO.
            push=(("VEC4", "base_color"), ("VEC4", "fallback_albedo"), ("VEC4", "emission"), ("VEC4", "eye"),
                  ("VEC4", "rough_range"),
                  ("INT", "has_texture"), ("FLOAT", "texture_filter"), ("INT", "material_row"),
                  ("FLOAT", "normal_strength"), ("FLOAT", "bump_strength"), ("FLOAT", "bump_distance"),
                  ("FLOAT", "dither")),
            typedefs=CAMERA_TYPEDEF,
            ubos=((0, "CameraBlock", "camera"),),
            outputs=tuple((slot, "FLOAT" if ch == 1 else "VEC4", f"out_{name}")
                          for slot, (name, _fmt, ch) in enumerate(GBUFFER_TARGETS)),
        )

    def _allocate(self, width: int, height: int) -> None:
        import gpu  # noqa: PLC0415

        self._targets = {name: make_target(width, height, fmt) for name, fmt, _ch in GBUFFER_TARGETS}
        self._depth_buffer = make_target(width, height, "DEPTH_COMPONENT32F")
        self._fb = gpu.types.GPUFrameBuffer(
            depth_slot=self._depth_buffer,
            color_slots=tuple(self._targets[name] for name, _f, _c in GBUFFER_TARGETS),
        )
        # Separate framebuffer so the depth target can be cleared to BACKGROUND_DEPTH while the
        # other targets clear to 0 (a clear writes one value to every colour slot).
        self._fb_depth_only = gpu.types.GPUFrameBuffer(color_slots=(self._targets["depth"],))

    def _release_targets(self) -> None:
        self._targets = None
        self._depth_buffer = None
        self._fb = None
        self._fb_depth_only = None

    def free(self) -> None:
        super().free()
        self._ubo = None
        self._pos_vbo = None
        self._attr_vbo = None
        self._draws = []
        self._dummy_texture = None
        self._weight_texture = None
        self._tint_texture = None
        self._vertex_count = 0

    # -- geometry ----------------------------------------------------------------------------
    def upload(self, snapshot) -> None:
        """Build vertex/index buffers and material textures from a `SceneSnapshot`.

        Uses geometry.positions (V, 3) float32, normals (V, 3), uvs (V, 2) (NaN = no UV),
        tangents (V, 4) or None (normal maps), triangles (T, 3) int32 and material_index (T,) int32. Triangles are grouped by material
        (one index buffer each) over shared vertex buffers; textures are uploaded once here.
        """
        import gpu  # noqa: PLC0415

        self.create()
        geo = snapshot.geometry
        n_vert = int(geo.positions.shape[0])
        uvs = np.asarray(geo.uvs, np.float32).reshape(n_vert, 2)
        uv_valid = finite_rows(uvs).astype(np.float32)
        tangents = getattr(geo, "tangents", None)
        map_uvs = getattr(geo, "normal_uvs", None)
        # Without normal maps (no tangents, no texture of one) and UVs of the maps' own, the
        # vertices leave out the tangent and map UV: 24 bytes a vertex instead of 48, half the
        # buffer to fill and for every raster to read (the car's 430k corners: 21 -> 10 MB).
        normal_maps = any(getattr(getattr(m, "normal_map", None), "texture", None) is not None
                          for m in snapshot.materials)
        self._layout = "plain" if tangents is None and map_uvs is None and not normal_maps else "main"
        fmt = gpu.types.GPUVertFormat()
        fmt.attr_add(id="nor", comp_type="F32", len=3, fetch_mode="FLOAT")
        fmt.attr_add(id="uv", comp_type="F32", len=2, fetch_mode="FLOAT")
        fmt.attr_add(id="uv_valid", comp_type="F32", len=1, fetch_mode="FLOAT")
        if self._layout == "main":
            fmt.attr_add(id="tangent", comp_type="F32", len=4, fetch_mode="FLOAT")
            fmt.attr_add(id="nuv", comp_type="F32", len=2, fetch_mode="FLOAT")
        self._attr_vbo = gpu.types.GPUVertBuf(fmt, max(n_vert, 1))
        if n_vert:
            self._attr_vbo.attr_fill("nor", np.ascontiguousarray(geo.normals, np.float32).reshape(n_vert, 3))
            # The attributes a scene without UVs or normal maps leaves at zero share one block of
            # zeros: each new array of a million corners is its pages' first touch, ~2 ms a MB
            # on this VM (the atrium's upload: UVs 20 -> 0 ms, tangents 5.5 -> 0 ms).
            zeros = (np.zeros((n_vert, 4), np.float32)
                     if (tangents is None and self._layout == "main") or not uv_valid.any() else None)
            # Rows that are not finite are drawn without their UVs (uv_valid, which the shader
            # reads): any value stands there.
            if uv_valid.all():
                clean_uvs = np.ascontiguousarray(uvs)
            elif not uv_valid.any():  # (zeros made above)
                clean_uvs = zeros.reshape(-1)[: 2 * n_vert].reshape(n_vert, 2)
            else:
                clean_uvs = np.where(uv_valid[:, None] > 0.0, uvs, np.float32(0.0))
            self._attr_vbo.attr_fill("uv", clean_uvs)
            self._attr_vbo.attr_fill("uv_valid", uv_valid)
            if self._layout == "main":
                # Zero tangents: no frame there, the shader keeps the smooth normal.
                tangents = (zeros if tangents is None
                            else np.nan_to_num(np.asarray(tangents, np.float32).reshape(n_vert, 4), nan=0.0))
                self._attr_vbo.attr_fill("tangent", np.ascontiguousarray(tangents))
                # The normal and bump maps' UVs (`Geometry.normal_uvs`: the mesh's own under a
                # baked colour's atlas), else the texture UVs.
                self._attr_vbo.attr_fill("nuv", clean_uvs if map_uvs is None else np.ascontiguousarray(np.nan_to_num(
                    np.asarray(map_uvs, np.float32).reshape(n_vert, 2), nan=0.0, posinf=0.0, neginf=0.0)))
        self._vertex_count = n_vert
        if self._dummy_texture is None:
            self._dummy_texture = upload_texture_2d(np.ones((1, 1, 4), np.float32), "RGBA16F")

        tris = np.asarray(geo.triangles, np.int32).reshape(-1, 3)
        mat_index = np.asarray(geo.material_index, np.int32).reshape(-1)
        # Objects hidden from the camera (Object > Visibility > Camera) are not drawn; the rays
        # still see them, so they keep casting shadows and bouncing light, as in Cycles.
        hidden = [i for i, o in enumerate(snapshot.objects) if not o.camera_visible]
        drawn = ~np.isin(geo.object_index, hidden) if hidden else np.ones(tris.shape[0], bool)
        # Holdouts (objects, collections, the Holdout shader) are drawn as holes (TEXTURE_HOLDOUT).
        holes = [i for i, o in enumerate(snapshot.objects) if getattr(o, "holdout", False)]
        hole = np.isin(geo.object_index, holes) if holes else np.zeros(tris.shape[0], bool)
        catchers = [i for i, o in enumerate(snapshot.objects) if getattr(o, "shadow_catcher", False)]
        catch = np.isin(geo.object_index, catchers) if catchers else np.zeros(tris.shape[0], bool)
        self._draws = []
        self._weight_texture = upload_texture_2d(weight_table(snapshot.materials), "RGBA16F")
        self._tint_texture = upload_texture_2d(tint_table(snapshot.materials), "RGBA32F")
        for m, material in enumerate(snapshot.materials):
            if getattr(material, "clear", False):
                continue  # clear glass (`Material.clear`): the camera sees what lies behind it
            mine = (mat_index == m) & drawn
            if getattr(material, "holdout", False):
                parts = ((None, TEXTURE_HOLDOUT, tris[mine]),)
            else:
                parts = ((None, 0, tris[mine & ~hole & ~catch]), (None, TEXTURE_CATCHER, tris[mine & ~hole & catch]),
                         (None, TEXTURE_HOLDOUT, tris[mine & hole]))
            parts = [(flag, sel) for _none, flag, sel in parts if sel.shape[0]]
            if not parts:
                continue
            texture, flags = None, 0
            if material.texture is not None or material.alpha is not None:
                texture, flags = upload_texture_2d(_texture_rgba(material), "RGBA16F"), (
                    (TEXTURE_COLOR if material.texture is not None else 0)
                    | (TEXTURE_ALPHA if material.alpha is not None else 0))
            normal_map = getattr(material, "normal_map", None)
            normal = bump = None
            if normal_map is not None and normal_map.texture is not None:
                normal = upload_texture_2d(np.ascontiguousarray(np.concatenate(
                    [normal_map.texture, np.ones((*normal_map.texture.shape[:2], 1), np.float32)], axis=-1)), "RGBA16F")
                flags |= TEXTURE_NORMAL
            if normal_map is not None and normal_map.bump is not None:
                height = np.zeros((*normal_map.bump.height.shape, 4), np.float32)
                height[..., 0] = normal_map.bump.height
                bump = upload_texture_2d(height, "RGBA32F")  # height differences need the precision
                flags |= TEXTURE_BUMP | (TEXTURE_BUMP_ATLAS if normal_map.bump.on_atlas else 0)
            glow_texture = getattr(material, "emission_texture", None)
            metal = getattr(material, "metallic_map", None)
            glow = None
            if glow_texture is not None or metal is not None:
                # Half floats hold radiance up to 65504: emission textures are HDR. The alpha
                # carries the Metallic texture (TEXTURE_METALLIC), else 1.
                rgb = (glow_texture if glow_texture is not None
                       else np.broadcast_to(np.asarray(material.emission, np.float32), (*metal.shape, 3)))
                a = np.ones(rgb.shape[:2], np.float32) if metal is None else _nearest(metal, rgb.shape[:2])
                glow = upload_texture_2d(np.ascontiguousarray(np.concatenate([rgb, a[..., None]], axis=-1),
                                                              np.float32), "RGBA16F")
                flags |= (TEXTURE_EMISSION if glow_texture is not None else 0) | (
                    TEXTURE_METALLIC if metal is not None else 0)
            rough, rough_range = None, (0.0, 1.0, 1.0, 1.0)
            span = glossy.roughness_range(material)
            if span is not None:
                rough = upload_texture_2d(material.roughness_map, "R16F")
                flags |= TEXTURE_ROUGHNESS
                rough_range = (*span, float(glossy.METALLIC_STEPS if metal is not None else 1),
                               float(glossy.ROUGHNESS_STEPS))
            metal_colour = None
            if getattr(material, "metal_texture", None) is not None and glossy.is_textured_metal(material):
                metal_colour = upload_texture_2d(metal_texels(material), "RGBA16F")
            base = np.asarray(material.base_color, np.float32).reshape(3)
            self._draws += [_MaterialDraw(
                batch=None,
                ibo=gpu.types.GPUIndexBuf(type="TRIS", seq=np.ascontiguousarray(sel)),
                base_color=(*base.tolist(), float(np.clip(getattr(material, "coverage", 1.0), 0.0, 1.0))),
                fallback_albedo=(*np.asarray(material.mean_albedo, np.float32).reshape(3).tolist(), 1.0),
                emission=(*np.asarray(material.emission, np.float32).reshape(3).tolist(), 1.0),
                texture=texture,
                flags=flags | hole_flag,
                row=m,
                normal=normal,
                normal_strength=float(normal_map.strength) if normal_map is not None else 1.0,
                bump=bump,
                bump_strength=float(normal_map.bump.strength) if bump is not None else 1.0,
                bump_distance=float(normal_map.bump.distance) if bump is not None else 0.0,
                glow=glow,
                rough=rough,
                rough_range=rough_range,
                metal=metal_colour,
            ) for hole_flag, sel in parts]
        self.bends_normals = any(d.flags & (TEXTURE_NORMAL | TEXTURE_BUMP) for d in self._draws)
        self.update_positions(geo.positions)
        log.debug("gbuffer upload: %d vertices, %d triangles, %d material draws",
                  n_vert, tris.shape[0], len(self._draws))

    def update_positions(self, positions: np.ndarray) -> None:
        """Replace the vertex positions, (V, 3) float32 world space, same V as `upload`.

        Only the position buffer is rebuilt; normals, UVs, indices and textures are kept.
        (Blender's Python API cannot refill a vertex buffer that was drawn: a new one is made.)
        """
        import gpu  # noqa: PLC0415

        if self._attr_vbo is None:
            raise RasterError("update_positions before upload")
        positions = np.ascontiguousarray(positions, np.float32).reshape(-1, 3)
        if positions.shape[0] != self._vertex_count:
            raise RasterError(f"update_positions: {positions.shape[0]} positions for {self._vertex_count} vertices")
        fmt = gpu.types.GPUVertFormat()
        fmt.attr_add(id="pos", comp_type="F32", len=3, fetch_mode="FLOAT")
        self._pos_vbo = gpu.types.GPUVertBuf(fmt, max(positions.shape[0], 1))
        if positions.shape[0]:
            self._pos_vbo.attr_fill("pos", positions)
        for draw in self._draws:
            draw.batch = gpu.types.GPUBatch(type="TRIS", buf=self._pos_vbo, elem=draw.ibo)
            draw.batch.vertbuf_add(self._attr_vbo)

    # -- frame -------------------------------------------------------------------------------
    def execute(self, view: np.ndarray, proj: np.ndarray, texture_filter: float = TEXTURE_FILTER,
                dither: float = 0.0) -> GBuffer:
        """Rasterize with camera `view` (4, 4) world->camera and `proj` (4, 4) camera->clip
        (numpy or mathutils matrices, perspective or orthographic). texture_filter : pixels of
        screen footprint each pixel's texture taps cover (see gbuffer_frag.glsl). dither : this
        raster's offset of the thresholds at which surfaces seen with a chance (`Material.coverage`)
        show, in [0, 1): a subframe's own (`subframe_dither`).

        Returns the GBuffer textures at the size set by `resize` (background only before `upload`).
        """
        import gpu  # noqa: PLC0415

        self._require()
        data = camera_block(view, proj)
        if self._ubo is None:
            self._ubo = gpu.types.GPUUniformBuf(data)
        else:
            self._ubo.update(data)
        shader = self._shader(self._layout)
        eye = camera_eye(view, proj)
        with self._fb.bind():
            gpu.state.viewport_set(0, 0, self.width, self.height)
            self._fb.clear(color=(0.0, 0.0, 0.0, 0.0), depth=1.0)
        with self._fb_depth_only.bind():
            self._fb_depth_only.clear(color=(BACKGROUND_DEPTH, 0.0, 0.0, 0.0))
        with self._fb.bind():
            gpu.state.viewport_set(0, 0, self.width, self.height)
            with draw_state(depth_test="LESS", depth_mask=True), mirrored_winding(view):
                gpu.state.face_culling_set("NONE")
                for draw in self._draws:
                    shader.uniform_block("camera", self._ubo)
                    shader.uniform_float("base_color", draw.base_color)
                    shader.uniform_float("fallback_albedo", draw.fallback_albedo)
                    shader.uniform_float("emission", draw.emission)
                    shader.uniform_float("eye", eye)
                    shader.uniform_int("has_texture", draw.flags)
                    shader.uniform_float("texture_filter", float(texture_filter))
                    shader.uniform_int("material_row", draw.row)
                    if self._layout == "main":  # (the plain layout has no normal map: its
                        # compiler may drop what only a normal map reads)
                        shader.uniform_float("normal_strength", draw.normal_strength)
                        shader.uniform_sampler("normal_tx", draw.normal or self._dummy_texture)
                    shader.uniform_float("bump_strength", draw.bump_strength)
                    shader.uniform_float("bump_distance", draw.bump_distance)
                    shader.uniform_float("dither", float(dither))
                    shader.uniform_sampler("albedo_tx", draw.texture or self._dummy_texture)
                    shader.uniform_sampler("bump_tx", draw.bump or self._dummy_texture)
                    shader.uniform_sampler("emission_tx", draw.glow or self._dummy_texture)
                    shader.uniform_sampler("rough_tx", draw.rough or self._dummy_texture)
                    shader.uniform_float("rough_range", draw.rough_range)
                    shader.uniform_sampler("weight_tx", self._weight_texture)
                    shader.uniform_sampler("tint_tx", self._tint_texture)
                    shader.uniform_sampler("metal_tx", draw.metal or self._dummy_texture)
                    draw.batch.draw(shader)
        return self.outputs()

    def outputs(self) -> GBuffer:
        """The current targets (after `execute`)."""
        t = self._targets
        if t is None:
            raise RasterError("gbuffer: no targets (resize first)")
        return GBuffer(t["albedo"], t["normal"], t["position"], t["emission"], t["depth"],
                       self.width, self.height, t["material"])

    def read(self, name: str, out: np.ndarray | None = None) -> np.ndarray:
        """Target `name` (albedo|normal|position|emission|depth|material) as (h, w, c) float32, bottom-up."""
        for slot, (tname, _fmt, ch) in enumerate(GBUFFER_TARGETS):
            if tname == name:
                return read_framebuffer(self._fb, slot, self.width, self.height, READ_CHANNELS.get(name, ch), out=out)
        raise KeyError(name)

    def read_surface(self, normal: np.ndarray) -> np.ndarray:
        """The smooth surface normals (h, w, 4) of the last `execute`: `normal` itself (the
        `normal` target's read-back, the same array) when no drawn material bends its normals,
        else the material target's gba (xyz) with its r as w: > 0.5 on geometry, as the normal
        target's alpha. One read-back only where it differs."""
        if not self.bends_normals:
            return normal
        slot = [name for name, _f, _c in GBUFFER_TARGETS].index(SURFACE_TARGET)
        rgba = read_framebuffer(self._fb, slot, self.width, self.height, 4)
        return np.ascontiguousarray(rgba[..., (1, 2, 3, 0)])

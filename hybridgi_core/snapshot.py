"""Scene snapshot: plain numpy copies of what the tracer and shader need.

The Blender side fills these from the depsgraph on the main thread; everything after that
(tracing, shading, cache updates) reads only these arrays, so worker threads never touch `bpy`.
Units and conventions follow Cycles (checked against its passes): lights in watts (sun: W/m^2), emission and
world colour as radiance.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace

import numpy as np

from . import sheen
from .blocks import for_blocks
from .errors import EmptySceneError, InvalidGeometryError
from .rows import column_bounds, row_norms
from .specular import GlossySurface, SpecularLayer, hemispherical_diffuse_weight, hemispherical_glossy_albedo

log = logging.getLogger(__name__)

LIGHT_KINDS = ("POINT", "SPOT", "SUN", "AREA")
AREA_SHAPES = ("SQUARE", "RECTANGLE", "DISK", "ELLIPSE")
#: A planar object this many times larger than the rest of the scene is a ground plane (see
#: SceneSnapshot.focus_bounds); the grid then extends FOCUS_MARGIN of the rest's size around it.
GROUND_RATIO = 2.5
FOCUS_MARGIN = 0.6
#: Opacity under which an alpha-textured surface is a hole (Cycles blends stochastically; a
#: clip at one half keeps the same outline).
ALPHA_CUTOFF = 0.5
#: A triangle is degenerate when twice its area is below this share of its object's squared size
#: (the diagonal of the object's box): the tolerance follows the object, so a micrometre cube and
#: a sphere 100 km from the origin keep their triangles.
ZERO_AREA_RELATIVE = 1e-14
#: Textures larger than this many texels per side are box-filtered down on entry (a 16k texture
#: would otherwise mean gigabytes of float32 copies and a GPU upload over the device's limit).
MAX_TEXTURE_SIZE = 4096
#: The largest colour or radiance component read as a value: Blender stores an "inf" typed into a
#: colour or strength field as FLT_MAX (3.4e38), which is finite but overflows the first float32
#: sum or square it meets (every pixel then NaN); no light level a scene means comes near it.
MAX_FINITE_COLOR = 1e15
#: Largest side of `Material.metal_texture` (a second colour texture, its tint only).
METAL_TEXTURE_SIZE = 1024


@dataclass
class Geometry:
    """World-space triangles, unindexed per corner where attributes split.

    positions : (V, 3) float32, world space
    triangles : (T, 3) int32, indices into positions
    normals : (V, 3) float32, unit shading normals per vertex (corner normals already split)
    uvs : (V, 2) float32, active UV layer; NaN where the mesh has none
    material_index : (T,) int32, index into SceneSnapshot.materials
    object_index : (T,) int32, index into SceneSnapshot.objects
    tangents : (V, 4) float32 or None: world-space unit tangent (xyz) of the normal-map UV map
        (MikkTSpace, as Blender computes it) and the bitangent sign (w, +-1; the mirroring of the
        object's transform folded in), so that bitangent = w * cross(normal, tangent); rows of zeros
        where a mesh has none; None when no mesh in the scene needs them (no normal map)
    normal_uvs : (V, 2) float32 or None: the UVs normal and bump maps are read with where they
        differ from `uvs` (a baked colour puts its triangles' `uvs` on the bake's atlas; the maps
        keep the mesh's own, which their tangents follow); None: `uvs`
    """

    positions: np.ndarray
    triangles: np.ndarray
    normals: np.ndarray
    uvs: np.ndarray
    material_index: np.ndarray
    object_index: np.ndarray
    tangents: np.ndarray | None = None
    normal_uvs: np.ndarray | None = None

    @property
    def triangle_count(self) -> int:
        return int(self.triangles.shape[0])

    def subset(self, tri_mask: np.ndarray) -> Geometry:
        """Triangles where tri_mask is true, vertices compacted (new arrays; keeping every
        triangle and vertex is a plain copy, far cheaper than the gathers)."""
        tris = self.triangles[tri_mask]
        # np.unique(tris, return_inverse=True) without its sort: a mask over the vertices.
        mask = np.zeros(self.positions.shape[0], bool)
        mask[tris.ravel()] = True
        if tris.shape[0] == self.triangle_count and mask.all():
            return Geometry(self.positions.copy(), self.triangles.astype(np.int32), self.normals.copy(), self.uvs.copy(),
                            self.material_index.copy(), self.object_index.copy(),
                            None if self.tangents is None else self.tangents.copy(),
                            None if self.normal_uvs is None else self.normal_uvs.copy())
        used = np.flatnonzero(mask)
        inverse = (np.cumsum(mask, dtype=np.int64) - 1).astype(np.int32)[tris]
        return Geometry(
            positions=self.positions[used],
            triangles=inverse.reshape(-1, 3),
            normals=self.normals[used],
            uvs=self.uvs[used],
            material_index=self.material_index[tri_mask],
            object_index=self.object_index[tri_mask],
            tangents=None if self.tangents is None else self.tangents[used],
            normal_uvs=None if self.normal_uvs is None else self.normal_uvs[used],
        )

    def face_normals(self) -> np.ndarray:
        """(T, 3) float32 unit geometric normals (zero for degenerate triangles)."""
        p = self.positions[self.triangles]
        n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
        length = np.linalg.norm(n, axis=1, keepdims=True)
        return np.divide(n, length, out=np.zeros_like(n), where=length > 0).astype(np.float32)


@dataclass
class NormalMap:
    """What bends a material's shading normal: a tangent-space normal map (Cycles' Normal Map
    node, Tangent Space, fed by an image) and / or a Bump node over an image's height.

    texture : (h, w, 3) float32 or None, the map's values as Cycles reads them (Non-Color: raw),
        row 0 at v = 0; the shading normal is T x + B y + N z with (x, y, z) = 2 texture - 1, in
        the frame `Geometry.tangents` gives, then mixed with the smooth normal by `strength`
        (Cycles' svm_node_normal_map: N + (mapped - N) max(strength, 0), renormalized)
    strength : the Normal Map node's Strength
    uv_map : the UV map its tangents follow ("" = the mesh's active render UV map)
    bump : `BumpMap` applied after the map (a Bump node whose Normal is the map's), or None
    """

    texture: np.ndarray | None = None
    strength: float = 1.0
    uv_map: str = ""
    bump: BumpMap | None = None

    def __post_init__(self) -> None:
        if self.texture is not None:
            self.texture = fit_texture(self.texture, MAX_TEXTURE_SIZE, "normal map")
        self.strength = float(self.strength) if np.isfinite(self.strength) else 1.0

    def key(self) -> tuple:
        """What identifies it for change detection (the textures' sums, not their bytes)."""
        texture = None if self.texture is None else (self.texture.shape, float(self.texture.sum(dtype=np.float64)))
        return texture, self.strength, self.uv_map, None if self.bump is None else self.bump.key()


@dataclass
class BumpMap:
    """Cycles' Bump node over an image's height (svm_node_set_bump): the shading normal becomes
    normalize(N - distance x the height's gradient along the surface), mixed with N by strength.

    height : (h, w) float32, what the image gives the node's Height input (a colour's Rec.709
        luminance, or its alpha), row 0 at v = 0
    strength : the node's Strength (at least 0, as Cycles clamps it)
    distance : the node's Distance in metres, negated when the node inverts
    on_atlas : the height is Blender's bake of a procedural over the material's atlas (its UVs
        are the `Geometry.normal_uvs` of its triangles): its differences step half a texel, not
        the pixel's footprint, which would cross into the atlas's next triangle
    """

    height: np.ndarray
    strength: float = 1.0
    distance: float = 1.0
    on_atlas: bool = False

    def __post_init__(self) -> None:
        height = np.asarray(self.height, np.float32)
        self.height = fit_texture(np.repeat(height[..., None], 3, axis=2), MAX_TEXTURE_SIZE, "bump map")[..., 0].copy()
        self.strength = max(float(self.strength), 0.0) if np.isfinite(self.strength) else 1.0
        self.distance = float(self.distance) if np.isfinite(self.distance) else 0.0

    def key(self) -> tuple:
        return (self.height.shape, float(self.height.sum(dtype=np.float64)), self.strength, self.distance,
                bool(self.on_atlas))


@dataclass
class Material:
    """Lambertian surface: linear base colour, optional texture, emission radiance.

    texture : (h, w, 3) float32 linear RGB, row 0 at v = 0 (Blender's image order), or None
    emission : (3,) radiance in W/(m^2 sr) = emission colour x strength; with an
        `emission_texture`, that texture's mean (what reads where no UV is known)
    emission_texture : (h, w, 3) float32 emitted radiance per texel (colour x strength,
        scene-linear, may exceed 1), row 0 at v = 0, read through the same UVs as `texture`; or
        None (the constant `emission` everywhere)
    alpha : (h, w) float32 opacity from an image, row 0 at v = 0, or None (opaque): the surface is
        cut out where it is below ALPHA_CUTOFF, for the camera and for rays (`cutout.py`)
    bake_id : the reader's name for a texture it had Blender bake over this material's own UV
        atlas (one material per mesh then), so an edit of the material can bake it again; None
        for materials read directly
    specular : the Principled BSDF's dielectric specular layer over the diffuse base
        (`specular.SpecularLayer`), the glossy closures of any other node tree with the diffuse
        weight they leave (`specular.GlossySurface`), or None for a plain Lambertian surface.
        base_color is the diffuse colour before the view-dependent weight, which the G-buffer
        applies per pixel and probe hits as its hemispherical mean (`specular.diffuse_weight`)
    normal_map : `NormalMap` the G-buffer bends the shading normal by, or None; probe-ray hits
        keep the facet normal (a hit only feeds a cell's average)
    metallic_map : (h, w) float32 a Principled BSDF's Metallic per texel (0..1, read through the
        same UVs as `texture`, whose colour already carries the (1 - metallic) weight), or None;
        `specular` then holds the mean metallic, and the G-buffer picks each pixel's glossy
        lobes among `glossy.METALLIC_STEPS` variants of the material by its texel's value
    """

    name: str = "default"
    base_color: np.ndarray = field(default_factory=lambda: np.full(3, 0.8, np.float32))
    texture: np.ndarray | None = None
    emission: np.ndarray = field(default_factory=lambda: np.zeros(3, np.float32))
    alpha: np.ndarray | None = None
    bake_id: str | None = None
    specular: SpecularLayer | GlossySurface | None = None
    normal_map: NormalMap | None = None
    emission_texture: np.ndarray | None = None
    metallic_map: np.ndarray | None = None
    #: (h, w) float32 a Principled BSDF's Roughness per texel (0..1, through the same UVs as
    #: `texture`), or None; `specular` then holds its mean, and the G-buffer picks each pixel's
    #: glossy lobes among `glossy.ROUGHNESS_STEPS` variants by its texel's value
    roughness_map: np.ndarray | None = None
    #: (h, w, 3) float32 the colour texture of a material with a `metallic_map` (whose `texture`
    #: is then the diffuse base, (1 - metallic) x colour): its metallic lobe's colour per texel
    #: (`glossy.metal_tint_basis`), or None
    metal_texture: np.ndarray | None = None
    #: its surface is a Holdout shader: the camera sees a hole (Combined 0, alpha 0), rays a black surface
    holdout: bool = False
    #: shadow rays pass through it (a Mix Shader whose factor is Light Path > Is Shadow Ray with a
    #: Transparent BSDF on that side: glass that lets the lamps through); other rays see the surface
    shadow_transparent: bool = False
    #: most of the light passes straight through it (a Transparent BSDF, glass, a Principled BSDF's
    #: transmission; a constant alpha is `coverage`): rendered as clear thin glass, a hole
    #: for the camera and for every ray (`cutout.py`), with no refraction and no reflection
    clear: bool = False
    #: the share of the light its surface stops where the rest passes straight through (a constant
    #: alpha, a Transparent BSDF mixed in by a constant factor): the camera and every ray see the
    #: surface with that chance, drawn per pixel and subframe (the G-buffer) and per hit
    #: (`cutout.py`); the material's other values are its surface's where it is seen. 1: opaque
    coverage: float = 1.0
    #: a clear material whose light passes by refraction (glass, a Principled BSDF's transmission,
    #: a Refraction BSDF), not a Transparent BSDF's or an alpha's: Cycles' shadow rays stop at it,
    #: so the sun and point / spot lamps do not shine through it (`cutout.Cutouts.glass`)
    refractive: bool = False
    #: a refractive material's index of refraction and colour (the tint of the light it refracts,
    #: None: white): what the camera's refraction paths take (`refraction.py`)
    ior: float = 1.5
    tint: np.ndarray | None = None
    #: the tint applies to its reflections too (a Glass BSDF's Color, as in Cycles; a Principled
    #: BSDF's Base Color tints only what it refracts)
    tint_reflection: bool = False
    #: (3,) per channel, the share of the diffuse colour that is a Translucent BSDF's (lit from
    #: behind: Cycles counts it in the Diffuse passes), or None (all of it reflects)
    translucent: np.ndarray | None = None
    #: (3,) the colour of a Sheen closure (a Sheen BSDF's, a Principled BSDF's sheen weight x
    #: tint), or None: its light is diffuse light weighted by the sheen's directional albedo at
    #: the view angle (`sheen.py`); `sheen_roughness` its roughness, `sheen_layered` whether it
    #: lies over the base as a Principled BSDF's layer (the base then weighted 1 - max(sheen) A)
    sheen: np.ndarray | None = None
    sheen_roughness: float = 0.5
    sheen_layered: bool = False

    def __post_init__(self) -> None:
        # Non-finite colours would reach every pixel that sees (or bounces off) this material.
        self.base_color = _finite_color(self.base_color, 0.8, f"material {self.name!r} base colour")
        if self.translucent is not None:
            share = np.clip(np.nan_to_num(np.asarray(self.translucent, np.float32).reshape(-1)[:3], nan=0.0), 0.0, 1.0)
            self.translucent = share if share.size == 3 and share.any() else None
        if self.sheen is not None:
            colour = np.clip(np.nan_to_num(np.asarray(self.sheen, np.float32).reshape(-1)[:3], nan=0.0), 0.0, None)
            self.sheen = colour if colour.size == 3 and colour.any() else None
        self.sheen_roughness = float(np.clip(np.nan_to_num(self.sheen_roughness, nan=0.5), 0.0, 1.0))
        self.emission = _finite_color(self.emission, 0.0, f"material {self.name!r} emission")
        if self.texture is not None:
            self.texture = fit_texture(self.texture, MAX_TEXTURE_SIZE, f"material {self.name!r}")
        if self.emission_texture is not None:
            self.emission_texture = np.maximum(fit_texture(
                self.emission_texture, MAX_TEXTURE_SIZE, f"material {self.name!r} emission"), np.float32(0.0))
            self.emission = self.emission_texture.reshape(-1, 3).mean(axis=0, dtype=np.float64).astype(np.float32)
        if self.metallic_map is not None:
            metal = np.nan_to_num(np.asarray(self.metallic_map, np.float32), nan=0.0, posinf=1.0, neginf=0.0)
            self.metallic_map = np.clip(fit_texture(np.repeat(metal[..., None], 3, axis=-1), MAX_TEXTURE_SIZE,
                                                    f"material {self.name!r} metallic")[..., 0], 0.0, 1.0)
        if self.metal_texture is not None:
            # Only its colour's variation is read from it (`glossy.metal_tint_basis`): 1k texels a side.
            self.metal_texture = np.clip(np.nan_to_num(fit_texture(
                self.metal_texture, METAL_TEXTURE_SIZE, f"material {self.name!r} metal colour", quiet=True), nan=0.0),
                0.0, 1.0)
        if self.roughness_map is not None:
            rough = np.nan_to_num(np.asarray(self.roughness_map, np.float32), nan=0.5, posinf=1.0, neginf=0.0)
            self.roughness_map = np.ascontiguousarray(np.clip(fit_texture(
                np.repeat(rough[..., None], 3, axis=-1), MAX_TEXTURE_SIZE, f"material {self.name!r} roughness")[..., 0],
                0.0, 1.0))

    @property
    def mean_albedo(self) -> np.ndarray:
        """(3,) albedo to use where no UV is known (decimated ray meshes)."""
        if self.texture is None:
            return self.base_color
        return (self.base_color * self.texture.reshape(-1, 3).mean(axis=0)).astype(np.float32)

    @property
    def hit_diffuse_weight(self) -> float:
        """Share of the diffuse base a probe-ray hit reflects under the specular layer (its
        cosine-weighted mean over the hemisphere; 1 without a layer)."""
        return hemispherical_diffuse_weight(self.specular) * sheen.hit_weight(self)

    @property
    def hit_glossy_albedo(self) -> np.ndarray:
        """(3,) albedo a probe-ray hit adds for its glossy lobes (`specular.hemispherical_glossy_albedo`,
        blurred by Cycles' default Filter Glossy; `shading.SurfaceTable` uses the scene's)."""
        return hemispherical_glossy_albedo(self.specular)


@dataclass
class Light:
    """A Blender light with Cycles' radiometric conventions.

    kind : POINT | SPOT | SUN | AREA
    power : watts for POINT/SPOT/AREA, irradiance in W/m^2 for SUN (Blender's "Strength")
    matrix : (4, 4) world matrix; lights shine along local -Z (SPOT, SUN, AREA)
    radius : metres, radius of a POINT/SPOT's emitter ("shadow_soft_size")
    soft_falloff : POINT/SPOT with a radius: True emits from a disc facing each receiver (Blender's
        "Soft Falloff", its default), False from a sphere (hybridgi_core/lights.py)
    spot_size : radians, full cone angle; spot_blend : 0..1
    angle : radians, full angular diameter of the SUN disc
    shape, size, size_y : AREA shape and its extents in metres (size_y for RECTANGLE/ELLIPSE)
    spread : radians, AREA only: the full angle of its emission cone (Cycles' "Spread"; pi: the
        whole hemisphere, Lambertian). Narrower: radiance x `lights.spread_attenuation`.
    cast_shadow : False traces no shadow rays for this lamp (Blender's "Shadow" checkbox off).
    glossy_power : the power glossy lobes see (0 when the lamp object is hidden from glossy rays);
        None: `power`. `power` is what diffuse surfaces see (0 when hidden from diffuse rays).
    profile : POINT/SPOT only: an `ies.IESProfile` (an IES Texture node on the lamp's emission
        strength, times its Strength) that scales its radiance per direction, or None
    """

    kind: str
    color: np.ndarray
    power: float
    matrix: np.ndarray
    radius: float = 0.0
    soft_falloff: bool = True
    spot_size: float = np.pi / 4
    spot_blend: float = 0.15
    angle: float = 0.0
    shape: str = "SQUARE"
    size: float = 1.0
    size_y: float = 1.0
    name: str = ""
    spread: float = np.pi
    cast_shadow: bool = True
    glossy_power: float | None = None
    profile: object | None = None

    def __post_init__(self) -> None:
        if self.kind not in LIGHT_KINDS:
            raise InvalidGeometryError(f"unknown light kind {self.kind!r}")
        if self.kind == "AREA" and self.shape not in AREA_SHAPES:
            raise InvalidGeometryError(f"unknown area light shape {self.shape!r}")
        what = f"light {self.name!r}"
        self.color = _finite_color(self.color, 0.0, f"{what} colour")
        self.matrix = np.asarray(self.matrix, np.float64).reshape(4, 4)
        if not np.isfinite(self.matrix).all():
            raise InvalidGeometryError(f"{what}: its transform is not finite")
        # A light that is not finite would put NaN in every pixel it reaches: it emits nothing.
        for name in ("power", "radius", "spot_size", "spot_blend", "angle", "size", "size_y", "spread",
                     "glossy_power"):
            if name == "glossy_power" and self.glossy_power is None:
                continue
            value = float(getattr(self, name))
            if not np.isfinite(value):
                log.warning("%s: %s=%r is not finite; the light is switched off", what, name, value)
                self.power = 0.0
                self.glossy_power = 0.0 if self.glossy_power is not None else None
                value = 0.0
            setattr(self, name, value)
        self.spread = min(max(self.spread, 0.0), float(np.pi))
        self.cast_shadow = bool(self.cast_shadow)

    def for_glossy(self) -> Light:
        """This lamp as glossy lobes see it: `glossy_power` in place of `power`."""
        if self.glossy_power is None or self.glossy_power == self.power:
            return self
        return replace(self, power=self.glossy_power, glossy_power=None)

    @property
    def position(self) -> np.ndarray:
        return self.matrix[:3, 3].astype(np.float32)

    @property
    def directional(self) -> bool:
        """Whether its radiance depends on the direction it leaves in: a spot's cone, an IES
        profile (`lights.spot_attenuation` weighs both)."""
        return self.kind == "SPOT" or (self.profile is not None and self.kind == "POINT")

    @property
    def direction(self) -> np.ndarray:
        """Unit emission axis in world space (local -Z)."""
        d = -self.matrix[:3, 2]
        return (d / max(np.linalg.norm(d), 1e-30)).astype(np.float32)


#: AO distance (m) Cycles uses when the scene has no World (blender/sync.cpp sets 10 then); a
#: World's own Ambient Occlusion distance defaults to 1 m, so the two differ.
NO_WORLD_AO_DISTANCE = 10.0


@dataclass
class World:
    """The sky: radiance = background colour x strength; AO distance from World settings.

    sky_sh : (9, 3) float32 L2 radiance SH of a sky that varies with direction (an environment
        map without its sun, `environment.split_environment`), or None for a uniform `color`
        (which then still holds its mean over the upper hemisphere, for the background).
    sky_map : `environment.SkyMap` of the same sky, or None: rays read it where given (the SH
        stays for what needs a smooth sky).
    background : (3,) float32 what the camera sees of the world where it differs from `color`
        (a world hidden from diffuse rays lights nothing but is still seen; one hidden from the
        camera is black); None: `color`.
    background_map : `environment.BackgroundMap` of what the camera sees by direction (an
        environment image or a baked world tree), or None: `background_color` everywhere.
    """

    color: np.ndarray = field(default_factory=lambda: np.zeros(3, np.float32))
    ao_distance: float = 1.0
    sky_sh: np.ndarray | None = None
    sky_map: object | None = None
    background: np.ndarray | None = None
    background_map: object | None = None

    @property
    def background_color(self) -> np.ndarray:
        """(3,) float32 the world's colour as the camera sees it."""
        return self.color if self.background is None else self.background

    @property
    def any(self) -> bool:
        """Whether the sky gives any light."""
        return bool(self.color.any()) or (self.sky_sh is not None and bool(self.sky_sh.any()))

    def radiance(self, directions: np.ndarray) -> np.ndarray:
        """(n, 3) float32 sky radiance towards unit `directions` (n, 3)."""
        if self.sky_map is not None:
            return self.sky_map.radiance(directions)
        if self.sky_sh is None:
            return np.broadcast_to(self.color.astype(np.float32), (directions.shape[0], 3))
        from .sh import basis  # noqa: PLC0415  (sh imports nothing from here; kept local for clarity)

        return np.maximum(basis(directions, 2) @ self.sky_sh.astype(np.float32), np.float32(0.0))

    def __post_init__(self) -> None:
        self.color = _finite_color(self.color, 0.0, "world colour")
        if self.background is not None:
            self.background = _finite_color(self.background, 0.0, "world background")
        if not (np.isfinite(self.ao_distance) and self.ao_distance >= 0.0):
            log.warning("world AO distance %r is not a finite distance; using 1 m", self.ao_distance)
            self.ao_distance = 1.0


@dataclass
class ObjectInfo:
    name: str
    dynamic: bool = False  # moves or deforms over the animation: traced in the per-frame scene
    camera_visible: bool = True  # seen by the camera (False: still casts shadows and bounces light)
    #: a holdout (Object > Visibility > Holdout, a holdout collection): the camera sees a hole
    #: there (Combined 0, alpha 0), rays see the object as usual
    holdout: bool = False
    #: blocks shadow rays (Object > Visibility > Ray Visibility > Shadow; False: lamps shine through it)
    casts_shadow: bool = True
    #: a shadow catcher (Object > Visibility > Shadow Catcher): the camera sees the world behind it
    #: times what the other objects do to its light (`catcher.py`); rays see it as usual
    shadow_catcher: bool = False


@dataclass
class SceneSnapshot:
    geometry: Geometry
    materials: list[Material]
    lights: list[Light] = field(default_factory=list)
    world: World = field(default_factory=World)
    objects: list[ObjectInfo] = field(default_factory=list)
    #: (3,) float32 world position of the scene's camera, or None (no camera): where the cache's
    #: grid is spent (`focus_bounds`).
    viewpoint: np.ndarray | None = None

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(lo, hi) float32 corners of the geometry's bounding box."""
        if self.geometry.triangle_count == 0:
            raise EmptySceneError("the scene has no triangles")
        g = self.geometry
        used = np.zeros(g.positions.shape[0], bool)  # a mask, not np.unique's sort
        used[g.triangles.ravel()] = True
        return column_bounds(g.positions if used.all() else g.positions[used])

    def focus_bounds(self, margin: float = FOCUS_MARGIN) -> tuple[np.ndarray, np.ndarray]:
        """Bounds the cache grid should cover: like `bounds`, but a ground plane much larger than
        everything else (a car on a 20 m floor) does not set them.

        Such a plane would stretch the cells until the objects on it fall into one or two layers
        of cells. Only a horizontal plane at the bottom of the scene can be a ground plane (walls
        never are, so a room keeps its bounds while things move inside it), and only when it is
        over GROUND_RATIO times the extent of the rest; the rest's box then grows by `margin` of
        its extent on each side (bounce light from the floor around it), within the full bounds.
        A camera (`viewpoint`) inside the rest's box looks at the objects from among them (a room
        with windows, a street), not at the floor around them from outside: the box is then the
        rest's own. Why: a 5 m room on a 40 m ground spread its 48 cells over 11.7 m, 23 cm cells
        at 15 cm walls, and the sunlit ground's light leaked through them into the room (320x180
        vs Cycles, the room's Diffuse Indirect +12.5% with the margin, +0.3% without).
        """
        if self.geometry.triangle_count == 0:
            raise EmptySceneError("the scene has no triangles")
        _ids, blo, bhi = object_boxes(self.geometry)
        lo, hi = blo.min(axis=0), bhi.max(axis=0)  # == bounds(): the boxes span every corner
        size = (bhi - blo).max(axis=1)
        extent = float((hi - lo).max())
        flat = (bhi[:, 2] - blo[:, 2]) <= 1e-3 * np.maximum(size, 1e-9)
        at_bottom = bhi[:, 2] <= float(lo[2]) + 1e-3 * extent
        candidate = flat & at_bottom
        if not candidate.any() or candidate.all():
            return lo, hi
        rlo, rhi = blo[~candidate].min(axis=0), bhi[~candidate].max(axis=0)
        ground = candidate & (size > GROUND_RATIO * float((rhi - rlo).max()))
        if not ground.any():
            return lo, hi
        flo, fhi = blo[~ground].min(axis=0), bhi[~ground].max(axis=0)
        # The ground's own height still counts: cells must reach down to it.
        flo[2] = min(float(flo[2]), float(lo[2]))
        among = self.viewpoint is not None and bool(np.all((self.viewpoint >= flo) & (self.viewpoint <= fhi)))
        pad = 0.0 if among else margin * (fhi - flo).max()
        return np.maximum(flo - pad, lo).astype(np.float32), np.minimum(fhi + pad, hi).astype(np.float32)


def object_boxes(geometry: Geometry, tri_mask: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Bounding boxes of each object's triangles in one pass over the triangles (in blocks over
    threads, `blocks.for_blocks`).

    tri_mask : optional (T,) bool, triangles to count (others are ignored).
    Returns ids (m,) int32 of the objects that have triangles, lo (m, 3) and hi (m, 3) float32.
    """
    tris, obj, pos = geometry.triangles, geometry.object_index, geometry.positions

    def block(a, b):
        t, ob = tris[a:b], obj[a:b]
        if tri_mask is not None:
            sel = np.flatnonzero(tri_mask[a:b])
            t, ob = t[sel], ob[sel]
        return _run_boxes(ob, *(np.take(pos, t[:, k], axis=0) for k in range(3)))

    return _fold_boxes(for_blocks(tris.shape[0], block), int(obj.max(initial=0)) + 1)


def _run_boxes(ob: np.ndarray, c0: np.ndarray, c1: np.ndarray, c2: np.ndarray):
    """(ids, lo, hi) of one block's triangles (corners c0, c1, c2 (m, 3) float32, objects ob
    (m,)) per object, or None for an empty block."""
    if ob.size == 0:
        return None
    lo = np.minimum(np.minimum(c0, c1), c2)
    hi = np.maximum(np.maximum(c0, c1), c2)
    if ob.size > 1 and not (ob[1:] >= ob[:-1]).all():  # objects interleaved: sort them into runs
        order = np.argsort(ob, kind="stable")
        ob, lo, hi = ob[order], lo[order], hi[order]
    starts = np.concatenate(([0], np.flatnonzero(ob[1:] != ob[:-1]) + 1))
    return ob[starts], np.minimum.reduceat(lo, starts, axis=0), np.maximum.reduceat(hi, starts, axis=0)


def _fold_boxes(parts: list, n_ids: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`object_boxes`' (ids ascending, lo, hi) of the blocks' `_run_boxes` (None: empty) over
    object ids below n_ids: each object's box is the union of its boxes in every block."""
    parts = [p for p in parts if p is not None]
    if not parts:
        empty = np.zeros((0, 3), np.float32)
        return np.zeros(0, np.int32), empty, empty
    ids = np.concatenate([p[0] for p in parts])
    lo = np.full((n_ids, 3), np.inf, np.float32)
    hi = np.full((n_ids, 3), -np.inf, np.float32)
    np.minimum.at(lo, ids, np.concatenate([p[1] for p in parts]))
    np.maximum.at(hi, ids, np.concatenate([p[2] for p in parts]))
    seen = np.unique(ids)
    return seen.astype(np.int32), lo[seen], hi[seen]


def fit_texture(texture: np.ndarray, max_size: int = MAX_TEXTURE_SIZE, what: str = "texture",
                quiet: bool = False) -> np.ndarray:
    """(h, w, 3) float32 finite texture, box-filtered by an integer factor until both sides are at
    most `max_size` (a warning unless `quiet`: a copy reduced on purpose); non-finite texels
    become 0 (logged)."""
    tex = np.asarray(texture, np.float32)
    if tex.ndim != 3 or tex.shape[2] != 3 or tex.shape[0] == 0 or tex.shape[1] == 0:
        raise InvalidGeometryError(f"{what}: texture must be (h, w, 3), got {tex.shape}")
    h, w = tex.shape[:2]
    factor = -(-max(h, w) // max_size)
    if factor > 1:
        # Pad by edge repetition to a multiple of the factor, then average factor x factor blocks
        # (a sum over one axis at a time: no float64 copy of the full texture).
        ph, pw = -(-h // factor) * factor, -(-w // factor) * factor
        if (ph, pw) != (h, w):
            tex = np.pad(tex, ((0, ph - h), (0, pw - w), (0, 0)), mode="edge")
        tex = tex.reshape(ph // factor, factor, pw, 3).mean(axis=1, dtype=np.float32)
        tex = tex.reshape(ph // factor, pw // factor, factor, 3).mean(axis=2, dtype=np.float32)
        if not quiet:
            log.warning("%s: %dx%d texture reduced to %dx%d (limit %d per side)", what, w, h, tex.shape[1],
                        tex.shape[0], max_size)
    bad = ~np.isfinite(tex)
    if bad.any():
        log.warning("%s: %d non-finite texel values replaced by 0", what, int(bad.sum()))
        tex = np.where(bad, np.float32(0.0), tex)
    return np.ascontiguousarray(tex, np.float32)


def _finite_color(value, fallback: float, what: str) -> np.ndarray:
    color = np.asarray(value, np.float32).reshape(3)
    finite = np.abs(color) <= MAX_FINITE_COLOR  # NaN fails the comparison too
    if not finite.all():
        log.warning("%s %s is not finite; using %g", what, color.tolist(), fallback)
        color = np.where(finite, color, np.float32(fallback)).astype(np.float32)
    return color


def sanitized(geometry: Geometry, n_materials: int, n_objects: int, owned: bool = False) -> Geometry:
    """Cast to the documented dtypes and drop triangles that cannot be traced.

    Triangles with non-finite vertices or (near) zero area are dropped with a log line, never
    passed to Embree; shape errors raise InvalidGeometryError. Normals that are missing or
    non-finite fall back to the face normal. owned : the caller gives `geometry`'s arrays up (a
    sync's fresh concatenation): where every triangle is kept, the result takes them as they are
    instead of copies (300k triangles of ~1M corners: 60-220 ms of copies, mostly first touches);
    else the result never shares an array with `geometry`.
    """
    pos = np.asarray(geometry.positions, np.float32).reshape(-1, 3)
    tris = np.asarray(geometry.triangles)
    if tris.size and (tris.ndim != 2 or tris.shape[1] != 3):
        raise InvalidGeometryError(f"triangles must be (T, 3), got {tris.shape}")
    tris = tris.reshape(-1, 3).astype(np.int32, copy=False)  # `subset` copies unless owned
    n_vert = pos.shape[0]
    if tris.size and (tris.min() < 0 or tris.max() >= n_vert):
        raise InvalidGeometryError("triangle indices out of range of the positions")
    normals = np.asarray(geometry.normals, np.float32).reshape(-1, 3)
    uvs = np.asarray(geometry.uvs, np.float32).reshape(-1, 2)
    if normals.shape[0] != n_vert or uvs.shape[0] != n_vert:
        raise InvalidGeometryError("normals and uvs need one row per position")
    tangents = _sanitized_tangents(geometry.tangents, n_vert)
    normal_uvs = getattr(geometry, "normal_uvs", None)
    if normal_uvs is not None:
        normal_uvs = np.asarray(normal_uvs, np.float32).reshape(-1, 2)
        if normal_uvs.shape[0] != n_vert:
            raise InvalidGeometryError("normal_uvs need one row per position")
    mat = np.asarray(geometry.material_index, np.int32).reshape(-1)
    obj = np.asarray(geometry.object_index, np.int32).reshape(-1)
    if mat.shape[0] != tris.shape[0] or obj.shape[0] != tris.shape[0]:
        raise InvalidGeometryError("material_index and object_index need one entry per triangle")
    if mat.size and (mat.min() < 0 or mat.max() >= max(n_materials, 1)):
        raise InvalidGeometryError("material_index out of range of the materials")
    if obj.size and (obj.min() < 0 or obj.max() >= max(n_objects, 1)):
        raise InvalidGeometryError("object_index out of range of the objects")

    finite, area2, size2 = _triangle_sizes(pos, tris, obj, n_objects)
    keep = finite & (area2 > 0.0) & (area2 > ZERO_AREA_RELATIVE * size2)
    dropped = int((~keep).sum())
    if dropped:
        log.warning(
            "dropped %d of %d triangles (non-finite vertices: %d, zero area: %d)",
            dropped, tris.shape[0], int((~finite).sum()), dropped - int((~finite).sum()),
        )
    out = Geometry(pos, tris, normals, uvs, mat, obj, tangents, normal_uvs)
    if not (owned and dropped == 0):
        out = out.subset(keep)
    out.normals = _unit_normals(out)
    return out


def _triangle_sizes(pos: np.ndarray, tris: np.ndarray, obj: np.ndarray, n_objects: int):
    """((T,) bool finite, (T,) float64 twice the area, (T,) float64 squared diagonal of the
    triangle's object's box over its finite triangles) of the triangles `tris` of (V, 3) float32
    positions `pos`, objects `obj` (T,).

    The area in float64 component by component (np.cross and norm over (T, 3, 3) cost ~3x more),
    from float32 corners: a float32 difference would round a tiny triangle far from the origin to
    zero area. In blocks over threads (`blocks.for_blocks`), each block's per-object boxes folded
    together afterwards: the same bits as the whole-array expressions."""
    n_tri = tris.shape[0]
    vert_finite = None if np.isfinite(pos).all() else np.isfinite(pos).all(axis=1)
    finite = np.ones(n_tri, bool)
    area2 = np.empty(n_tri, np.float64)

    def block(a, b):
        t = tris[a:b]
        c0, c1, c2 = (np.take(pos, t[:, k], axis=0) for k in range(3))
        d0 = c0.astype(np.float64)
        with np.errstate(invalid="ignore", over="ignore"):
            e1, e2 = c1 - d0, c2 - d0
            area2[a:b] = np.sqrt((e1[:, 1] * e2[:, 2] - e1[:, 2] * e2[:, 1]) ** 2
                                 + (e1[:, 2] * e2[:, 0] - e1[:, 0] * e2[:, 2]) ** 2
                                 + (e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]) ** 2)
        ob = obj[a:b]
        if vert_finite is not None:
            finite[a:b] = vert_finite[t].all(axis=1)
            keep = np.flatnonzero(finite[a:b])
            c0, c1, c2, ob = c0[keep], c1[keep], c2[keep], ob[keep]
        return _run_boxes(ob, c0, c1, c2)

    n_ids = max(n_objects, int(obj.max(initial=0)) + 1)
    ids, blo, bhi = _fold_boxes(for_blocks(n_tri, block), n_ids)
    diag2 = np.zeros(n_ids)
    diag2[ids] = np.sum((bhi.astype(np.float64) - blo) ** 2, axis=1)
    return finite, area2, diag2[obj]


def _unit_normals(geometry: Geometry) -> np.ndarray:
    """(V, 3) float32 unit normals of `geometry`: its normals normalized, in blocks over threads;
    those missing or non-finite take the face normal (a vertex shared by several triangles takes
    the last one: good enough for a fallback). `sanitized`'s own geometry: its normals are
    normalized in place when they are a float32 C-ordered array (a new array of a million corners
    is 12 MB of pages touched for the first time)."""
    normals = geometry.normals
    writable = normals.dtype == np.float32 and normals.flags.c_contiguous and normals.flags.writeable
    out = normals if writable else np.empty(normals.shape, np.float32)
    # Broken rows, judged by the normals as given (in place, a tiny one is unit by then).
    fix = np.zeros(normals.shape[0], bool)

    def block(a, b) -> bool:  # whether the block holds a broken normal
        n = normals[a:b]
        norm = row_norms(n)  # np.linalg.norm's sums in its order
        fix[a:b] = ~((norm >= 1e-6) & np.isfinite(norm))
        with np.errstate(invalid="ignore"):  # inf / inf where a normal is broken: redone below
            out[a:b] = n / np.maximum(norm, 1e-12)[:, None]
        return bool(fix[a:b].any())

    if not any(for_blocks(normals.shape[0], block)) or not geometry.triangle_count:
        return out
    fn = geometry.face_normals()
    vert_fn = np.zeros_like(normals)
    vert_fn[geometry.triangles.ravel()] = np.repeat(fn, 3, axis=0)
    normals[fix] = vert_fn[fix]
    if out is normals:  # normalized in place above, but for the rows just fixed
        rows = np.flatnonzero(fix)
        fixed = normals[rows]
        normals[rows] = fixed / np.maximum(np.linalg.norm(fixed, axis=1), 1e-12)[:, None]
        return normals
    norm = np.linalg.norm(normals, axis=1)
    return (normals / np.maximum(norm, 1e-12)[:, None]).astype(np.float32)


def _sanitized_tangents(tangents, n_vert: int) -> np.ndarray | None:
    """(V, 4) float32 tangents with non-finite or zero-length rows zeroed (no normal map there),
    or None."""
    if tangents is None:
        return None
    t = np.asarray(tangents, np.float32).reshape(-1, 4)
    if t.shape[0] != n_vert:
        raise InvalidGeometryError("tangents need one row per position")
    bad = ~np.isfinite(t).all(axis=1) | (np.abs(t[:, :3]).sum(axis=1) == 0)
    if bad.any():
        t = t.copy()
        t[bad] = 0.0
    return np.ascontiguousarray(t)


def make_snapshot(
    geometry: Geometry,
    materials: list[Material],
    lights: list[Light] | None = None,
    world: World | None = None,
    objects: list[ObjectInfo] | None = None,
    owned: bool = False,
    viewpoint=None,
) -> SceneSnapshot:
    """Validated snapshot: sanitized geometry, at least one material and one object entry.
    owned : the caller gives `geometry`'s arrays up (`sanitized`). viewpoint : the camera's
    position or None (a non-finite one counts as none)."""
    materials = materials or [Material()]
    n_obj = int(np.max(geometry.object_index, initial=-1)) + 1
    objects = objects if objects is not None else [ObjectInfo(f"object_{i}") for i in range(n_obj)]
    geometry = sanitized(geometry, len(materials), len(objects), owned=owned)
    if viewpoint is not None:
        viewpoint = np.asarray(viewpoint, np.float32).reshape(3)
        viewpoint = viewpoint if np.isfinite(viewpoint).all() else None
    return SceneSnapshot(geometry, materials, list(lights or []), world or World(), objects, viewpoint)


def geometry_from_arrays(
    positions: np.ndarray,
    triangles: np.ndarray,
    material_index: np.ndarray | int = 0,
    object_index: np.ndarray | int = 0,
    normals: np.ndarray | None = None,
    uvs: np.ndarray | None = None,
) -> Geometry:
    """Convenience constructor for procedural scenes and tests: flat normals when none are given.

    Without normals, every triangle gets its own three vertices so flat shading is exact.
    """
    positions = np.asarray(positions, np.float32).reshape(-1, 3)
    triangles = np.asarray(triangles, np.int64).reshape(-1, 3)
    t = triangles.shape[0]
    if normals is None:
        corners = triangles.ravel()
        positions = positions[corners]
        if uvs is not None:
            uvs = np.asarray(uvs, np.float32).reshape(-1, 2)[corners]
        triangles = np.arange(3 * t, dtype=np.int32).reshape(-1, 3)
        g = Geometry(positions, triangles, np.zeros_like(positions), np.zeros((3 * t, 2), np.float32),
                     np.zeros(t, np.int32), np.zeros(t, np.int32))
        normals = np.repeat(g.face_normals(), 3, axis=0)
    mat = np.broadcast_to(np.asarray(material_index, np.int32), (t,)).copy()
    obj = np.broadcast_to(np.asarray(object_index, np.int32), (t,)).copy()
    if uvs is None:
        uvs = np.full((positions.shape[0], 2), np.nan, np.float32)
    return Geometry(positions, triangles.astype(np.int32), np.asarray(normals, np.float32), np.asarray(uvs, np.float32), mat, obj)


#: Corners from which `concat_geometry` spreads its copies over threads.
CONCAT_THREADED_ROWS = 65536


def concat_geometry(parts: list[Geometry], out: dict | None = None) -> Geometry:
    """Join geometries, offsetting triangle indices.

    Each part's rows are copied into arrays of the whole, the copies spread over threads (numpy
    copies without the GIL) from CONCAT_THREADED_ROWS corners on: the atrium's 960k corners took
    39 ms of one core in np.concatenate's copies, mostly first touches of the new arrays. The
    same values, cast as `astype` casts. out : optional arrays of the whole, by field name (the
    right shape and dtype), used instead of new ones; a part's rows already there (the same
    memory: written in place by their maker) are not copied again."""
    if not parts:
        return Geometry(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32), np.zeros((0, 3), np.float32),
                        np.zeros((0, 2), np.float32), np.zeros(0, np.int32), np.zeros(0, np.int32))
    given = out or {}  # arrays of the whole the caller made
    v_starts = np.cumsum([0] + [p.positions.shape[0] for p in parts]).tolist()
    t_starts = np.cumsum([0] + [p.triangles.shape[0] for p in parts]).tolist()
    n_v, n_t = v_starts[-1], t_starts[-1]
    whole = {
        "positions": np.empty((n_v, 3), np.float32),
        "normals": np.empty((n_v, 3), np.float32),
        "uvs": np.empty((n_v, 2), np.float32),
        "triangles": np.empty((n_t, 3), np.int32),
        "material_index": np.empty(n_t, np.int32),
        "object_index": np.empty(n_t, np.int32),
    }
    if any(getattr(p, "normal_uvs", None) is not None for p in parts):
        whole["normal_uvs"] = np.empty((n_v, 2), np.float32)
    if any(p.tangents is not None for p in parts):
        whole["tangents"] = np.empty((n_v, 4), np.float32)
    for name, array in given.items():
        if array.shape != whole[name].shape or array.dtype != whole[name].dtype:
            raise ValueError(f"concat_geometry: out[{name!r}] is {array.dtype} {array.shape}, "
                             f"not {whole[name].dtype} {whole[name].shape}")
        whole[name] = array
    per_triangle = ("triangles", "material_index", "object_index")
    copies = []  # (destination rows, source or None for zeros, triangle index offset or None)
    for p, v0, v1, t0, t1 in zip(parts, v_starts[:-1], v_starts[1:], t_starts[:-1], t_starts[1:], strict=True):
        for name, dst in whole.items():
            src = getattr(p, name)
            if name == "normal_uvs" and src is None:
                src = p.uvs  # a part without a normal-map UV map reads its own
            rows = dst[t0:t1] if name in per_triangle else dst[v0:v1]
            if src is not None and _same_rows(rows, src):
                continue  # written there in place
            copies.append((rows, src, v0 if name == "triangles" else None))

    def copy(a, b):
        for dst, src, offset in copies[a:b]:
            if src is None:  # a part without tangents: no normal map there
                dst[...] = 0.0
            elif offset is None:
                np.copyto(dst, src, casting="unsafe")
            else:
                np.add(src, offset, out=dst, casting="unsafe")

    for_blocks(len(copies), copy, 1 if n_v >= CONCAT_THREADED_ROWS else len(copies))
    return Geometry(**whole)


def _same_rows(dst: np.ndarray, src: np.ndarray) -> bool:
    """Whether `src` is the very memory of `dst` (the same start, shape, strides and dtype)."""
    return (src.shape == dst.shape and src.dtype == dst.dtype and src.strides == dst.strides
            and src.__array_interface__["data"][0] == dst.__array_interface__["data"][0])

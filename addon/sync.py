"""Depsgraph -> `SceneSnapshot`: the one module that reads scene data for the core.

Main thread only: it reads `bpy` data. Everything it returns is numpy arrays and plain Python
values (no bpy object survives in the snapshot), so the core's worker threads can use it freely.

Conventions (Cycles', checked against its Diffuse Direct pass to < 1%): geometry in world space with modifiers, instances and
geometry nodes applied; lights in Blender's units with colour x temperature, a constant node tree's
emission and exposure folded into `color`/`power` (portals skipped; EEVEE's diffuse and specular
factors not read, as Cycles does not), area-light sizes unscaled (the object's scale stays
in the matrix); materials reduced to a Lambertian base colour (optionally an image) plus emission radiance, with
glossy closures (`hybridgi_core.specular`: a Principled BSDF's specular layer and metallic lobe, Glossy,
Metallic and Glass BSDFs, mixed by constant, Fresnel or Layer Weight factors: `hybridgi_core.surface_mix`)
and the view-dependent weight they leave the diffuse part.
"""

import hashlib
import logging
import math
import os
from dataclasses import dataclass, replace

import numpy as np

from hybridgi_core import corner_triangles, environment, flat_faces, hair, ies, points, surface_mix
from hybridgi_core import snapshot as snap
from hybridgi_core import specular as sp
from hybridgi_core.blackbody import blackbody_rgb
from hybridgi_core.blocks import for_blocks
from hybridgi_core.errors import LimitError
from hybridgi_core.glossy import MIN_ROUGHNESS
from hybridgi_core.rows import cross_rows, equal_rows, float_bits
from hybridgi_core.specular import SpecularLayer

from . import compat, material_bake, world_bake
from .bake_store import BakeStore

log = logging.getLogger(__name__)

#: Albedo of materials this module cannot interpret (Blender's default material colour).
FALLBACK_GREY = 0.8
#: Roughness over which a Principled BSDF's transmission counts as diffuse light from behind (a
#: Translucent BSDF's) rather than as clear glass, rising linearly to all of it at
#: FROSTED_ROUGHNESS[1]. Why: Cycles' rough refraction blurs what lies behind into a milky glow
#: (a sphere of transmission 0.5 looks like a white matte ball, one of 1 at roughness 0.4 frosted),
#: which clear glass (a hole for the camera) lost altogether: spheres of transmission 0.5 at
#: roughness 0.2 / 0.4 / 0.7 vanished against Cycles' white ones (320x120 against Cycles 256 spp,
#: Combined over each sphere 0.48 / 0.44 / 0.57 -> 0.16 / 0.09 / 0.10). Frosted light counts half
#: towards clear glass (`_shader_surface`): at transmission 1 the blurred view of what lies behind
#: is nearer a hole's than a milky surface's (roughness 0.7: 0.43 as a hole, 0.56 translucent).
FROSTED_ROUGHNESS = (0.2, 0.4)

#: Colour spaces of byte images: sRGB-encoded values are linearized, linear ones kept; any other
#: (Display P3, Rec.2020, log encodings) is read as linear Rec.709 with a warning.
SRGB_SPACES = frozenset({"sRGB"})
LINEAR_SPACES = frozenset({"Linear Rec.709", "Non-Color", "scene_linear"})

#: Output-node target: Cycles is the reference the engine is compared against.
OUTPUT_TARGET = "CYCLES"


def snapshot_from_depsgraph(depsgraph, dynamic_names=frozenset(), wait_for_world=True):
    """The evaluated scene of `depsgraph` as a validated `SceneSnapshot`.

    dynamic_names : names of objects that move or deform over the animation; an instance is
        dynamic when its object or its instancer is named here.

    An empty scene gives a snapshot with no triangles (its `bounds()` raises EmptySceneError),
    so a scene lit only by the sky still syncs; the pipeline decides whether that is an error.
    wait_for_world=False (the viewport) also lets colour inputs that need a bake
    (`material_bake`) keep their constant value until the background bake is done.
    """
    if wait_for_world:
        start_world_bakes(depsgraph.scene.world)
    builder = _SnapshotBuilder(frozenset(dynamic_names), _collection_flags(depsgraph.view_layer),
                               wait=wait_for_world, render_mode=getattr(depsgraph, "mode", "RENDER") == "RENDER",
                               texture_limit=texture_limit(depsgraph.scene),
                               material_override=material_override(depsgraph))
    for instance in depsgraph.object_instances:
        builder.add_instance(instance)
    builder.warn_unsupported()
    builder.bake_materials()
    world, world_lamps = read_world(depsgraph.scene.world, wait_for_world)
    builder.lights += world_lamps
    camera = depsgraph.scene.camera
    viewpoint = None if camera is None else tuple(camera.evaluated_get(depsgraph).matrix_world.translation)
    return builder.finish(world, viewpoint)


def material_override(depsgraph):
    """The view layer's Material Override (View Layer > Filter, a clay render), evaluated
    (its animated values), or None. Cycles and EEVEE render every surface with it, objects
    without a material included; lamps and the world keep theirs."""
    override = getattr(depsgraph.view_layer, "material_override", None)
    if override is None:
        return None
    try:
        return depsgraph.id_eval_get(override)
    except (AttributeError, KeyError, RuntimeError, TypeError):
        return override


#: Cycles' per-object ray visibility HybridGI does not follow (the object takes part as if on):
#: property -> what it means, for the warning.
IGNORED_VISIBILITY = {
    "visible_diffuse": "hidden from diffuse rays",
    "visible_glossy": "hidden from glossy rays",
}


def _collection_flags(view_layer) -> dict[str, set[str]]:
    """Object name -> {"holdout", "indirect_only"} flags its view-layer collections set."""
    flags: dict[str, set[str]] = {}

    def walk(layer_collection, inherited):
        own = set(inherited)
        if layer_collection.holdout:
            own.add("holdout")
        if layer_collection.indirect_only:
            own.add("indirect_only")
        if own:
            for obj in layer_collection.collection.objects:
                flags.setdefault(obj.name, set()).update(own)
        for child in layer_collection.children:
            walk(child, own)

    if view_layer is not None:
        walk(view_layer.layer_collection, set())
    return flags


@dataclass(slots=True)
class _LocalMesh:
    """One evaluated mesh in object space, split per corner (face corners are the vertices).

    positions, normals : (L, 3) float32; uvs : (L, 2) float32 (NaN without a UV map)
    triangles : (T, 3) int32 corner indices; slot : (T,) int32 material slot of each triangle
    tangents : (L, 4) float32 object-space tangent and bitangent sign (`mesh_tangents`), or None
    normal_uvs : (L, 2) float32 the mesh's own UVs where `uvs` holds a bake's atlas (`with_atlas`:
        what normal and bump maps are read with), or None (`uvs`)
    source : (L,) int64 the Blender corner each corner copies (corners appended for the bent
        triangles of flat faces, `flat_faces`), what Blender's per-corner data is read at; None:
        corner i is Blender's corner i
    """

    positions: np.ndarray
    normals: np.ndarray
    uvs: np.ndarray
    triangles: np.ndarray
    slot: np.ndarray
    tangents: np.ndarray | None = None
    normal_uvs: np.ndarray | None = None
    source: np.ndarray | None = None

    def blender_corners(self, corners: np.ndarray) -> np.ndarray:
        """The Blender corners of corners (indices into this mesh's corners)."""
        return corners if self.source is None else self.source[corners]


#: Object types whose geometry is rendered (Curves as tubes, point clouds as spheres).
SURFACE_TYPES = ("MESH", "CURVES", "POINTCLOUD")
#: Strands of one particle hair system read (one `co_hair` call per point each).
MAX_PARTICLE_STRANDS = 50_000
#: Corners x instances that `transformed` maps in one block.
TRANSFORM_BLOCK = 1 << 17


def _hair_shape(shape, root, tip, t):
    """Cycles' shaperadius: the strand's radius factor from root to tip at t (0..1) by Shape."""
    radius = 1.0 - np.asarray(t, np.float64)
    if shape < 0.0:
        radius = radius ** (1.0 + shape)
    elif shape > 0.0:
        radius = radius ** (1.0 / max(1.0 - shape, 1e-6))
    return radius * (root - tip) + tip


def _hair_arrays(curves, name):
    """`_LocalMesh` of a Blender Curves datablock's strands as tubes, or None without any."""
    n_points, n_curves = len(curves.points), len(curves.curves)
    if n_points < 2 or n_curves == 0:
        return None
    points_ = np.empty(n_points * 3, np.float32)
    curves.position_data.foreach_get("vector", points_)
    offsets = np.empty(n_curves + 1, np.int32)
    curves.curve_offset_data.foreach_get("value", offsets)
    tubes = hair.tubes(points_, offsets, _radii(curves.attributes, n_points))
    return _shape_local(tubes, curves.attributes, "CURVE", n_curves, ("hair", "strands"), name)


def _pointcloud_arrays(cloud, name):
    """`_LocalMesh` of a PointCloud's points as spheres (`hybridgi_core.points`; no UVs), or None."""
    n = len(cloud.points)
    if n == 0:
        return None
    positions = np.empty(n * 3, np.float32)
    cloud.attributes["position"].data.foreach_get("vector", positions)
    spheres = points.spheres(positions, _radii(cloud.attributes, n))
    return _shape_local(spheres, cloud.attributes, "POINT", n, ("point cloud", "points"), name)


def _radii(attributes, n: int) -> np.ndarray:
    """(n,) float32 the points' "radius" attribute, Blender's radius where it is missing."""
    radii = np.full(n, points.DEFAULT_RADIUS, np.float32)
    radius = attributes.get("radius")
    if radius is not None and radius.domain == "POINT" and radius.data_type == "FLOAT":
        radius.data.foreach_get("value", radii)
    return radii


def _shape_local(shape, attributes, domain: str, count: int, words: tuple[str, str], name):
    """`_LocalMesh` of a `hair.ShapeMesh` made of `count` elements (strands, points) of the object
    `name`, or None when it has no triangle: a warning when it was thinned, each triangle's slot
    its element's material_index (on `domain`), no UVs. words : (what it is, its elements)."""
    if shape.thinned > 1:
        log.warning("%s %r: %d %s are more than %d triangles; every %d-th is kept, widened to cover as much",
                    words[0], name, count, words[1], hair.TRIANGLE_BUDGET, shape.thinned)
    if shape.triangles.shape[0] == 0:
        return None
    slot = np.zeros(shape.triangles.shape[0], np.int32)
    index = attributes.get("material_index")
    if index is not None and index.domain == domain and index.data_type == "INT":
        per_element = np.empty(count, np.int32)
        index.data.foreach_get("value", per_element)
        slot = per_element[shape.source]
    return _LocalMesh(positions=shape.positions, normals=shape.normals,
                      uvs=np.full((shape.positions.shape[0], 2), np.nan, np.float32), triangles=shape.triangles,
                      slot=slot)


def corner_verts(mesh) -> np.ndarray:
    """(corners,) int32 the vertex of each face corner of a Blender mesh (its `.corner_vert`)."""
    out = np.empty(len(mesh.loops), np.int32)
    mesh.attributes[".corner_vert"].data.foreach_get("value", out)
    return out


def mesh_arrays(mesh):
    """`_LocalMesh` of a Blender mesh, or None when it has no polygons.

    One foreach_get per attribute into arrays of the attribute's own dtype (a dtype mismatch
    makes foreach_get several times slower).
    """
    n_poly = len(mesh.polygons)
    if n_poly == 0:
        return None
    n_vert = len(mesh.vertices)
    n_corner = len(mesh.loops)

    vert_pos = np.empty(n_vert * 3, np.float32)
    mesh.attributes["position"].data.foreach_get("vector", vert_pos)
    corner_vert = corner_verts(mesh)
    positions = np.take(vert_pos.reshape(-1, 3), corner_vert, axis=0)  # ~5x fancy indexing's speed
    triangles, tri_poly = _corner_triangles(mesh, n_poly, n_corner, positions)
    if triangles.shape[0] == 0:
        return None
    normals = np.empty(n_corner * 3, np.float32)
    mesh.corner_normals.foreach_get("vector", normals)

    # Cycles' Image Textures without a Vector input read the UV map active for rendering.
    uv_layer = next((layer for layer in mesh.uv_layers if layer.active_render), mesh.uv_layers.active)
    if uv_layer is not None:
        uvs = np.empty(n_corner * 2, np.float32)
        uv_layer.uv.foreach_get("vector", uvs)
        uvs = uvs.reshape(-1, 2)
    else:
        uvs = np.full((n_corner, 2), np.nan, np.float32)

    material_attr = mesh.attributes.get("material_index")
    if material_attr is not None and material_attr.domain == "FACE" and material_attr.data_type == "INT":
        poly_slot = np.empty(n_poly, np.int32)
        material_attr.data.foreach_get("value", poly_slot)
        slot = poly_slot[tri_poly]
    else:
        slot = np.zeros(triangles.shape[0], np.int32)

    normals = normals.reshape(-1, 3)
    source = None
    smooth = np.empty(n_poly, bool)
    mesh.polygons.foreach_get("use_smooth", smooth)
    if not smooth.all():
        bent = flat_faces.bent_flat_triangles(smooth, positions, normals, triangles, tri_poly)
        if bent.size:
            triangles, positions, normals, uvs, source = flat_faces.own_corners(bent, triangles, positions, normals,
                                                                               uvs)
    return _LocalMesh(
        positions=positions,
        normals=normals,
        uvs=uvs,
        triangles=triangles,
        slot=slot,
        source=source,
    )


def _corner_triangles(mesh, n_poly: int, n_corner: int, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(triangles (T, 3) corner indices, each triangle's face (T,)) int32: Blender's
    `loop_triangles`, made here where the faces are triangles and quads (`corner_triangles`:
    reading them costs a getter call per triangle), read from Blender where a face is an n-gon."""
    if n_poly >= corner_triangles.MIN_FACES and n_corner <= 4 * n_poly:  # (else a face has 5 corners or more)
        sizes = np.empty(n_poly, np.int32)
        mesh.polygons.foreach_get("loop_total", sizes)
        made = corner_triangles.from_sizes(sizes, positions)
        if made is not None:
            return made
    n_tri = len(mesh.loop_triangles)
    triangles = np.empty(n_tri * 3, np.int32)
    mesh.loop_triangles.foreach_get("loops", triangles)
    tri_poly = np.empty(n_tri, np.int32)
    mesh.loop_triangle_polygons.foreach_get("value", tri_poly)
    return triangles.reshape(-1, 3), tri_poly


def mesh_tangents(mesh, uv_map=""):
    """(L, 4) float32 per-corner tangent and bitangent sign of `mesh` for the UV map `uv_map`
    ("" = the active render map), as Blender computes them for Cycles' Normal Map node
    (MikkTSpace, `Mesh.calc_tangents`); None when the mesh has no such UV map.

    MikkTSpace needs triangles and quads: a mesh with n-gons takes per-triangle UV tangents
    averaged over the corners that share a vertex and a UV (`uv_tangents`), near it on smooth
    surfaces."""
    layer = (mesh.uv_layers.get(uv_map) if uv_map
             else next((layer for layer in mesh.uv_layers if layer.active_render), mesh.uv_layers.active))
    if layer is None:
        return None
    n_corner = len(mesh.loops)
    try:
        mesh.calc_tangents(uvmap=layer.name)
    except RuntimeError:  # n-gons
        return _ngon_tangents(mesh, layer)
    tangents = np.empty((n_corner, 4), np.float32)
    vec = np.empty(n_corner * 3, np.float32)
    mesh.loops.foreach_get("tangent", vec)
    tangents[:, :3] = vec.reshape(-1, 3)
    sign = np.empty(n_corner, np.float32)
    mesh.loops.foreach_get("bitangent_sign", sign)
    tangents[:, 3] = sign
    mesh.free_tangents()
    return tangents


def _ngon_tangents(mesh, layer):
    n_corner = len(mesh.loops)
    corner_vert = corner_verts(mesh)
    vert_pos = np.empty(len(mesh.vertices) * 3, np.float32)
    mesh.attributes["position"].data.foreach_get("vector", vert_pos)
    triangles = np.empty(len(mesh.loop_triangles) * 3, np.int32)
    mesh.loop_triangles.foreach_get("loops", triangles)
    normals = np.empty(n_corner * 3, np.float32)
    mesh.corner_normals.foreach_get("vector", normals)
    uvs = np.empty(n_corner * 2, np.float32)
    layer.uv.foreach_get("vector", uvs)
    return uv_tangents(vert_pos.reshape(-1, 3)[corner_vert], normals.reshape(-1, 3), uvs.reshape(-1, 2),
                       triangles.reshape(-1, 3), corner_vert)


def uv_tangents(positions, normals, uvs, triangles, corner_vert):
    """(L, 4) float32 tangents of corners (positions, normals (L, 3), uvs (L, 2)) from the UV
    gradients of the triangles (T, 3) they belong to, summed over the corners that share a vertex
    (`corner_vert` (L,)) and a UV, made perpendicular to each corner's normal; w is the sign of
    the UV map's handedness. Rows of zeros where the UVs give no direction."""
    p = positions[triangles].astype(np.float64)
    t = uvs[triangles].astype(np.float64)
    e1, e2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    d1, d2 = t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]
    det = d1[:, 0] * d2[:, 1] - d2[:, 0] * d1[:, 1]
    # dP/du and dP/dv, unnormalized (weighted by area, as MikkTSpace's sum is by angle).
    sgn = np.where(det < 0, -1.0, 1.0)[:, None]
    tu = (e1 * d2[:, 1:2] - e2 * d1[:, 1:2]) * sgn
    tv = (e2 * d1[:, 0:1] - e1 * d2[:, 0:1]) * sgn
    # Corners welded by vertex and UV share one sum.
    group = equal_rows(np.asarray(corner_vert).reshape(-1), float_bits(uvs[:, 0]), float_bits(uvs[:, 1]))
    su = np.zeros((group.max(initial=-1) + 1, 3))
    sv = np.zeros_like(su)
    for c in range(3):
        np.add.at(su, group[triangles[:, c]], tu)
        np.add.at(sv, group[triangles[:, c]], tv)
    n = normals.astype(np.float64)
    u = su[group] - n * np.sum(su[group] * n, axis=1, keepdims=True)
    length = np.linalg.norm(u, axis=1, keepdims=True)
    out = np.zeros((positions.shape[0], 4), np.float32)
    ok = (length[:, 0] > 1e-20) & np.isfinite(length[:, 0])
    out[ok, :3] = u[ok] / length[ok]
    out[ok, 3] = np.where(np.sum(np.cross(n[ok], u[ok]) * sv[group][ok], axis=1) < 0, -1.0, 1.0)
    return out


def transformed(local, matrices, slot_to_material, first_object, out=None):
    """`Geometry` of instances of `local`, one per (4, 4) matrix of `matrices` (I, 4, 4), finite,
    instance i with object index first_object + i (or first_object[i]: an (I,) array): a
    scattered mesh (thousands of rocks or leaves of one instancer) is transformed in a few
    batched numpy calls, not a dozen calls per instance.

    out : optional (positions, normals), (I, corners, 3) float32 arrays (views of the snapshot's
    whole arrays: `_SnapshotBuilder._placed_parts`) the instances' positions and normals are
    written into, instead of new arrays that `concat_geometry` would copy there.

    slot_to_material : (S,) int32 global material index of each material slot (at least one).
    A zero scale on one axis flattens the object, as in Cycles, which still renders it (a plane
    seen from both sides); on two axes its triangles have no area and the snapshot drops them.
    """
    m = np.asarray(matrices, np.float64).reshape(-1, 4, 4)
    count, corners = m.shape[0], local.positions.shape[0]
    linear = m[:, :3, :3]
    det = np.linalg.det(linear)
    # Normals transform with the cofactor matrix (det x inverse transpose), so non-uniform scale
    # keeps them perpendicular; unlike the inverse it exists for a flattened object, whose
    # normals all turn along the squashed axis. Only their direction counts (renormalized below).
    sign = np.where(det < 0, -1.0, 1.0)[:, None, None]
    to_world, to_normal = linear.transpose(0, 2, 1), _cofactor(linear).transpose(0, 2, 1) * sign
    if out is None:
        positions = np.empty((count, corners, 3), np.float32)
        normals = np.empty((count, corners, 3), np.float32)
    else:
        positions, normals = out
    # In blocks of corners: the float64 temporaries of a 900k-triangle mesh (2.6 M corners, 60 MB
    # each) stay in cache and their pages are reused, not faulted in afresh (its positions' matmul
    # 76-507 ms in one go, 37-115 ms in blocks on this 2-core VM). The same arithmetic row by
    # row: the same bits (dragon_npm renders identically).
    # The blocks run on a few threads (`blocks.for_blocks`), each writing its own corners.

    def block(a, b):
        positions[:, a:b] = np.matmul(local.positions[a:b], to_world) + m[:, None, :3, 3]
        nb = np.matmul(local.normals[a:b], to_normal).astype(np.float32)
        length = np.sqrt(np.einsum("ilk,ilk->il", nb, nb))[..., None]
        normals[:, a:b] = np.divide(nb, length, out=np.zeros_like(nb), where=length > 0)

    for_blocks(corners, block, max(1, TRANSFORM_BLOCK // count))
    tangents = None
    if local.tangents is not None:
        # Tangents are surface directions: they follow the linear map itself. A mirroring
        # transform swaps the frame's handedness, so the bitangent sign flips with det.
        tangents = np.empty((count, corners, 4), np.float32)
        vec = np.matmul(local.tangents[:, :3], linear.transpose(0, 2, 1))
        length = np.sqrt(np.einsum("ilk,ilk->il", vec, vec))[..., None]
        tangents[..., :3] = np.divide(vec, length, out=np.zeros_like(vec), where=length > 0)
        tangents[..., 3] = local.tangents[None, :, 3] * np.where(det < 0, -1.0, 1.0)[:, None]
        tangents = tangents.reshape(-1, 4)
    n_tri = local.triangles.shape[0]
    triangles = np.empty((count, n_tri, 3), np.int32)
    triangles[:] = local.triangles
    # A mirroring transform flips the winding; reverse it so geometric and shading normals agree.
    triangles[det < 0] = local.triangles[:, ::-1]
    triangles += (np.arange(count, dtype=np.int32) * np.int32(corners))[:, None, None]
    slots = np.clip(local.slot, 0, len(slot_to_material) - 1)
    return snap.Geometry(
        positions=positions.reshape(-1, 3),
        triangles=triangles.reshape(-1, 3),
        normals=normals.reshape(-1, 3),
        uvs=local.uvs if count == 1 else np.tile(local.uvs, (count, 1)),
        material_index=np.tile(np.asarray(slot_to_material, np.int32)[slots], count),
        object_index=np.repeat(np.arange(first_object, first_object + count, dtype=np.int32) if np.ndim(first_object) == 0
                               else np.asarray(first_object, np.int32), n_tri),
        tangents=tangents,
        normal_uvs=(None if local.normal_uvs is None else
                    local.normal_uvs if count == 1 else np.tile(local.normal_uvs, (count, 1))),
    )


def _instance_part(batch, i: int, corners: int, n_tri: int):
    """Instance i of a `transformed` batch of a mesh of `corners` corners and `n_tri` triangles
    as a `Geometry` of its own (views of the batch; its triangles numbered from its corners)."""
    rows = slice(i * corners, (i + 1) * corners)
    tris = slice(i * n_tri, (i + 1) * n_tri)
    return snap.Geometry(
        positions=batch.positions[rows], triangles=batch.triangles[tris] - np.int32(i * corners),
        normals=batch.normals[rows], uvs=batch.uvs[rows], material_index=batch.material_index[tris],
        object_index=batch.object_index[tris], tangents=None if batch.tangents is None else batch.tangents[rows],
        normal_uvs=None if batch.normal_uvs is None else batch.normal_uvs[rows])


def _listed(names, shown=5) -> str:
    names = sorted(names)
    return ", ".join(repr(n) for n in names[:shown]) + (f" and {len(names) - shown} more" if len(names) > shown else "")


def _cofactor(m):
    """(I, 3, 3) cofactor matrices of `m` (I, 3, 3) (det(m) inv(m).T where m is invertible)."""
    return np.stack([cross_rows(m[:, 1], m[:, 2]), cross_rows(m[:, 2], m[:, 0]), cross_rows(m[:, 0], m[:, 1])],
                    axis=1)


#: Bytes a placed triangle costs at the render's peak (its corners in the snapshot, the BVH, the
#: shading tables, the G-buffer's vertex buffers): 10.2M triangles of 500 instanced spheres
#: peaked at 2.4 GB (0.4 GB of it Blender's own).
BYTES_PER_TRIANGLE = 200
#: Share of the memory the system has available that a scene's triangles may take.
MEMORY_SHARE = 0.8


def available_memory() -> int | None:
    """Bytes the system can still give this process (Linux: MemAvailable), or None where unknown."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        return None
    return None


def check_flattened_size(triangles: int, available: int | None = None) -> None:
    """Raise `LimitError` before the instances are placed when their `triangles` would take more
    than MEMORY_SHARE of the memory available (`available_memory` unless given). Why: every
    instance is copied into one mesh (Cycles instances them), and a scatter of a few thousand
    detailed trees is hundreds of millions of triangles; the process was killed by the system
    part way instead of saying so."""
    available = available_memory() if available is None else available
    if available is None or triangles * BYTES_PER_TRIANGLE <= MEMORY_SHARE * available:
        return
    need, have = triangles * BYTES_PER_TRIANGLE / 2**30, available / 2**30
    raise LimitError(
        f"the scene holds {triangles:,} triangles once its instances are placed, about {need:.1f} GiB to render "
        f"with {have:.1f} GiB free: HybridGI copies every instance (Cycles shares them); scatter fewer or "
        "simpler instances (Simplify > Max Child Particles, the instancer's density or a lower-poly object)")


class _SnapshotBuilder:
    def __init__(self, dynamic_names, collection_flags=None, wait=True, render_mode=True,
                 texture_limit=snap.MAX_TEXTURE_SIZE, material_override=None):
        self.dynamic_names = dynamic_names
        #: The view layer's Material Override: every slot's material when set (`material_override`).
        self.material_override = material_override
        self.wait = wait
        self.render_mode = render_mode  # a render's depsgraph: particle paths at their render steps
        self._baked = {}  # (material, mesh pointer, slot) -> material index
        self._optional_left = OPTIONAL_BAKE_JOBS  # mask and height bakes this sync may still queue
        self._optional_granted = set()  # (material, mesh pointer, slot) whose optional bakes were queued
        self._bakes = []  # (material index, bpy material, [BakeJob])
        self._atlas_meshes = {}  # (mesh pointer, baked slots) -> _LocalMesh with atlas UVs
        self._sockets = {}  # material pointer -> its `bake_sockets` (one walk of its tree per sync)
        self._variants = {}  # (material, mesh pointer, slot) -> the Object Info value sets baked
        self._object_outputs = {}  # material name -> `object_info_outputs`, read once per sync
        self._variant_warned = set()
        self.without_material = set()  # object names (Cycles gives them a glossy default)
        self.volumes = set()  # Volume objects' names: not rendered, warned once
        self.collection_flags = collection_flags or {}
        self.ignored: dict[str, set[str]] = {}  # what is approximated -> object names, warned once
        #: Instances to place (`_add_placed`): key -> [local mesh, slot materials, [object index],
        #: [matrix]], and (key, instance) in the order they came.
        self._groups = {}
        self._order = []
        self.objects = []
        self.lights = []
        self.lamp_notes: dict[str, set[str]] = {}  # what of a lamp is approximated -> lamp names
        self.materials = []
        self._material_index = {}
        self._meshes = {}  # evaluated mesh pointer -> _LocalMesh | None, shared by its instances
        self._tangent_meshes = {}  # (mesh pointer, UV map) -> the _LocalMesh with its tangents
        self._textures = _TextureCache(texture_limit)

    def add_instance(self, instance):
        obj = instance.object
        self._note_linking(obj)
        if obj.type == "LIGHT":
            lamp = light_from_blender(obj.data, instance.matrix_world, obj.name, obj, self.lamp_notes)
            if lamp is not None:
                self.lights.append(lamp)
            return
        if obj.type == "MESH" and instance.show_particles and len(obj.particle_systems):
            self._add_particle_hair(instance)
        if obj.type == "VOLUME" and instance.show_self:
            # Cycles renders a Volume object's grids (smoke, clouds, Mesh to Volume) through its
            # volume shader; HybridGI renders surfaces only: named, left out, the rest rendered.
            self.volumes.add(obj.name if not instance.is_instance or instance.parent is None
                             else instance.parent.name)
            return
        # Meshes, Curves (hair) as tubes and point clouds as spheres: curves, text, surfaces and
        # metaballs also arrive as a mesh instance of their evaluated geometry (converting them too
        # would count them twice).
        if obj.type not in SURFACE_TYPES or not instance.show_self:
            return
        local = self._local_mesh(obj) if obj.type == "MESH" else self._shape_mesh(obj)
        if local is None:
            return
        parent = instance.parent if instance.is_instance else None
        dynamic = obj.name in self.dynamic_names or (parent is not None and parent.name in self.dynamic_names)
        matrix = np.asarray(instance.matrix_world, np.float64)
        if not np.isfinite(matrix).all():
            log.debug("skipped %s: singular transform", obj.name)
            return
        slot_to_material, local = self._slot_materials(obj, local, dynamic, instance=instance)
        self._add_placed(local, slot_to_material, matrix)
        # A curve's own mesh instance has the curve as its parent: keep its plain name.
        name = obj.name if parent is None or parent.name == obj.name else f"{parent.name}/{obj.name}"
        camera_visible = bool(getattr(obj, "visible_camera", True))
        casts_shadow = bool(getattr(obj, "visible_shadow", True)) and (
            parent is None or parent.name == obj.name or bool(getattr(parent, "visible_shadow", True)))
        holdout = bool(getattr(obj, "is_holdout", False)) or "holdout" in self.collection_flags.get(obj.name, ())
        catcher = bool(getattr(obj, "is_shadow_catcher", False))
        if parent is not None and parent.name != obj.name:
            camera_visible = camera_visible and bool(getattr(parent, "visible_camera", True))
            holdout = holdout or bool(getattr(parent, "is_holdout", False)) or (
                "holdout" in self.collection_flags.get(parent.name, ()))
            catcher = catcher or bool(getattr(parent, "is_shadow_catcher", False))
        if catcher and not self.render_mode:
            # Final renders compose it (`catcher.py`); the viewport draws the plain surface.
            self.ignored.setdefault("a shadow catcher (composed in final renders only)", set()).add(name)
        self._note_ignored(obj)
        self.objects.append(snap.ObjectInfo(name=name, dynamic=dynamic, camera_visible=camera_visible,
                                            holdout=holdout, casts_shadow=casts_shadow, shadow_catcher=catcher))

    def _add_particle_hair(self, instance):
        """Particle systems of type Hair rendered as strands (Render As Path) as tubes, in world
        space (`ParticleSystem.co_hair`), children included; past MAX_PARTICLE_STRANDS every n-th
        strand is read, widened by sqrt(n) (warned)."""
        obj = instance.object
        for psys in obj.particle_systems:
            settings = psys.settings
            if settings.type != "HAIR" or settings.render_type != "PATH":
                continue
            total = len(psys.particles) + len(psys.child_particles)
            steps = (1 << int(settings.render_step if self.render_mode else settings.display_step)) + 1
            if total == 0:
                continue
            stride = max(1, math.ceil(total / MAX_PARTICLE_STRANDS))
            if stride > 1:
                log.warning("hair %r of %r: %d strands; every %d-th is rendered, widened to cover as much",
                            psys.name, obj.name, total, stride)
            strands = range(0, total, stride)
            points = np.array([tuple(psys.co_hair(obj, particle_no=i, step=k)) for i in strands for k in range(steps)],
                              np.float32).reshape(len(strands), steps, 3)
            # Steps past a strand's path read as the origin: each strand's points up to the first.
            valid = np.any(points != 0.0, axis=2)
            valid[:, 0] = True
            counts = np.where(valid.all(axis=1), steps, np.argmin(valid, axis=1))
            keep = np.arange(steps)[None, :] < counts[:, None]
            t = np.broadcast_to(np.arange(steps) / max(steps - 1, 1), points.shape[:2])
            radii = 0.5 * settings.radius_scale * _hair_shape(settings.shape, settings.root_radius,
                                                              settings.tip_radius, t) * math.sqrt(stride)
            offsets = np.concatenate([[0], np.cumsum(counts)])
            tubes = hair.tubes(points[keep], offsets, radii[keep].astype(np.float32))
            if tubes.triangles.shape[0] == 0:
                continue
            local = _LocalMesh(positions=tubes.positions, normals=tubes.normals,
                               uvs=np.full((tubes.positions.shape[0], 2), np.nan, np.float32),
                               triangles=tubes.triangles,
                               slot=np.full(tubes.triangles.shape[0], max(int(settings.material) - 1, 0), np.int32))
            slot_to_material, local = self._slot_materials(obj, local, bakes=False)
            # co_hair gives the emitter's own world space: an instance of it moves the strands along.
            matrix = np.eye(4)
            if instance.is_instance:
                matrix = np.asarray(instance.matrix_world, np.float64) @ np.linalg.inv(
                    np.asarray(obj.matrix_world, np.float64))
            if not np.isfinite(matrix).all():
                continue
            self._add_placed(local, slot_to_material, matrix)
            self.objects.append(snap.ObjectInfo(name=f"{obj.name}/{psys.name}",
                                                camera_visible=bool(getattr(obj, "visible_camera", True)),
                                                casts_shadow=bool(getattr(obj, "visible_shadow", True))))

    def _add_placed(self, local, slot_to_material, matrix):
        """Queue one instance of `local` (object index: the next ObjectInfo's). Every instance of
        one mesh with the same materials is transformed in one batch (`transformed`), wherever it
        came: a collection of a trunk and a crown instanced 300 times alternates between the two,
        ~0.5 ms of numpy calls an instance one by one (0.3 s of a landscape's sync)."""
        key = (id(local), tuple(slot_to_material))
        group = self._groups.setdefault(key, [local, slot_to_material, [], []])
        group[2].append(len(self.objects))
        group[3].append(matrix)
        self._order.append((key, len(group[3]) - 1))

    def _placed_parts(self) -> tuple[list, dict]:
        """The queued instances' `Geometry`, in the order they came (the snapshot the same as one
        by one: each instance a view of its batch, its triangles numbered from its own corners),
        and the snapshot's whole positions and normals, which the batches whose instances came one
        after another (every mesh used once, a particle system's copies) are transformed into in
        place: `concat_geometry` (its `out`) then copies only the others. Why: the atrium's 960k
        corners' positions and normals were written twice, 23 MB faulted in twice (its sync's
        concatenation 40 ms)."""
        corners = [self._groups[key][0].positions.shape[0] for key, _i in self._order]
        starts = np.cumsum([0] + corners).tolist()
        whole = {"positions": np.empty((starts[-1], 3), np.float32), "normals": np.empty((starts[-1], 3), np.float32)}
        first_at, runs = {}, {}
        for k, (key, i) in enumerate(self._order):
            first_at.setdefault(key, k)
            runs[key] = runs.get(key, True) and k == first_at[key] + i  # instance i at its run's i-th place
        batches = {}
        for key, (local, slot_to_material, objects, matrices) in self._groups.items():
            out = None
            if runs[key]:
                n, a = len(matrices), starts[first_at[key]]
                rows = slice(a, a + n * local.positions.shape[0])
                out = tuple(whole[name][rows].reshape(n, -1, 3) for name in ("positions", "normals"))
            batches[key] = transformed(local, np.stack(matrices), slot_to_material, np.asarray(objects, np.int32), out)
        parts = []
        for key, i in self._order:
            local, batch = self._groups[key][0], batches[key]
            parts.append(_instance_part(batch, i, local.positions.shape[0], local.triangles.shape[0]))
        return parts, whole

    def _note_ignored(self, obj):
        for prop, meaning in IGNORED_VISIBILITY.items():
            hidden = not getattr(obj, prop, True) if prop.startswith("visible") else getattr(obj, prop, False)
            if hidden:
                self.ignored.setdefault(meaning, set()).add(obj.name)
        if "indirect_only" in self.collection_flags.get(obj.name, ()):
            self.ignored.setdefault("in an indirect-only collection", set()).add(obj.name)

    def _note_linking(self, obj):
        """Light and shadow linking (Blender 4.0+): noted, not followed."""
        linking = getattr(obj, "light_linking", None)
        if linking is None:
            return
        for prop, meaning in (("receiver_collection", "light-linked (a Light Linking receiver collection)"),
                              ("blocker_collection", "shadow-linked (a Shadow Linking blocker collection)")):
            if getattr(linking, prop, None) is not None:
                self.ignored.setdefault(meaning, set()).add(obj.name)

    def warn_unsupported(self):
        """One warning per kind of setting HybridGI does not follow, naming the objects."""
        warn_lamp_notes(self.lamp_notes)
        if self.volumes:
            many = len(self.volumes) > 1
            log.warning("Volume %s %s: HybridGI renders surfaces only; %s left out", "objects" if many else "object",
                        _listed(self.volumes), "they are" if many else "it is")
        for meaning, names in sorted(self.ignored.items()):
            shown = ", ".join(sorted(names)[:5]) + (f" and {len(names) - 5} more" if len(names) > 5 else "")
            objects = "object" if len(names) == 1 else "objects"
            log.warning("%s %s %s %s; HybridGI renders it like any other object", objects, shown,
                        "is" if len(names) == 1 else "are", meaning)

    def finish(self, world, viewpoint=None):
        check_flattened_size(sum(self._groups[key][0].triangles.shape[0] for key, _i in self._order))
        parts, whole = self._placed_parts()
        self._warn_glossy()
        geometry = snap.concat_geometry(parts, out=whole)  # new arrays, handed over whole
        return snap.make_snapshot(geometry, self.materials, self.lights, world, self.objects, owned=True,
                                  viewpoint=viewpoint)

    def _warn_glossy(self):
        """One warning per sync for the shader features HybridGI still approximates (Principled,
        Glossy, Metallic and Glass BSDFs, mixes), naming each material and node (the glossy lobes
        themselves are rendered: `glossy.py`)."""
        notes = self._textures.approximated
        if not notes:
            return
        names = sorted(notes)
        listed = "; ".join(f"material {name!r} {', '.join(sorted(notes[name]))}" for name in names[:5])
        more = f" (and {len(names) - 5} more materials)" if len(names) > 5 else ""
        log.warning("Shader features approximated: %s%s", listed, more)

    def _shape_mesh(self, obj):
        """`_LocalMesh` of a Curves object's strands as tubes (`hybridgi_core.hair`) or a
        PointCloud's points as spheres (`hybridgi_core.points`), no UVs; or None."""
        key = obj.data.as_pointer()
        if key not in self._meshes:
            arrays = _hair_arrays if obj.type == "CURVES" else _pointcloud_arrays
            self._meshes[key] = arrays(obj.data, obj.name)
        return self._meshes[key]

    def _local_mesh(self, obj):
        key = obj.data.as_pointer()
        if key not in self._meshes:
            self._meshes[key] = mesh_arrays(obj.data)
        return self._meshes[key]

    def _slot_materials(self, obj, local, dynamic=False, bakes=True, instance=None):
        """(global material index of each slot, the local mesh): slots whose material needs a
        bake get a material of their own for this mesh (and for this object's Object Info values
        where the material reads them: `object_values`), and its triangles the atlas UVs."""
        # One slot under a view layer's override: every slot index clips to it.
        materials = ([self.material_override] if self.material_override is not None
                     else [slot.material for slot in obj.material_slots])
        if not materials:
            materials = list(obj.data.materials)
        if not materials:
            self.without_material.add(obj.name)
            return [self._material(None)], local
        slots = np.clip(local.slot, 0, len(materials) - 1)
        if obj.type != "MESH" or not bakes:
            # Hair tubes have no UVs to bake over, nor tangents: each material's own values.
            return [self._material(material) for material in materials], local
        baked, bumped = {}, set()
        for s, material in enumerate(materials):
            own, masks, heights, images = self._bake_sockets(material)
            count = int((slots == s).sum())
            if heights and material_bake.cell_texels(count) < MIN_BUMP_CELL_TEXELS:
                heights = []  # too fine a mesh for the atlas: the smooth normal, noted (`_height_map`)
            if (masks or heights) and not self._optional_bakes(material, obj, s, len(masks) + len(heights)):
                masks, heights = [], []  # past the sync's budget: their own values, noted
            if (own or masks or heights) and count:
                baked[s] = own + masks + heights + images
                if heights:
                    bumped.add(s)
        indices = [self._material(material) if s not in baked
                   else self._baked_material(material, obj, local, slots, s, baked[s], dynamic, instance)
                   for s, material in enumerate(materials)]
        local = self._with_tangents(obj, local, [indices[s] for s in np.unique(slots).tolist()])
        if baked:
            key = (obj.data.as_pointer(), tuple(sorted(baked)), tuple(sorted(bumped)))
            if key not in self._atlas_meshes:
                self._atlas_meshes[key] = with_atlas(local, slots, sorted(baked), bumped)
            local = self._atlas_meshes[key]
        return indices, local

    def _optional_bakes(self, material, obj, slot, jobs: int) -> bool:
        """Whether this mesh slot's mask and height bakes (`jobs` of them) fit the sync's
        OPTIONAL_BAKE_JOBS; a slot already granted (another instance of the mesh) always does."""
        key = (material.name_full, obj.data.as_pointer(), slot)
        if key in self._optional_granted:
            return True
        if self._optional_left < jobs:
            return False
        self._optional_left -= jobs
        self._optional_granted.add(key)
        return True

    def _bake_sockets(self, material) -> tuple[list, list, list, list]:
        """`bake_plan` of `material` (None: none), walked once per sync however many objects
        use it (1000 objects of one material: 60 ms of walks)."""
        if material is None:
            return [], [], [], []
        key = material.as_pointer()
        if key not in self._sockets:
            self._sockets[key] = bake_plan(material)
        return self._sockets[key]

    def _with_tangents(self, obj, local, used):
        """`local` with the tangents of the normal-map UV map its materials `used` (global
        indices) follow, or `local` itself when none of them has a normal map (one computation per
        mesh and UV map, shared by its instances)."""
        maps = [self.materials[i].normal_map for i in used
                if self.materials[i].normal_map is not None and self.materials[i].normal_map.texture is not None]
        if not maps:
            return local
        uv_map = maps[0].uv_map
        if any(m.uv_map != uv_map for m in maps[1:]):
            log.warning("object %r: normal maps on different UV maps; all follow %r", obj.name, uv_map or "the active one")
        key = (obj.data.as_pointer(), uv_map)
        if key not in self._tangent_meshes:
            tangents = mesh_tangents(obj.data, uv_map)
            if tangents is None:
                log.warning("object %r: no UV map %r for its normal map; rendered without it", obj.name, uv_map)
            if tangents is not None and local.source is not None:
                tangents = tangents[local.source]
            self._tangent_meshes[key] = local if tangents is None else replace(local, tangents=tangents)
        return self._tangent_meshes[key]

    def _baked_material(self, material, obj, local, slots, slot, sockets, dynamic=False, instance=None):
        """Index of `material` on the triangles of `slot` of this mesh, its bake queued; one per
        set of the object's Object Info values where the material reads them (`object_values`:
        up to MAX_OBJECT_VARIANTS per mesh slot, further objects share the nearest one's)."""
        base = (material.name_full, obj.data.as_pointer(), slot)
        outputs = self._object_outputs.get(base[0])
        if outputs is None:
            outputs = self._object_outputs[base[0]] = object_info_outputs(material)
        values = object_values(instance, outputs) if instance is not None else None
        if values is not None:
            values = self._object_variant(base, values, material.name)
        key = base + (None if values is None else tuple(sorted((k, repr(v)) for k, v in values.items())),)
        index = self._baked.get(key)
        if index is None:
            jobs = [bake_job(material, node, socket, obj.data, local, np.nonzero(slots == slot)[0])
                    for node, socket in sockets]
            for job in jobs:
                job.dynamic = dynamic
                job.object_values = values
            index = self._baked[key] = len(self.materials)
            # Replaced in bake_materials; its normal map now already, so that the mesh gets the
            # tangents of the map's UV map (`_with_tangents`).
            read = material_from_blender(material, self._textures, pending=True, queued=sockets)
            self.materials.append(snap.Material(name=material.name, normal_map=read.normal_map))
            self._bakes.append((index, material, jobs))
        return index

    def _object_variant(self, base, values: dict, name: str) -> dict:
        """`values`, or, once MAX_OBJECT_VARIANTS sets were baked for this mesh slot, the set
        nearest to them (by Random, then Location) among those: a scatter of thousands of
        instances bakes a few dozen textures, not one per instance (warned once)."""
        known = self._variants.setdefault(base, [])
        if values in known or len(known) < MAX_OBJECT_VARIANTS:
            if values not in known:
                known.append(values)
            return values
        if name not in self._variant_warned:
            self._variant_warned.add(name)
            log.warning("material %r: more than %d objects differ in what its Object Info node reads; the others "
                        "take the bake of the nearest one", name, MAX_OBJECT_VARIANTS)

        def distance(other):
            return (abs(other.get("random", 0.0) - values.get("random", 0.0)),
                    float(np.linalg.norm(np.subtract(other.get("location", (0, 0, 0)), values.get("location", (0, 0, 0))))))

        return min(known, key=distance)

    def bake_materials(self):
        """Bake every queued colour input (one process for all; cached ones cost nothing) and
        read those materials with their textures."""
        if not self._bakes:
            return
        textures = material_bake.bake([job for _, _, jobs in self._bakes for job in jobs], wait=self.wait)
        for index, material, jobs in self._bakes:
            bake_id = jobs[0].key
            _BAKE_JOBS[bake_id] = jobs
            while len(_BAKE_JOBS) > 256:
                _BAKE_JOBS.pop(next(iter(_BAKE_JOBS)))
            baked = {(job.node, job.socket): textures[job.key] for job in jobs if job.key in textures}
            # quiet: a bake that failed warned itself, naming the material and the node.
            converted = material_from_blender(material, self._textures, baked=baked, pending=True,
                                              queued=[(job.node, job.socket) for job in jobs])
            converted.bake_id = bake_id
            # Its triangles read the bake's atlas UVs; a normal or bump map keeps the mesh's own
            # (`with_atlas`, `Geometry.normal_uvs`).
            self.materials[index] = converted

    def _material(self, material):
        key = None if material is None else material.name_full
        index = self._material_index.get(key)
        if index is None:
            # No material: Cycles' default surface, a Principled BSDF (base 0.8, specular 0.5).
            converted = (snap.Material(specular=SpecularLayer()) if material is None
                         else material_from_blender(material, self._textures))
            index = self._material_index[key] = len(self.materials)
            self.materials.append(converted)
        return index


# --- materials -----------------------------------------------------------------------------


def material_from_blender(material, textures=None, baked=None, pending=False, queued=None):
    """Lambertian `Material` of a Blender material (see the module docstring for what is read).

    baked : (node name, input identifier) -> (h, w, 3) texture Blender baked for a colour input
        this reader cannot fold (`bake_sockets`); pending : such bakes were started, so an input
        without its texture (still baking in the background, or failed: `material_bake` warned)
        keeps its constant value without a second warning. queued : the (node name, identifier)
        pairs whose bakes were started for it (default: every `bake_sockets` pair when pending)."""
    textures = textures if textures is not None else _TextureCache()
    textures.baked = baked or {}
    textures.pending = pending
    textures.queued = set(queued if queued is not None else bake_sockets(material)) if pending else set()
    name = material.name
    tree = material.node_tree
    if tree is None:
        return snap.Material(name=name, base_color=_rgb(material.diffuse_color))
    volume = _warn_volume(tree, f"material {name!r}")
    shader = _linked_node(_surface_input(tree))
    if shader is None:
        return _without_surface(name, volume)
    if shader.type == "HOLDOUT":
        # The camera sees a hole (the G-buffer and the film, `Material.holdout`); rays a black surface.
        return snap.Material(name=name, base_color=np.zeros(3, np.float32), holdout=True)
    shadow_transparent = False
    surface = _shadow_ray_mix(shader)
    if surface is not None:
        shader, shadow_transparent = surface, True
    part = _shader_surface(shader, textures, name)
    if part is None:
        log.warning("material %r: shader %s is not supported; using grey %.1f", name, shader.bl_idname, FALLBACK_GREY)
        return _grey(name)
    displaced = _displacement_bump(material, tree, textures, name)
    if displaced is not None:
        if part.normal is None:
            part.normal = snap.NormalMap(bump=displaced)
        elif part.normal.bump is None:
            part.normal = replace(part.normal, bump=displaced)
        else:
            _note(textures, name, shader, "a Bump node and a Displacement: rendered with the Bump node's only")
    if part.cover <= COVER_NONE:
        part = replace(part, clear=1.0, refract=0.0)
    if part.clear >= snap.ALPHA_CUTOFF:
        # Most of its light passes: a hole for the camera and for rays (as Cycles shows a clear
        # pane, and its light reaches what lies behind), not the dark mirror its reflection alone
        # made of it (a room lit through a glass window was black). Its own notes are moot.
        textures.approximated.pop(name, None)
        refractive = part.refract >= 0.5 * part.clear
        textures.approximated.setdefault(name, set()).add(
            f"lets {part.clear:.0%} of its light through: rendered as clear thin glass (light and the view "
            "pass straight through it, without refraction, reflection or tint)" if not refractive else
            f"lets {part.clear:.0%} of its light through: final renders show its refraction, reflection and "
            "tint to the camera; light and the GI's rays pass straight through it (no caustics), and the "
            "viewport shows it as clear thin glass")
        # Glass (most of the passing light refracted) stops the shadow rays of small lamps, as
        # Cycles' glass does (`lights.stopped_by_glass`).
        ior, tint, tinted_reflection = part.glass if part.glass is not None else (1.5, None, False)
        return snap.Material(name=name, base_color=np.zeros(3, np.float32), clear=True,
                             refractive=refractive, ior=ior, tint=tint, tint_reflection=tinted_reflection)
    if part.clear > 0:
        _note(textures, name, shader, f"lets {part.clear:.0%} of its light through (rendered opaque)")
    coverage = 1.0 if part.cover >= COVER_FULL else float(part.cover)
    specular = part.surface()
    if specular is not None and sp.surface_lobes(specular):
        textures.glossy.add(name)
    return snap.Material(name=name, base_color=part.base.astype(np.float32), texture=part.texture,
                         emission=part.emission.astype(np.float32), alpha=part.alpha, specular=specular,
                         normal_map=part.normal, emission_texture=part.emission_texture,
                         metallic_map=part.metallic_map if part.layer is not None else None,
                         roughness_map=part.roughness_map if part.layer is not None else None,
                         metal_texture=part.metal_texture if part.layer is not None else None,
                         shadow_transparent=shadow_transparent, translucent=part.translucent, sheen=part.sheen,
                         sheen_roughness=part.sheen_roughness, sheen_layered=part.sheen_layered,
                         coverage=coverage)


#: A surface seen with at most this chance (`SurfacePart.cover`: a constant alpha, a Transparent
#: BSDF mixed in) is clear glass; with at least COVER_FULL, opaque.
COVER_NONE = 0.02
COVER_FULL = 0.98


def frosted_share(roughness: float) -> float:
    """Share of a transmission of `roughness` rendered as translucency (FROSTED_ROUGHNESS)."""
    lo, hi = FROSTED_ROUGHNESS
    return float(np.clip((float(roughness) - lo) / (hi - lo), 0.0, 1.0))


def _principled_sheen(shader, textures, name) -> tuple[np.ndarray | None, float]:
    """((3,) a Principled BSDF's sheen colour, Sheen Weight x Sheen Tint, or None; its Sheen
    Roughness), from the sockets' constants (`_constant_value` notes a linked one)."""
    weight_socket = _input(shader, "Sheen Weight")
    if weight_socket is None:
        return None, 0.5
    weight = float(np.clip(_scalar_value(weight_socket, textures, name), 0.0, None))
    if weight <= 0:
        return None, 0.5
    tint = _input(shader, "Sheen Tint")
    colour = _constant_color(tint, name) if tint is not None else np.ones(3)
    roughness = _input(shader, "Sheen Roughness")
    rough = _scalar_value(roughness, textures, name) if roughness is not None else 0.5
    return (weight * np.asarray(colour, np.float64)).astype(np.float32), float(rough)


def _shadow_ray_mix(shader):
    """The other shader of Mix(a surface, Transparent BSDF) whose factor is Light Path > Is Shadow
    Ray (Transparent on the factor-1 side): what every ray but shadow rays sees; None for any
    other shader."""
    if shader.type != "MIX_SHADER" or shader.mute:
        return None
    source, output = _source(shader.inputs["Fac"])
    if source is None or source.type != "LIGHT_PATH" or output != "Is Shadow Ray":
        return None
    other, clear = (_linked_node(s) for s in shader.inputs[-2:])
    if clear is None or clear.type != "BSDF_TRANSPARENT" or other is None:
        return None
    return other


def _shader_surface(shader, textures, name, depth=0):
    """`surface_mix.SurfacePart` of a shader node, or None when it is not one this reader knows.
    The diffuse colour is what Cycles' Diffuse Color pass shows: a Principled BSDF's base colour
    weighted by (1 - metallic) (1 - transmission), tinted by its coat, and by its specular
    layer's view-dependent layering; Mix and Add Shader combine their inputs by their factor (a
    constant, or a Fresnel / Layer Weight node's output over the view angle). Glossy, Metallic
    and Glass BSDFs give glossy closures (`specular.GlossyLobe`)."""
    zero = np.zeros(3, np.float32)
    kind = shader.type
    if kind == "BSDF_PRINCIPLED":
        base, texture = _color_socket(shader.inputs["Base Color"], textures, name)
        metallic_map = _metallic_map(shader, textures, name)
        metallic = (float(metallic_map.mean()) if metallic_map is not None
                    else _scalar_value(shader.inputs["Metallic"], textures, name))
        transmission = _constant_value(_input(shader, "Transmission Weight", "Transmission"), name)
        coat = _scalar_value(_input(shader, "Coat Weight"), textures, name) if _input(shader, "Coat Weight") else 0.0
        tint = _constant_color(_input(shader, "Coat Tint"), name) if _input(shader, "Coat Tint") else np.ones(3)
        roughness_map = _roughness_map(shader, textures, name)
        roughness = _roughness(shader, textures, name, texels=roughness_map, per_pixel=True)
        transmission = float(np.clip(transmission, 0, 1))
        # Rough transmission scatters as a Translucent BSDF would: part of the diffuse colour.
        share = frosted_share(roughness)
        frosted = transmission * share
        weight = (1.0 - np.clip(metallic, 0, 1)) * (1.0 - transmission + frosted)
        _note_approximations(shader, textures, name, metallic, transmission, coat, roughness)
        layer = _specular_layer(shader, name, base, texture, metallic, transmission, roughness, coat, tint)
        metal_texture = None
        if metallic_map is not None:
            # The diffuse base per texel, base colour x (1 - metallic) as Cycles weighs it; the
            # glossy lobes per pixel (`Material.metallic_map`), ray hits' by the mean metallic.
            # The colour texture itself stays the metal's (`Material.metal_texture`).
            if texture is not None:
                metallic_map = _resampled(metallic_map, texture.shape)
                metal_texture = (np.asarray(base, np.float32) * texture).astype(np.float32)
            texture = (base if texture is None else texture) * (1.0 - metallic_map)
            base = np.ones(3, np.float32)
            weight = 1.0 - transmission + frosted
        base = base * weight * (1.0 + np.clip(coat, 0, 1) * (tint - 1.0))
        emission, glow = _emission(shader, shader.inputs["Emission Color"], shader.inputs["Emission Strength"],
                                   textures, name)
        diffuse = sp.diffuse_weight(layer, sp.view_grid())
        # What passes straight through the surface: its transmitted share. A constant alpha is the
        # share of the light the surface stops at all (`cover`, the surface seen with that chance;
        # an alpha texture cuts holes instead: `alpha`).
        alpha_socket = shader.inputs["Alpha"]
        opacity = 1.0 if alpha_socket.is_linked else float(np.clip(_constant_value(alpha_socket, name), 0.0, 1.0))
        passing = 1.0 - float(np.clip(metallic, 0, 1))
        refract = passing * transmission
        # Frosted light counts half towards clear glass: a surface that scatters most of what
        # passes looks like a surface (a white ball at transmission 0.5) until nearly all passes.
        clear = passing * (transmission - 0.5 * frosted)
        sheen_colour, sheen_roughness = _principled_sheen(shader, textures, name)
        translucent = None
        if frosted > 0:
            translucent = np.full(3, frosted / (1.0 - transmission + frosted), np.float32)
            _note(textures, name, shader, f"transmission {transmission:.2f} at roughness {roughness:.2f} "
                  f"({share:.0%} of it rendered as a Translucent BSDF's light from behind, "
                  "without refraction)")
        return surface_mix.SurfacePart(base=base, texture=texture, emission=emission, emission_texture=glow,
                                       alpha=_alpha_map(alpha_socket, textures, name), diffuse=diffuse,
                                       lobes=sp.layer_lobes(layer), layer=layer,
                                       normal=_normal_map(shader, textures, name),
                                       metallic_map=None if metallic_map is None else metallic_map[..., 0],
                                       roughness_map=roughness_map,
                                       metal_texture=metal_texture,
                                       clear=clear, refract=refract, cover=opacity, sheen=sheen_colour,
                                       glass=_glass_optics(shader, "Base Color", textures, name) if refract > 0 else None,
                                       sheen_roughness=sheen_roughness,
                                       sheen_layered=True, translucent=translucent)
    if kind in ("BSDF_HAIR_PRINCIPLED", "BSDF_HAIR"):
        _note(textures, name, shader, "hair BSDF (rendered as a diffuse fibre of its overall colour)")
        return surface_mix.SurfacePart(base=_hair_colour(shader, name))
    if kind == "BSDF_DIFFUSE":
        rough = _input(shader, "Roughness")
        if rough is not None and (rough.is_linked or _constant_value(rough, name) > 0):
            _note(textures, name, shader, ROUGH_DIFFUSE_NOTE)
        base, texture = _color_socket(shader.inputs["Color"], textures, name)
        return surface_mix.SurfacePart(base=base, texture=texture, normal=_normal_map(shader, textures, name))
    if kind == "EMISSION":
        emission, glow = _emission(shader, shader.inputs["Color"], shader.inputs["Strength"], textures, name)
        return surface_mix.SurfacePart(emission=emission, emission_texture=glow)
    if kind in ("BSDF_GLOSSY", "BSDF_ANISOTROPIC", "BSDF_METALLIC", "BSDF_GLASS"):
        # Glass transmits what it does not reflect: clear (`snapshot.Material.clear`) on its own.
        glass = 1.0 if kind == "BSDF_GLASS" else 0.0
        return surface_mix.SurfacePart(lobes=[_glossy_lobe(shader, kind, textures, name)], clear=glass,
                                       refract=glass,
                                       glass=_glass_optics(shader, "Color", textures, name) if glass else None)
    if kind in ("BSDF_TRANSPARENT", "BSDF_REFRACTION"):
        # Light passes (straight through a Transparent BSDF, refracted through a Refraction BSDF:
        # rendered straight): clear on its own; no diffuse reflection (Cycles' Diffuse Color pass
        # is black there).
        return surface_mix.SurfacePart(base=zero, clear=1.0, refract=1.0 if kind == "BSDF_REFRACTION" else 0.0,
                                       glass=(_glass_optics(shader, "Color", textures, name)
                                              if kind == "BSDF_REFRACTION" else None))
    if kind == "BSDF_TRANSLUCENT":
        # Diffuse light from behind: Cycles counts it in the Diffuse passes (its colour in Diffuse
        # Color); the lamps' light is taken on the back of the surface (`Material.translucent`).
        base, texture = _color_socket(shader.inputs["Color"], textures, name)
        return surface_mix.SurfacePart(base=base, texture=texture, normal=_normal_map(shader, textures, name),
                                       translucent=np.ones(3, np.float32))
    if kind == "BSDF_TOON":
        # Cycles' Toon closures are a diffuse (Diffuse passes) or a glossy one whose lobe is a
        # cone of `Size` x 90 degrees: rendered as a Diffuse BSDF or a GGX lobe of that roughness.
        notes = []
        colour = _mean_colour_input(shader.inputs["Color"], textures, name, shader, notes)
        size = float(np.clip(_constant_value(shader.inputs["Size"], name), 0.0, 1.0))
        _note(textures, name, shader, ", ".join([*notes, "Toon BSDF (its light is rendered as a smooth diffuse or "
                                                 "glossy closure's, without the toon steps)"]))
        if getattr(shader, "component", "DIFFUSE") == "GLOSSY":
            return surface_mix.SurfacePart(lobes=[sp.GlossyLobe(weight=np.maximum(colour, 0.0), roughness=max(size, 0.05),
                                                                 distribution="GGX", fresnel="none")])
        return surface_mix.SurfacePart(base=np.asarray(colour, np.float32), normal=_normal_map(shader, textures, name))
    if kind == "BSDF_SHEEN":
        # A diffuse closure weighted by the sheen lobe's albedo at the view angle (`sheen.py`).
        notes = []
        colour = _mean_colour_input(shader.inputs["Color"], textures, name, shader, notes)
        if getattr(shader, "distribution", "MICROFIBER") != "MICROFIBER":
            notes.append("Ashikhmin velvet (rendered as Microfiber)")
        if notes:
            _note(textures, name, shader, ", ".join(notes))
        return surface_mix.SurfacePart(base=zero, sheen=np.asarray(colour, np.float32),
                                       sheen_roughness=_roughness(shader, textures, name),
                                       normal=_normal_map(shader, textures, name))
    if kind == "HOLDOUT":
        return surface_mix.SurfacePart(base=zero)
    if kind in ("MIX_SHADER", "ADD_SHADER") and depth < 8:
        return _mix_surface(shader, kind, textures, name, depth)
    return None


#: Nodes whose output over the view angle a Mix Shader's factor reads as such (`_factor_table`),
#: not as a cutout mask to bake.
VIEW_FACTOR_NODES = frozenset({"FRESNEL", "LAYER_WEIGHT", "LIGHT_PATH"})

#: Scalar inputs of a Principled BSDF that `bake_sockets` bakes when a texture feeds them (the
#: bake process routes them through a clamped Math node: Blender's own colour-to-float conversion).
#: Roughness fed by nodes (an ORM texture's green through Separate Color, as glTF imports wire it;
#: a Math or Color Ramp over an image) is baked so that its lobe takes the mean of what Blender
#: evaluates, not the socket's own value (a glTF import's is its roughness factor, often 1); an
#: Alpha fed by nodes (an image's alpha through a Math node or a Color Ramp, a procedural mask) is
#: baked into the cutout it makes (it rendered opaque).
BAKED_SCALARS = {"BSDF_PRINCIPLED": ("Metallic", "Roughness", "Alpha"), "BSDF_GLOSSY": ("Roughness",),
                 "BSDF_ANISOTROPIC": ("Roughness",), "BSDF_METALLIC": ("Roughness",), "BSDF_GLASS": ("Roughness",)}


def _metallic_map(shader, textures, name):
    """(h, w, 1) float32 Metallic per texel, or None when Metallic is a constant (or its texture
    is missing: the constant path warns): an Image Texture's colour straight into it is read
    directly (the mesh's UVs, as a base colour image), anything else (and any Metallic of a
    material with other bakes, so that both share the atlas) is what Blender baked."""
    socket = shader.inputs["Metallic"]
    if not socket.is_linked or _fold(socket, 0) is not None:
        return None
    texels = textures.baked.get((shader.name, socket.identifier))
    if texels is None:
        source, output = _source(socket)
        if source is not None and _direct_image(source, output):
            texels = textures.get(source.image, name)
    if texels is None:
        return None
    # A colour into a float input: Blender converts by the mean of the channels' luminance;
    # metallic masks are grey.
    return np.clip(np.asarray(texels, np.float32)[..., :3].mean(axis=-1, keepdims=True), 0.0, 1.0)


def _resampled(values: np.ndarray, shape) -> np.ndarray:
    """`values` (h', w', c) at (h, w) by nearest texels (textures read through the same UVs)."""
    h, w = shape[:2]
    if values.shape[:2] == (h, w):
        return values
    return values[(np.arange(h) * values.shape[0]) // h][:, (np.arange(w) * values.shape[1]) // w]


#: Nodes that pass an image's channels through unchanged when their outputs feed the matching
#: inputs of a combining node (a swizzle or a flipped channel: OpenGL <-> DirectX maps).
SEPARATE_NODES = frozenset({"SEPXYZ", "SEPRGB", "SEPARATE_COLOR"})
COMBINE_NODES = frozenset({"COMBXYZ", "COMBRGB", "COMBINE_COLOR"})


def _normal_map(shader, textures, name):
    """`snapshot.NormalMap` of a BSDF's Normal input: a Normal Map node in tangent space whose
    Color is an Image Texture (directly, or through Separate -> Combine nodes that swap or flip
    channels: 1 - x by a Math Subtract or an Invert), and / or a Bump node over an image's height
    (`_bump_map`; its Normal may be such a map). None when the input is unlinked; anything else
    (object / world space maps, other nodes) keeps the smooth normal, noted once a sync."""
    socket = _input(shader, "Normal")
    if socket is None or not socket.is_linked:
        return None
    node, _output = _source(socket)
    if node is None:
        return None
    bump = None
    if node.type == "BUMP":
        bump = _bump_map(node, textures, name)
        if bump is None:
            return None
        node, _output = _source(node.inputs["Normal"])
        if node is None:
            return snap.NormalMap(bump=bump)
    only_bump = None if bump is None else snap.NormalMap(bump=bump)
    if node.type != "NORMAL_MAP":
        _note(textures, name, node, f"{node.bl_idname} on a Normal input (rendered with the smooth normal)")
        return only_bump
    if node.space != "TANGENT":
        _note(textures, name, node, f"{node.space.lower().replace('_', ' ')} space normal map (rendered with the smooth normal)")
        return only_bump
    strength = _constant_value(node.inputs["Strength"], name)
    colour = node.inputs["Color"]
    if not colour.is_linked:
        return only_bump  # the default colour (0.5, 0.5, 1) is the unbent normal
    found = _image_channels(colour)
    if found is None:
        source = _linked_node(colour)
        _note(textures, name, node, f"normal map colour from {source.bl_idname if source else 'a muted link'} "
              "(rendered with the smooth normal)")
        return only_bump
    image_node, channels, flips = found
    pixels = textures.get(image_node.image, name)
    if pixels is None:
        return only_bump
    if not _direct_image(image_node, "Color"):
        what = ("a UDIM (tiled) normal map image" if getattr(image_node.image, "source", "") == "TILED"
                else "normal map image through a mapping or projection")
        _note(textures, name, node, f"{what} (rendered with the smooth normal)")
        return only_bump
    if channels != (0, 1, 2) or any(flips):
        pixels = pixels[..., list(channels)]
        pixels = np.where(np.asarray(flips)[None, None, :], np.float32(1.0) - pixels, pixels).astype(np.float32)
    return snap.NormalMap(texture=pixels, strength=strength, uv_map=node.uv_map, bump=bump)


def _displacement_bump(material, tree, textures, name):
    """`snapshot.BumpMap` of the Material Output's Displacement as Cycles renders it by default
    (Displacement > Bump Only, or the bump of Displacement and Bump): a Displacement node's
    height bends the shading normal as a Bump node of Distance = its Scale does (Cycles
    evaluates the displaced surface's normal, the same first-order term). None when nothing is
    linked; anything it cannot follow (true displacement, a height other than an image, a vector
    displacement) is noted."""
    output = tree.get_output_node(OUTPUT_TARGET)
    socket = None if output is None else output.inputs.get("Displacement")
    if socket is None or not socket.is_linked:
        return None
    node, _output = _source(socket)
    if node is None:
        return None
    method = getattr(material, "displacement_method", None) or getattr(
        getattr(material, "cycles", None), "displacement_method", "BUMP")
    if method == "DISPLACEMENT":
        _note(textures, name, node, "true displacement (Settings > Displacement) is not rendered (the undisplaced surface)")
        return None
    if method == "DISPLACEMENT_BOTH":  # pragma: no cover - older Blender's name
        method = "BOTH"
    if method == "BOTH":
        _note(textures, name, node, "Displacement and Bump: rendered as its bump only")
    if node.type != "DISPLACEMENT":
        _note(textures, name, node, f"displacement from {node.bl_idname} (rendered without it)")
        return None
    height = _height_map(node, node.inputs["Height"], textures, name, "Displacement height")
    if height is None:
        return None
    return snap.BumpMap(height=height, strength=1.0, distance=_constant_value(node.inputs["Scale"], name),
                        on_atlas=_baked_height(node, textures))


def _height_map(node, socket, textures, name, what_for):
    """(h, w) float32 height of an Image Texture's Color (its Rec.709 luminance, as Cycles turns a
    colour into a float) or Alpha feeding `socket`, read through the mesh's UV map; None for a
    constant (nothing bends) or anything else (noted on `node`)."""
    source, output = _source(socket)
    if source is None:
        return None  # a constant height bends nothing
    baked = textures.baked.get((node.name, socket.identifier))
    if baked is not None:  # a procedural height: Blender's own values over the atlas (`height_bakes`)
        return _smoothed(np.asarray(baked, np.float32)[..., :3] @ surface_mix.GRAY.astype(np.float32))
    if not _direct_image(source, output, alpha=True):
        if (node.name, socket.identifier) in textures.queued:
            return None  # its bake is under way (the viewport) or failed (`material_bake` warned)
        what = "an image through a mapping or projection" if source.type == "TEX_IMAGE" else source.bl_idname
        _note(textures, name, node, f"{what_for} from {what} (rendered with the smooth normal)")
        return None
    if output == "Alpha":
        height = textures.alpha(source.image, name)
        return np.ones(tuple(source.image.size)[::-1], np.float32) if height is None else height  # no alpha: flat
    colour = textures.get(source.image, name)
    return None if colour is None else (colour @ surface_mix.GRAY.astype(np.float32)).astype(np.float32)


def _smoothed(height: np.ndarray) -> np.ndarray:
    """(h, w) float32 `height` under a [1 2 1] / 4 filter along both axes (edges repeated): a
    bake's few jittered samples per texel leave ~10% noise in its texel-to-texel differences,
    which a bump differencing half a texel apart turns into grain."""
    h = np.asarray(height, np.float32)
    for axis in (0, 1):
        padded = np.concatenate([np.take(h, [0], axis=axis), h, np.take(h, [-1], axis=axis)], axis=axis)
        n = h.shape[axis]
        h = (np.take(padded, range(0, n), axis=axis) + 2.0 * np.take(padded, range(1, n + 1), axis=axis)
             + np.take(padded, range(2, n + 2), axis=axis)) * np.float32(0.25)
    return h.astype(np.float32)


def _bump_map(node, textures, name):
    """`snapshot.BumpMap` of a Bump node whose Height is an Image Texture's Color (its Rec.709
    luminance, as Cycles turns a colour into a float) or Alpha, read through the mesh's UV map;
    None (noted) for any other height (`_height_map`)."""
    height = _height_map(node, node.inputs["Height"], textures, name, "Bump height")
    if height is None:
        return None
    distance = _constant_value(node.inputs["Distance"], name)
    return snap.BumpMap(height=height, strength=_constant_value(node.inputs["Strength"], name),
                        distance=-distance if node.invert else distance, on_atlas=_baked_height(node, textures))


def _baked_height(node, textures) -> bool:
    """Whether the Height of `node` (a Bump or Displacement node) is read from its bake."""
    return (node.name, node.inputs["Height"].identifier) in textures.baked


def _image_channels(socket):
    """(Image Texture node, (3,) source channel of each output channel, (3,) whether it is
    flipped as 1 - x) of a colour input fed by an image's Color, directly or through
    Separate -> (1 - x) -> Combine; None otherwise."""
    node, output = _source(socket)
    if node is None:
        return None
    if node.type == "TEX_IMAGE":
        return (node, (0, 1, 2), (False, False, False)) if output == "Color" and node.image is not None else None
    if node.type not in COMBINE_NODES or getattr(node, "mode", "RGB") != "RGB":
        return None
    image, channels, flips = None, [], []
    for inp in [i for i in node.inputs if i.enabled][:3]:
        src, out = _source(inp)
        flip = False
        if src is not None and ((src.type == "MATH" and src.operation == "SUBTRACT" and not src.use_clamp
                                 and not src.inputs[0].is_linked and float(src.inputs[0].default_value) == 1.0)
                                or (src.type == "INVERT" and not src.inputs["Fac"].is_linked
                                    and float(src.inputs["Fac"].default_value) == 1.0)):
            flip = True
            src, out = _source(src.inputs[1])
        if src is None or src.type not in SEPARATE_NODES or getattr(src, "mode", "RGB") != "RGB":
            return None
        outputs = [o.identifier for o in src.outputs if o.enabled]
        inner, inner_out = _source(src.inputs[0])
        if out not in outputs[:3] or inner is None or inner.type != "TEX_IMAGE" or inner_out != "Color":
            return None
        if image is not None and inner != image:
            return None
        image = inner
        channels.append(outputs.index(out))
        flips.append(flip)
    if image is None or image.image is None or len(channels) != 3:
        return None
    return image, tuple(channels), tuple(flips)


def _note(textures, name, node, text):
    """Record what of a node HybridGI renders only approximately (`_warn_glossy`: one warning a sync)."""
    textures.approximated.setdefault(name, set()).add(f"node {node.name!r}: {text}")


def _glossy_lobe(shader, kind, textures, name):
    """`specular.GlossyLobe` of a Glossy (Anisotropic), Metallic or Glass BSDF, set up as Cycles'
    svm_node_closure_bsdf sets up its closure: a Glossy BSDF's colour is the closure weight with
    no Fresnel (Multiscatter GGX's darkening uses it as the average Fresnel); a Metallic BSDF
    weighs 1 with the F82-tint or the physical conductor's Fresnel; a Glass BSDF's reflection is
    its colour times the real dielectric Fresnel of its IOR (its transmission is not rendered)."""
    notes = []
    distribution = getattr(shader, "distribution", "GGX")
    if distribution == "ASHIKHMIN_SHIRLEY":
        notes.append("Ashikhmin-Shirley distribution (rendered as GGX)")
        distribution = "GGX"
    roughness = _roughness(shader, textures, name)
    anisotropy = _input(shader, "Anisotropy")
    if anisotropy is not None and abs(_constant_value(anisotropy, name)) > 1e-4:
        notes.append("anisotropy (rendered isotropic)")
    film = _input(shader, "Thin Film Thickness")
    if film is not None and _constant_value(film, name) > 0:
        notes.append("thin film (not rendered)")
    if kind == "BSDF_METALLIC":
        if getattr(shader, "fresnel_type", "F82") == "PHYSICAL_CONDUCTOR":
            lobe = sp.GlossyLobe(
                roughness=roughness, distribution=distribution, fresnel="conductor",
                n=np.maximum(_constant_color(shader.inputs["IOR"], name), 0.0),
                k=np.maximum(_constant_color(shader.inputs["Extinction"], name), 0.0))
        else:
            f0 = np.clip(_mean_colour_input(shader.inputs["Base Color"], textures, name, node=shader, notes=notes), 0, 1)
            tint = np.clip(_constant_color(shader.inputs["Edge Tint"], name), 0.0, 1.0)
            b = np.zeros(3) if np.all(tint == 1.0) else sp.f82_b_from_tint(f0, tint)
            lobe = sp.GlossyLobe(roughness=roughness, distribution=distribution, fresnel="f82", f0=f0, b=b)
    else:
        colour = np.maximum(_mean_colour_input(shader.inputs["Color"], textures, name, node=shader, notes=notes), 0.0)
        if kind == "BSDF_GLASS":
            ior = max(_constant_value(shader.inputs["IOR"], name, 1.5), 1e-5)
            notes.append("Glass BSDF: only its reflection is rendered (the transmitted light is not)")
            if distribution == "MULTI_GGX":
                distribution = "GGX"  # Cycles compensates the glass's energy with tables of its own
            lobe = sp.GlossyLobe(weight=colour, roughness=roughness, distribution=distribution,
                                             fresnel="dielectric", ior=ior, f0=np.full(3, sp.f0_from_ior(ior)))
        else:
            lobe = sp.GlossyLobe(weight=colour, roughness=roughness, distribution=distribution,
                                             fresnel="none", fss=colour if distribution == "MULTI_GGX" else None)
    if lobe.roughness < MIN_ROUGHNESS:
        notes.append(f"a mirror-like reflection (roughness under {MIN_ROUGHNESS}: lamps' reflections are not rendered)")
    if notes:
        _note(textures, name, shader, ", ".join(notes))
    return lobe


def _glass_optics(shader, colour_socket: str, textures, name) -> tuple[float, np.ndarray, bool]:
    """(index of refraction, colour, whether the colour tints the reflection too) of a refracting
    closure: a Glass BSDF's Color tints both, as Cycles' does; a Principled BSDF's Base Color
    and a Refraction BSDF's Color tint the refracted light only. What the camera's refraction
    paths take (`refraction.py`); a textured colour by its mean."""
    ior = _constant_value(_input(shader, "IOR"), name, fallback=1.5) if _input(shader, "IOR") is not None else 1.5
    colour = _mean_colour_input(shader.inputs[colour_socket], textures, name, node=shader, notes=[])
    return float(np.clip(ior, 1.0, 4.0)), np.clip(colour, 0.0, 1.0).astype(np.float32), shader.type == "BSDF_GLASS"


def _mean_colour_input(socket, textures, name, node, notes):
    """(3,) a glossy closure's colour input: its constant, or the mean of the image or baked
    texture it reads (a glossy lobe has one colour), noted."""
    base, texture = _color_socket(socket, textures, name)
    if texture is None:
        return np.asarray(base, np.float64)
    notes.append(f"{socket.name} from a texture (its mean colour)")
    return np.asarray(base, np.float64) * texture.reshape(-1, 3).mean(axis=0)


def _note_approximations(shader, textures, name, metallic, transmission, coat, roughness):
    """Record what of a Principled BSDF HybridGI renders only approximately (`_warn_glossy`)."""
    notes = []
    if coat > 0 and _input(shader, "Coat Normal") is not None and _input(shader, "Coat Normal").is_linked:
        notes.append("coat normal (the coat takes the base's normal)")
    for socket, note in (("Anisotropic", "anisotropy (rendered isotropic)"),
                         ("Thin Film Thickness", "thin film (not rendered)"),
                         ("Subsurface Weight", "subsurface (rendered as diffuse)"),
                         ("Diffuse Roughness", ROUGH_DIFFUSE_NOTE)):
        value = _input(shader, socket)
        if value is not None and _constant_value(value, name) > 0:
            notes.append(note)
    level = _input(shader, "Specular IOR Level", "Specular")
    glossy = metallic > 0 or (level is not None and _constant_value(level, name) > 0)
    if glossy and _input(shader, "Roughness") is not None and roughness < MIN_ROUGHNESS:
        notes.append(f"a mirror-like specular (roughness under {MIN_ROUGHNESS}: lamps' reflections are not rendered)")
    if notes:
        _note(textures, name, shader, ", ".join(notes))


_UNREAD = object()


def _roughness(shader, textures, name, default=0.5, texels=_UNREAD, per_pixel=False):
    """A closure's Roughness: its constant, or the mean of its texels (`_roughness_map`: an image
    it reads directly or what Blender baked of the nodes feeding it; a lobe has one roughness:
    noted), else its own value (`_constant_value` warns). texels : the map the caller already
    read (None: a constant). per_pixel : the caller keeps the map, whose texels the image's
    pixels follow (a lone Principled BSDF's glossy variants, `glossy.roughness_range`): the note
    says the mean serves the rays' hits only."""
    socket = _input(shader, "Roughness")
    if socket is None:
        return default
    if texels is _UNREAD:
        texels = _roughness_map(shader, textures, name)
    if texels is not None:
        _note(textures, name, shader, "Roughness from a texture (its mean at ray hits; per pixel in 6 steps for a lone Principled BSDF)"
              if per_pixel else "Roughness from a texture (its mean)")
        return float(np.clip(np.nan_to_num(np.mean(texels, dtype=np.float64), nan=default), 0.0, 1.0))
    return _scalar_value(socket, textures, name, default)


def _roughness_map(shader, textures, name):
    """(h, w) float32 a closure's Roughness per texel, or None when it is a constant: an
    Image Texture's colour or alpha straight into it (the mesh's UVs, as a base colour image), or
    what Blender baked of the nodes feeding it (`BAKED_SCALARS`; on the bake's atlas, as the
    colour then is)."""
    socket = _input(shader, "Roughness")
    if socket is None or not socket.is_linked or _fold(socket, 0) is not None:
        return None
    texels = textures.baked.get((shader.name, socket.identifier))
    if texels is not None:
        return np.asarray(texels, np.float32)[..., :3].mean(axis=-1)
    node, output = _source(socket)
    if node is None or node.type != "TEX_IMAGE" or output not in ("Color", "Alpha"):
        return None
    if output == "Alpha":
        return textures.alpha(node.image, name)
    pixels = textures.get(node.image, name)
    return None if pixels is None else np.asarray(pixels, np.float32).reshape(*pixels.shape[:2], 3) @ surface_mix.GRAY


def _scalar_value(socket, textures, name, fallback: float = 0.0) -> float:
    """A float input's constant (`_constant_value`, `fallback` where not finite); one that
    `bake_sockets` bakes (`BAKED_SCALARS`), fed by nodes while its bake is on the way
    (`textures.pending`: the viewport shows the socket's value meanwhile), gives its own value
    without a warning."""
    if (textures.pending and socket.is_linked and socket.name in BAKED_SCALARS.get(socket.node.type, ())
            and _fold(socket, 0) is None):
        value = float(socket.default_value)
        return value if np.isfinite(value) else float(fallback)
    return _constant_value(socket, name, fallback)


def _specular_layer(shader, name, base, texture, metallic, transmission, roughness, coat=0.0, coat_tint=None):
    """`SpecularLayer` of a Principled BSDF: `roughness` (`_roughness`), its IOR, Specular IOR
    Level and Tint and its distribution (constant inputs; a linked one keeps its value, with a
    warning), weighted as Cycles weights the dielectric layer, and its coat (`_coat`); the metallic
    lobe's F0 is the (mean) base colour."""
    metal = base if texture is None else base * texture.reshape(-1, 3).mean(axis=0)
    metallic, transmission = float(np.clip(metallic, 0, 1)), float(np.clip(transmission, 0, 1))
    level = _input(shader, "Specular IOR Level", "Specular")
    tint = _input(shader, "Specular Tint")
    colour_tint = tint is not None and hasattr(tint.default_value, "__len__")
    return SpecularLayer(roughness=roughness,
                         ior=_constant_value(_input(shader, "IOR"), name, 1.5) if _input(shader, "IOR") else 1.5,
                         level=_constant_value(level, name) if level is not None else 0.5,
                         tint=_constant_color(tint, name) if colour_tint else np.ones(3, np.float32),
                         multiscatter=getattr(shader, "distribution", "MULTI_GGX") == "MULTI_GGX",
                         weight=(1.0 - metallic) * (1.0 - transmission), metallic=metallic, metal_color=metal,
                         transmission=transmission, **_coat(shader, name, coat, coat_tint))


def _coat(shader, name, weight: float, tint) -> dict:
    """A Principled BSDF's Coat inputs as `SpecularLayer` fields (constants; none without a coat
    of `weight`; the Coat Weight and Tint already read by the caller)."""
    if weight <= 0:
        return {}
    out = {"coat": weight}
    for field_name, socket in (("coat_roughness", "Coat Roughness"), ("coat_ior", "Coat IOR")):
        if _input(shader, socket) is not None:
            out[field_name] = _constant_value(_input(shader, socket), name)
    if tint is not None:
        out["coat_tint"] = tint
    return out


def _mix_surface(shader, kind, textures, name, depth):
    """`_shader_surface` of a Mix or Add Shader: its parts weighted by the factor (a constant, or
    a Fresnel / Layer Weight node's output over the view angle), or the usual cutout,
    Mix(Fac = an image's alpha, Transparent BSDF, a surface)."""
    nodes = [_linked_node(socket) for socket in (shader.inputs[-2:] if kind == "MIX_SHADER" else shader.inputs[:2])]
    parts = [_shader_surface(node, textures, name, depth + 1) if node is not None else surface_mix.SurfacePart()
             for node in nodes]
    if any(part is None for part in parts):
        return None
    weights = [surface_mix.constant_factor(1.0)] * 2
    if kind == "MIX_SHADER":
        kinds = [node.type if node is not None else None for node in nodes]
        if "BSDF_TRANSPARENT" in kinds and shader.inputs["Fac"].is_linked:
            fac_map = _alpha_map(shader.inputs["Fac"], textures, name)
            if fac_map is not None:
                # The transparent part's weight is the hole, not a darker surface.
                hole_first = kinds[0] == "BSDF_TRANSPARENT"
                part = parts[1] if hole_first else parts[0]
                return replace(part, alpha=fac_map if hole_first else 1.0 - fac_map)
        socket = shader.inputs["Fac"]
        fac_map = textures.baked.get((shader.name, socket.identifier))
        if fac_map is not None or (shader.name, socket.identifier) in textures.queued:
            # A mask per texel (`_texel_factor`, baked): the parts mix at its mean, their
            # colours per texel (`_texel_mix`); while it bakes (the viewport), at its own value.
            fac_map = None if fac_map is None else np.asarray(fac_map, np.float32)[..., :3].mean(axis=-1)
            mean = float(np.clip(fac_map.mean(), 0.0, 1.0)) if fac_map is not None else float(
                np.clip(socket.default_value, 0.0, 1.0))
            plain = [replace(p, texture=None, base=p.mean_colour().astype(np.float32)) for p in parts]
            part, notes = surface_mix.mix(plain, [surface_mix.constant_factor(1.0 - mean),
                                                  surface_mix.constant_factor(mean)], name)
            for note in notes:
                if fac_map is None or "one colour kept" not in note:  # the texels keep theirs
                    _note(textures, name, shader, note)
            return part if fac_map is None else _texel_mix(parts, fac_map, part)
        fac = _view_factor(socket, name)
        weights = [1.0 - fac, fac]
        covered = _covering_part(nodes, parts, weights)
        if covered is not None:
            return covered
    part, notes = surface_mix.mix(parts, weights, name)
    for note in notes:
        _note(textures, name, shader, note)
    return part


def _covering_part(nodes, parts, weights):
    """The part of Mix(a surface, a white Transparent BSDF) by a constant factor: the surface, seen
    with the chance of its weight (`SurfacePart.cover`), rather than a surface that weight dims
    (the mix of their colours). None for any other mix."""
    kinds = [node.type if node is not None else None for node in nodes]
    if kinds.count("BSDF_TRANSPARENT") != 1 or None in kinds or not all(np.all(w == w[0]) for w in weights):
        return None
    t = kinds.index("BSDF_TRANSPARENT")
    colour = nodes[t].inputs["Color"]
    if colour.is_linked or not np.allclose(tuple(colour.default_value)[:3], 1.0, atol=1e-3):
        return None  # a tinted Transparent BSDF: the mix as it is
    share = float(weights[1 - t][0])
    if not 0.0 < share < 1.0:
        return None
    part = parts[1 - t]
    return replace(part, cover=part.cover * share)


#: Cycles' melanin absorption per unit concentration (kernel/closure/bsdf_principled_hair*.h,
#: `sigma_from_concentration`): eumelanin, pheomelanin.
EUMELANIN_SIGMA = np.array([0.506, 0.841, 1.653])
PHEOMELANIN_SIGMA = np.array([0.343, 0.733, 1.924])


def _hair_reflectance_scale(radial_roughness: float) -> float:
    """Cycles' `sigma_from_reflectance` denominator at azimuthal roughness x: sigma = (ln c / it)^2."""
    x = float(np.clip(radial_roughness, 0.0, 1.0))
    return 5.969 - 0.215 * x + 2.532 * x**2 - 10.73 * x**3 + 5.574 * x**4 + 0.245 * x**5


def _hair_colour(shader, name) -> np.ndarray:
    """(3,) the diffuse colour a hair BSDF is rendered with: its fibre reflectance c (the Principled
    Hair's Direct Coloring colour, or exp(-sqrt(sigma) k) of its absorption, from melanin and tint
    or given, inverting Cycles' `sigma_from_reflectance`; a Hair BSDF's Color), brightened as a
    lock of fibres scatters light among them: 0.022 + 2.7c / (1 + 2c), fitted to Cycles' hair
    patches of melanin 0.6, absorption (0.25, 0.6, 1.2) and colour (0.6, 0.3, 0.1) under a sun and
    a grey sky, and of melanin 0.3 and colour (0.3, 0.5, 0.7) under an area lamp (the 0.022 is the
    fibres' white primary reflection). Dark hair is within ~10%; a light colour's fibres scatter
    forwards differently under each light (-10% under the sun, +12% under the area lamp)."""
    if shader.type == "BSDF_HAIR":
        c = _constant_color(shader.inputs["Color"], name)
    else:
        k = _hair_reflectance_scale(_constant_value(_input(shader, "Radial Roughness") or shader.inputs["Roughness"],
                                                    name, 0.3))
        mode = getattr(shader, "parametrization", "COLOR")
        if mode == "COLOR":
            c = _constant_color(shader.inputs["Color"], name)
        else:
            if mode == "MELANIN":
                melanin = -math.log(max(1.0 - _constant_value(shader.inputs["Melanin"], name, 0.8), 1e-4))
                red = float(np.clip(_constant_value(shader.inputs["Melanin Redness"], name, 1.0), 0.0, 1.0))
                sigma = melanin * ((1.0 - red) * EUMELANIN_SIGMA + red * PHEOMELANIN_SIGMA)
                tint = np.clip(_constant_color(shader.inputs["Tint"], name), 1e-4, 1.0)
                sigma = sigma + (np.log(tint) / k) ** 2
            else:
                sigma = np.maximum(np.asarray(_constant_color(shader.inputs["Absorption Coefficient"], name),
                                              np.float64), 0.0)
            c = np.exp(-np.sqrt(sigma) * k)
    c = np.clip(np.asarray(c, np.float64), 0.0, 1.0)
    return np.clip(0.022 + 2.7 * c / (1.0 + 2.0 * c), 0.0, 1.0).astype(np.float32)


def _texel_factor(socket) -> bool:
    """Whether a Mix Shader's linked Fac varies over the surface (a texture, an attribute, math on
    them) rather than over the view only (`_factor_table`'s nodes: Fresnel, Layer Weight, and
    Math, Ramps, Invert, Map Range over them), walking its nodes without evaluating them."""
    stack, seen = [socket], 0
    while stack and seen < 64:
        node, _output = _source(stack.pop())
        seen += 1
        if node is None or node.type in VIEW_FACTOR_NODES:
            continue
        if node.type not in ("MATH", "INVERT", "VALTORGB", "MAP_RANGE", "CLAMP"):
            return True
        stack += [s for s in node.inputs if s.is_linked]
    return False


def _texel_mix(parts, fac_map, mixed):
    """`mixed` (the parts' mix at the mask's mean factor) with its diffuse colour per texel:
    (1 - f) c0 + f c1 of the parts' colours (base x texture, read on the mask's texels, times the
    cosine mean of their diffuse weights) over the mask `fac_map` (h, w) in 0..1; the mix's
    relative view dependence, lobes, emission and the rest keep the mean factor's."""
    shape = fac_map.shape
    f = np.clip(np.asarray(fac_map, np.float32), 0.0, 1.0)[..., None]
    colours = []
    for part in parts:
        table = float(surface_mix._cosine_mean(np.asarray(part.base_table(), np.float64)))
        if part.texture is None:
            colours.append(np.broadcast_to(np.asarray(part.base, np.float32) * table, (*shape, 3)))
        else:
            colours.append(_resampled(np.asarray(part.texture, np.float32), shape) * np.asarray(part.base, np.float32)
                           * table)
    albedo = (1.0 - f) * colours[0] + f * colours[1]
    base = np.maximum(albedo.reshape(-1, 3).mean(axis=0), np.float32(1e-6))
    return replace(mixed, base=base.astype(np.float32), texture=(albedo / base).astype(np.float32))


def _view_factor(socket, name):
    """(V,) a Mix Shader's Fac over the view cosine (`_factor_table`), clamped as the Mix Shader
    clamps it; a factor from anything else keeps its own value (`_constant_value` warns)."""
    table = _factor_table(socket, name)
    if table is None:
        return surface_mix.constant_factor(_constant_value(socket, name))
    return np.clip(np.broadcast_to(np.asarray(table, np.float64), (sp.VIEW_SAMPLES,)), 0.0, 1.0)


def _factor_table(socket, name, depth=0):
    """(V,) or a float: what a float input evaluates to over the view cosine, through the nodes
    tutorials put between a Fresnel or Layer Weight node and a Mix Shader (Math, Invert, Color
    Ramp, Map Range) and constants; None for anything else. A colour reads as its luminance."""
    node, output = _source(socket)
    if node is None:  # unlinked or muted: the socket's own value
        value = socket.default_value
        return float(np.dot(tuple(value)[:3], surface_mix.GRAY)) if hasattr(value, "__len__") else float(value)
    if depth > 16:
        return None
    kind = node.type
    if kind == "FRESNEL":
        return surface_mix.fresnel_factor(_constant_value(node.inputs["IOR"], name, 1.5))
    if kind == "LAYER_WEIGHT":
        return surface_mix.layer_weight_factor(_constant_value(node.inputs["Blend"], name), output)
    if kind == "MATH":
        a, b = (_factor_table(node.inputs[i], name, depth + 1) for i in (0, 1))
        if a is None or b is None:
            return None
        return surface_mix.math_factor(node.operation, a, b, bool(node.use_clamp))
    if kind == "INVERT":
        fac, colour = (_factor_table(node.inputs[key], name, depth + 1) for key in ("Fac", "Color"))
        if fac is None or colour is None:
            return None
        return (1.0 - np.asarray(fac)) * np.asarray(colour) + np.asarray(fac) * (1.0 - np.asarray(colour))
    if kind == "VALTORGB":
        fac = _factor_table(node.inputs["Fac"], name, depth + 1)
        ramp = node.color_ramp
        rgba = None if fac is None else surface_mix.ramp_factor(
            np.broadcast_to(np.asarray(fac, np.float64), (sp.VIEW_SAMPLES,)), [e.position for e in ramp.elements],
            [tuple(e.color) for e in ramp.elements], ramp.interpolation)
        if rgba is None:
            return None
        return rgba[:, 3] if output == "Alpha" else rgba[:, :3] @ surface_mix.GRAY
    if kind == "MAP_RANGE" and getattr(node, "data_type", "FLOAT") == "FLOAT" and node.interpolation_type == "LINEAR":
        values = [_factor_table(node.inputs[key], name, depth + 1)
                  for key in ("Value", "From Min", "From Max", "To Min", "To Max")]
        if any(v is None for v in values):
            return None
        x, lo, hi, to_lo, to_hi = (np.asarray(v, np.float64) for v in values)
        span = hi - lo
        t = np.where(span != 0.0, (x - lo) / np.where(span != 0.0, span, 1.0), 0.0)
        out = to_lo + t * (to_hi - to_lo)
        return np.clip(out, np.minimum(to_lo, to_hi), np.maximum(to_lo, to_hi)) if node.clamp else out
    folded = _fold(socket, 0)
    return None if folded is None else float(np.dot(np.broadcast_to(folded, (3,)), surface_mix.GRAY)
                                             if np.ndim(folded) else folded)



def _alpha_map(socket, textures, name):
    """(h, w) float32 opacity an input reads from an image (its Alpha output, or its colour's
    mean when the colour output feeds it), or None for an opaque or constant input."""
    if socket is None or not socket.is_linked:
        return None  # a constant: the part's `clear` share
    baked = textures.baked.get((socket.node.name, socket.identifier))
    if baked is not None:
        return np.ascontiguousarray(np.asarray(baked, np.float32)[..., :3].mean(axis=-1))
    node, output = _source(socket)
    if node is not None and node.type == "TEX_IMAGE":
        if output == "Alpha":
            alpha = textures.alpha(node.image, name)
            if alpha is None:
                return None  # an image without alpha reads as opaque, as in Cycles
            return alpha
        if output == "Color":
            colour = textures.get(node.image, name)
            return None if colour is None else colour.mean(axis=-1)
    if node is not None and textures.pending:
        return None  # its bake is on the way: opaque meanwhile
    if node is not None and _fold(socket, 0) is not None:
        return None  # constant after all (the part's `clear` share)
    log.warning("material %r: alpha from %s could not be read; rendered opaque", name,
                node.bl_idname if node is not None else "a muted link")
    return None


#: Inputs (colour, strength) of the shaders whose emission `_emission` reads, and the name of
#: their product's bake (`bake_sockets`, `material_bake_process`: one EMIT bake of colour x strength).
EMISSION_INPUTS = {"BSDF_PRINCIPLED": ("Emission Color", "Emission Strength"), "EMISSION": ("Color", "Strength")}
EMISSION_BAKE = "emission"


def _emission(node, colour, strength, textures, name):
    """`_emission_parts`, negative radiance clamped to 0 as Cycles renders it (a negative Strength
    emits nothing there; taken as it was, it subtracted light: a cube of strength -5 read the
    image's Combined mean -1.33 where Cycles' is 0.55)."""
    value, glow = _emission_parts(node, colour, strength, textures, name)
    if (value < 0).any() or (glow is not None and (glow < 0).any()):
        log.warning("material %r: negative emission is not emitted (as in Cycles)", name)
        value = np.maximum(value, np.float32(0.0))
        glow = None if glow is None else np.maximum(glow, np.float32(0.0))
    return value, glow


def _emission_parts(node, colour, strength, textures, name):
    """((3,) emitted radiance, (h, w, 3) radiance per texel or None) of a shader's emission:
    colour x strength as Cycles' emission closure weighs it. Constants (and nodes folding to
    constants) give the constant, exactly as before; an Image Texture's colour plugged straight
    into the colour, under a constant strength, is that image times the strength (read through
    the mesh's UV map like a base colour image); anything else is the product Blender baked
    (`bake_sockets`). A bake still running or failed keeps the inputs' own values."""
    folded = _fold(colour, 0), _fold(strength, 0)
    if folded[0] is not None and folded[1] is not None:
        return _constant_color(colour, name) * _constant_value(strength, name), None
    baked = textures.baked.get((node.name, EMISSION_BAKE))
    if baked is not None:
        return baked.reshape(-1, 3).mean(axis=0).astype(np.float32), baked
    source, output = _source(colour)
    if folded[1] is not None and _direct_image(source, output):
        pixels = textures.get(source.image, name)
        if pixels is not None:
            glow = (pixels * np.float32(_constant_value(strength, name))).astype(np.float32)
            return glow.reshape(-1, 3).mean(axis=0).astype(np.float32), glow
    if not textures.pending:
        linked = _linked_node(colour) if folded[0] is None else _linked_node(strength)
        _note(textures, name, node, f"emission from {getattr(linked, 'bl_idname', 'a node')} could not be read "
              "(its sockets' own values are used)")
    value = folded[0] if folded[0] is not None else tuple(colour.default_value)[:3]
    scale = folded[1] if folded[1] is not None else strength.default_value
    return (np.broadcast_to(np.asarray(value, np.float32), (3,)) * np.float32(np.mean(scale))).astype(np.float32), None


def _input(node, *names):
    """The first of `names` that `node` has as an input (socket names changed across versions)."""
    for n in names:
        socket = node.inputs.get(n)
        if socket is not None:
            return socket
    return None


def _constant_color(socket, material_name):
    """(3,) colour of an input, following links to constant nodes (RGB, Value, a Mix of
    constants); a socket fed by anything else keeps its own value, with a warning."""
    value = _fold(socket, 0)
    if value is None:
        node = _linked_node(socket)
        log.warning("material %r: %s from %s is not supported; using its value", material_name, socket.name,
                    node.bl_idname if node is not None else "a muted link")
        return _rgb(socket.default_value) if hasattr(socket.default_value, "__len__") else np.full(3, _value(socket), np.float32)
    return np.broadcast_to(np.asarray(value, np.float32), (3,)).copy()


def _constant_value(socket, material_name, fallback: float = 0.0):
    """A float input's constant (the mean of a colour's), its own value where nodes feed it (with a
    warning); `fallback`, with a warning naming the input, where that is not finite (a NaN typed
    into Roughness turned the material's base colour into NaN, and the log named the colour)."""
    if socket is None:
        return 0.0
    value = _fold(socket, 0)
    if value is None:
        log.warning("material %r: %s from a node is not supported; using its value", material_name, socket.name)
        value = socket.default_value
    value = float(np.mean(value))
    if not np.isfinite(value) or abs(value) > MAX_FINITE_INPUT:
        log.warning("material %r: %s %s is not finite; using %g", material_name, socket.name, value, fallback)
        return float(fallback)
    return value


#: The largest magnitude a material's float input is read as (Blender stores an "inf" typed into
#: a field as FLT_MAX, finite but overflowing the first product it meets; as `snapshot.MAX_FINITE_COLOR`).
MAX_FINITE_INPUT = 1e15


def _fold(socket, depth):
    """The constant an input evaluates to (float or (3,) array), or None when it is not constant."""
    if not socket.is_linked:
        value = socket.default_value
        return np.asarray(tuple(value)[:3], np.float64) if hasattr(value, "__len__") else float(value)
    node, output = _source(socket)
    if node is None or depth > 16:
        return None
    if node.type == "RGB":
        return np.asarray(tuple(node.outputs[0].default_value)[:3], np.float64)
    if node.type == "VALUE":
        return float(node.outputs[0].default_value)
    if node.type == "MIX" and getattr(node, "data_type", "") in ("RGBA", "FLOAT") and node.blend_type == "MIX":
        names = ("A", "B")
        sockets = [s for s in node.inputs if s.name in names and s.enabled]
        fac = _fold(node.inputs[0], depth + 1)
        values = [_fold(s, depth + 1) for s in sockets]
        if fac is None or len(values) != 2 or any(v is None for v in values):
            return None
        fac = float(np.clip(np.mean(fac), 0, 1)) if getattr(node, "clamp_factor", True) else float(np.mean(fac))
        return (1 - fac) * np.asarray(values[0]) + fac * np.asarray(values[1])
    return None


def _grey(name):
    return snap.Material(name=name, base_color=np.full(3, FALLBACK_GREY, np.float32))


def _without_surface(name, volume: bool):
    """The `Material` of an output without a Surface shader, as Cycles renders it (measured): with
    a Volume shader the surface is a mere boundary that the camera, rays and shadows pass straight
    through (a fog box around a scene, a smoke domain: the volume itself is not rendered,
    `_warn_volume` said so), with nothing linked an opaque black surface."""
    if volume:
        return snap.Material(name=name, base_color=np.zeros(3, np.float32), clear=True)
    log.warning("material %r: no shader linked to its output: black, as Cycles renders it", name)
    return snap.Material(name=name, base_color=np.zeros(3, np.float32))


def _warn_volume(tree, what) -> bool:
    """Warn when a material's or world's output has a Volume shader linked: Cycles renders it
    (fog, absorption, scattering), HybridGI does not. Whether one is linked."""
    output = tree.get_output_node(OUTPUT_TARGET)
    volume = None if output is None else output.inputs.get("Volume")
    node = None if volume is None else _linked_node(volume)
    if node is not None:
        log.warning("%s: its Volume shader (%s) is not rendered: HybridGI renders surfaces only", what, node.bl_idname)
    return node is not None


def _surface_input(tree):
    output = tree.get_output_node(OUTPUT_TARGET)
    return None if output is None else output.inputs.get("Surface")


#: Node groups a shader tree is read through, nested at most this deep (Cycles flattens any depth).
GROUP_DEPTH = 8


class _Inputs:
    """A node's inputs seen through the node groups it sits in (`_GroupNode`)."""

    def __init__(self, raw, groups):
        self._raw, self._groups = raw, groups

    def _wrap(self, socket):
        return None if socket is None else _GroupSocket(socket, self._groups)

    def __getitem__(self, key):
        item = self._raw[key]
        return [self._wrap(s) for s in item] if isinstance(key, slice) else self._wrap(item)

    def get(self, key, default=None):
        socket = self._raw.get(key)
        return default if socket is None else self._wrap(socket)

    def __iter__(self):
        return (self._wrap(s) for s in self._raw)

    def __len__(self):
        return len(self._raw)


class _GroupNode:
    """A shader node as the material reader sees it: its inputs resolve through the node groups
    around it (`_GroupSocket`), its name carries the group nodes' (no clash with the material's
    own nodes, whose names key the bakes); every other attribute is the node's own."""

    def __init__(self, node, groups=()):
        self._node, self._groups = node, tuple(groups)

    def __getattr__(self, name):
        return getattr(self._node, name)

    @property
    def inputs(self):
        return _Inputs(self._node.inputs, self._groups)

    @property
    def name(self):
        return "/".join([g.name for g in self._groups] + [self._node.name])

    @property
    def grouped(self) -> bool:
        """Whether the node sits inside a node group (Blender cannot bake its inputs in place)."""
        return bool(self._groups)


class _GroupSocket:
    """An input socket of the flattened tree Cycles compiles: one linked from a node group's Group
    Input node is the group node's own input, in the tree around the group (linked there, or its
    value); `_source` descends into the groups it meets. `groups`: the group nodes the socket sits
    in, outermost first."""

    def __init__(self, socket, groups=()):
        self._socket, self._groups = socket, tuple(groups)
        self._hop = None  # `_outer`'s answer, once asked: (socket or None,)

    def __getattr__(self, name):
        return getattr(self._socket, name)

    def _outer(self):
        """The group node's input this socket reads through a Group Input node, or None (found
        once: `_source` asks for is_linked and links in turn)."""
        if self._hop is None:
            self._hop = (self._find_outer(),)
        return self._hop[0]

    def _find_outer(self):
        socket = self._socket
        if self._groups and socket.is_linked:
            link = socket.links[0]
            if not link.is_muted and link.from_node.type == "GROUP_INPUT":
                outer = self._groups[-1].inputs.get(link.from_socket.identifier)
                if outer is None:  # matched by name where identifiers differ (older files)
                    outer = next((i for i in self._groups[-1].inputs if i.name == link.from_socket.name), None)
                return None if outer is None else _GroupSocket(outer, self._groups[:-1])
        return None

    @property
    def is_linked(self):
        outer = self._outer()
        return self._socket.is_linked if outer is None else outer.is_linked

    @property
    def default_value(self):
        outer = self._outer()
        return self._socket.default_value if outer is None else outer.default_value

    @property
    def links(self):
        outer = self._outer()
        return outer.links if outer is not None else [_GroupLink(link, self._groups) for link in self._socket.links]

    @property
    def node(self):
        return _GroupNode(self._socket.node, self._groups)


class _GroupLink:
    """A link of the flattened tree (`_GroupSocket.links`)."""

    def __init__(self, link, groups):
        self._link, self._groups = link, groups

    def __getattr__(self, name):
        return getattr(self._link, name)

    @property
    def from_node(self):
        return _GroupNode(self._link.from_node, self._groups)


def _group_output(group_node, identifier):
    """The socket inside node group `group_node` that its output `identifier` gives (its active
    Group Output node's input), or None."""
    tree = getattr(group_node, "node_tree", None)
    if tree is None:
        return None
    outputs = [n for n in tree.nodes if n.type == "GROUP_OUTPUT"]
    out = next((n for n in outputs if getattr(n, "is_active_output", False)), outputs[0] if outputs else None)
    return None if out is None else out.inputs.get(identifier)


def _source(socket):
    """(node, output socket identifier) feeding `socket` through reroutes and node groups (a group
    node's output continues at its Group Output node inside, a Group Input's at the group node's
    input outside: the flattened tree Cycles compiles; nodes returned as `_GroupNode`); (None,
    None) when the socket is unlinked or the link or node is muted (Cycles then uses the socket's
    own value)."""
    if socket is not None and not isinstance(socket, _GroupSocket):
        socket = _GroupSocket(socket)
    while socket is not None and socket.is_linked:
        link = socket.links[0]
        if link.is_muted:
            return None, None
        node = link.from_node
        if node.type == "GROUP" and not node.mute:
            inner = _group_output(node, link.from_socket.identifier)
            if inner is None or len(node._groups) >= GROUP_DEPTH:
                return None, None
            socket = _GroupSocket(inner, node._groups + (node._node,))
            continue
        if node.type != "REROUTE":
            return (None, None) if node.mute else (node, link.from_socket.identifier)
        socket = node.inputs[0]
    return None, None


def _linked_node(socket):
    return _source(socket)[0]


def _color_socket(socket, textures, material_name):
    """(base colour (3,) float32, texture or None) of a colour input: its value, a folded
    constant, an image plugged in directly, or the texture Blender baked for it."""
    value = _rgb(socket.default_value)
    if not socket.is_linked:
        return value, None
    node, output = _source(socket)
    if node is None:
        return value, None  # a muted link: Cycles uses the socket's own value
    baked = textures.baked.get((socket.node.name, socket.identifier))
    if baked is not None:
        # Baked, even an image: the material's triangles read the bake's atlas UVs.
        return np.ones(3, np.float32), baked
    if _direct_image(node, output):
        texture = textures.get(node.image, material_name)
        if texture is not None:
            # The texture is the colour; the base colour multiplies it (Material.mean_albedo).
            return np.ones(3, np.float32), texture
        return value, None
    folded = _fold(socket, 0)
    if folded is not None:
        return np.broadcast_to(np.asarray(folded, np.float32), (3,)).copy(), None
    texture = textures.baked.get((socket.node.name, socket.identifier))
    if texture is not None:
        return np.ones(3, np.float32), texture
    if not textures.pending:
        log.warning("material %r: %s from node %r (%s) could not be baked; using its value", material_name,
                    socket.name, node.name, node.bl_idname)
    return value, None


def _direct_image(node, output, alpha: bool = False) -> bool:
    """Whether an Image Texture's colour is what the core samples itself: the mesh's default
    UV map, flat projection, repeated, one image (anything else, e.g. a UV Map node, box mapping
    or a UDIM image's tiles, which the mesh's UVs pick beyond 0..1, is baked). alpha : the socket
    is an opacity (`_alpha_map`), which reads the image's Alpha output itself too."""
    if node.type != "TEX_IMAGE" or output not in (("Color", "Alpha") if alpha else ("Color",)) or node.image is None:
        return False
    if getattr(node.image, "source", "FILE") == "TILED":
        return False
    vector = node.inputs.get("Vector")
    return (vector is None or _source(vector)[0] is None) and node.projection == "FLAT" and node.extension == "REPEAT"


#: Shader inputs whose colour `material_bake` bakes when the reader cannot fold it.
BAKED_INPUTS = {"BSDF_PRINCIPLED": "Base Color", "BSDF_DIFFUSE": "Color"}
#: What a Diffuse BSDF's Roughness or a Principled BSDF's Diffuse Roughness above 0 is noted as:
#: Cycles' rough diffuse (energy-preserving Oren-Nayar) brightens surfaces lit from behind the
#: viewer and darkens others; the light here is Lambertian (a floor and wall at roughness 1 under
#: the sun, 128x96: Combined 0.149 against Cycles).
ROUGH_DIFFUSE_NOTE = "a rough diffuse (Oren-Nayar roughness: rendered Lambertian)"


def bake_sockets(material) -> list[tuple[str, str]]:
    """Every pair of `bake_plan(material)` (its masks and bump height with the rest, and its
    images where anything else is baked)."""
    own, masks, heights, images = bake_plan(material)
    needed = own + masks + heights
    return needed + images if needed else needed


def bake_plan(material) -> tuple[list, list, list, list]:
    """(own, masks, heights, images): (node name, input identifier) of every diffuse colour input of `material`'s surface
    (through Mix / Add Shaders) that needs Blender to evaluate it: linked to anything but a
    readable image, a constant, or a muted link; and (node name, EMISSION_BAKE) of every
    emission whose colour or strength is linked to anything but constants or an image's colour
    under a constant strength; apart, the masks its Mix Shaders mix surfaces by (`_texel_factor`)
    and its bump height Blender must evaluate (`height_bakes`), which a sync bakes only within
    OPTIONAL_BAKE_JOBS (and a height only on a mesh coarse enough for its atlas); and its images
    on these inputs, which are baked too once anything else is (its triangles are then on the
    bake's atlas UVs)."""
    tree = getattr(material, "node_tree", None)
    if tree is None:
        return [], [], [], []
    out, images, masks = [], [], []
    stack, seen = [_linked_node(_surface_input(tree))], set()
    while stack:
        node = stack.pop()
        if node is None or node.name in seen or len(seen) > 64:
            continue
        seen.add(node.name)
        if node.type in ("MIX_SHADER", "ADD_SHADER"):
            shaders = [_linked_node(s) for s in node.inputs if s.type == "SHADER"]
            stack += shaders
            fac = node.inputs.get("Fac") if node.type == "MIX_SHADER" else None
            if (fac is not None and fac.is_linked and _fold(fac, 0) is None
                    and any(n is not None and n.type == "BSDF_TRANSPARENT" for n in shaders)):
                # A cutout mask from nodes (Mix(Transparent, surface) by a procedural or a
                # processed image): baked as the hole's map (`_alpha_map`).
                source, output = _source(fac)
                if source is not None and source.type not in VIEW_FACTOR_NODES:
                    (images if _direct_image(source, output) else out).append((node.name, fac.identifier))
            elif (fac is not None and fac.is_linked and not getattr(node, "grouped", False) and _fold(fac, 0) is None
                  and _texel_factor(fac)):
                # Two surfaces mixed by a mask (dirt, wear, a second material): its value per texel,
                # which mixes their colours (`_mix_surface`).
                masks.append((node.name, fac.identifier))
            continue
        if getattr(node, "grouped", False):
            continue  # inside a node group: the bake process edits the material's own tree only
        glow = EMISSION_INPUTS.get(node.type)
        if glow is not None and all(node.inputs.get(n) is not None for n in glow):
            colour, strength = (node.inputs[n] for n in glow)
            if _fold(colour, 0) is None or _fold(strength, 0) is None:
                source, output = _source(colour)
                image = _fold(strength, 0) is not None and _direct_image(source, output)
                (images if image else out).append((node.name, EMISSION_BAKE))
        for scalar in BAKED_SCALARS.get(node.type, ()):
            socket = node.inputs.get(scalar)
            source, output = _source(socket) if socket is not None and socket.is_linked else (None, None)
            if source is not None and _fold(socket, 0) is None:
                # An image's alpha straight into Alpha (a leaf card's cutout) is read as it is, not
                # baked per mesh (a tree of 40 cards: 40 bakes and materials, 0.19 s of each sync).
                direct = _direct_image(source, output, alpha=scalar == "Alpha")
                (images if direct else out).append((node.name, socket.identifier))
        name = BAKED_INPUTS.get(node.type)
        socket = node.inputs.get(name) if name else None
        if socket is None or not socket.is_linked:
            continue
        source, output = _source(socket)
        if source is None:
            continue
        if _direct_image(source, output):
            images.append((node.name, socket.identifier))
            continue
        if _fold(socket, 0) is None:
            out.append((node.name, socket.identifier))
    return out, masks, height_bakes(material, [tree.nodes[n] for n in seen if n in tree.nodes]), images


def height_bakes(material, shaders) -> list[tuple[str, str]]:
    """[(node name, "Height" identifier)] of the bump height Blender must evaluate for
    `material`, whose surface `shaders` were walked: a Bump node on their Normal input or the
    Material Output's Displacement node (Bump Only or Both), fed by a procedural or an image
    through a mapping (`_height_map` reads a plain image itself). Its bake lies on the atlas,
    so the bump of a slot that bakes it reads the atlas UVs (`with_atlas(bumped=)`); only where
    it is the material's one normal-bending map (a tangent-space map keeps the mesh's UVs and
    tangents, and two heights would need both UV sets): else none, and the height is noted as
    rendered with the smooth normal, as before."""
    tree = material.node_tree
    heights = {}
    for node in shaders:
        socket = _input(node, "Normal")
        if socket is None or not socket.is_linked or node.type in ("MIX_SHADER", "ADD_SHADER"):
            continue
        source, _output = _source(socket)
        if source is None:
            continue
        if source.type != "BUMP" or _source(source.inputs["Normal"])[0] is not None:
            return []  # a normal map (under the bump or alone) reads the mesh's own UVs
        heights[source.name] = source
    output = tree.get_output_node(OUTPUT_TARGET)
    socket = None if output is None else output.inputs.get("Displacement")
    if socket is not None and socket.is_linked:
        source, _output = _source(socket)
        method = getattr(material, "displacement_method", None) or getattr(
            getattr(material, "cycles", None), "displacement_method", "BUMP")
        if source is not None and source.type == "DISPLACEMENT" and method != "DISPLACEMENT":
            heights[source.name] = source
    if len(heights) != 1:
        return []
    node = next(iter(heights.values()))
    height = node.inputs.get("Height")
    if height is None or not height.is_linked or getattr(node, "grouped", False) or _fold(height, 0) is not None:
        return []
    source, output = _source(height)
    if source is None or _direct_image(source, output, alpha=True):
        return []
    return [(node.name, height.identifier)]


#: Object Info value sets baked per mesh slot of a material that reads them (`_object_variant`).
MAX_OBJECT_VARIANTS = 16
#: Object Info outputs `object_values` gives (the rest are not per object: the bake's copy of the
#: material has the same Material Index).
OBJECT_INFO_OUTPUTS = ("Location", "Color", "Alpha", "Object Index", "Random")


def object_info_outputs(material) -> frozenset:
    """Outputs of the Object Info nodes of `material`'s own tree that are linked: what its bakes
    must be given per object (`object_values`); empty for most materials."""
    tree = getattr(material, "node_tree", None)
    if tree is None:
        return frozenset()
    return frozenset(out.name for node in tree.nodes if node.type == "OBJECT_INFO" and not node.mute
                     for out in node.outputs if out.is_linked and out.name in OBJECT_INFO_OUTPUTS)


def object_values(instance, outputs) -> dict | None:
    """The Object Info values of a depsgraph instance, those in `outputs` (None when empty), as
    Cycles computes them: Random is the instance's random_id, or for an object of its own the
    hash of its name (Cycles' hash_uint2(hash_string(name), 0)), over 2^32 - 1; Location the
    instance's world translation; Color and Alpha the object's colour; the pass indices."""
    if not outputs:
        return None
    obj = instance.object
    out = {}
    if "Random" in outputs:
        rid = int(instance.random_id) & 0xFFFFFFFF if instance.is_instance else cycles_name_hash(obj.name)
        out["random"] = round(rid / 4294967295.0, 6)
    if "Location" in outputs:
        out["location"] = tuple(round(float(v), 5) for v in np.asarray(instance.matrix_world)[:3, 3])
    if "Color" in outputs or "Alpha" in outputs:
        out["color"] = tuple(round(float(v), 5) for v in obj.color)
    if "Object Index" in outputs:
        out["object_index"] = int(obj.pass_index)
    return out


def cycles_name_hash(name: str) -> int:
    """Cycles' random id of an object that is no instance: hash_uint2(hash_string(name), 0)
    (util/hash.h: a string hash, then Bob Jenkins' lookup3 final mix)."""
    m = 0xFFFFFFFF
    h = 0
    for ch in name.encode():
        h = (h * 37 + ch) & m
    seed = (0xDEADBEEF + (2 << 2) + 13) & m
    state = {"a": (seed + h) & m, "b": seed, "c": seed}
    # lookup3's final(a, b, c): x ^= y; x -= rot(y, k) for each (x, y, k) in turn.
    for x, y, k in _LOOKUP3_FINAL:
        v = state[y]
        state[x] = ((state[x] ^ v) - (((v << k) | (v >> (32 - k))) & m)) & m
    return state["c"]


_LOOKUP3_FINAL = (("c", "b", 14), ("a", "c", 11), ("b", "a", 25), ("c", "b", 16), ("a", "c", 4), ("b", "a", 14),
                  ("c", "b", 24))


#: bake_id -> the jobs a baked material was made of (the viewport re-bakes edited materials).
_BAKE_JOBS: dict[str, list] = {}


def bake_job(material, node, socket, mesh, local, triangles):
    """`BakeJob` of one input over the triangles (indices into `local.triangles`) of a mesh:
    their corners in object space, every UV map and colour attribute per corner."""
    own = local.triangles[triangles].ravel()
    corners = local.blender_corners(own)  # Blender's per-corner data is read at these
    uv_maps = {}
    for layer in mesh.uv_layers:
        uv = np.empty(len(mesh.loops) * 2, np.float32)
        layer.uv.foreach_get("vector", uv)
        uv_maps[layer.name] = uv.reshape(-1, 2)[corners]
    render = next((layer.name for layer in mesh.uv_layers if layer.active_render), None)
    colors = {}
    corner_vert = None
    for attr in mesh.color_attributes:
        if attr.domain not in ("POINT", "CORNER"):
            continue
        values = np.empty(len(attr.data) * 4, np.float32)
        attr.data.foreach_get("color", values)
        values = values.reshape(-1, 4)
        if attr.domain == "POINT":
            if corner_vert is None:
                corner_vert = corner_verts(mesh)
            values = values[corner_vert]
        colors[attr.name] = values[corners]
    _generic_attributes(material, mesh, corners, colors, corner_vert)
    texspace = (tuple(mesh.texspace_location), tuple(mesh.texspace_size))
    shader = material.node_tree.nodes[node]
    if socket == EMISSION_BAKE:
        colour, strength = (shader.inputs[n] for n in EMISSION_INPUTS[shader.type])
        source = _linked_node(colour) if _fold(colour, 0) is None else _linked_node(strength)
    else:
        source = _linked_node(next(s for s in shader.inputs if s.identifier == socket))
    return material_bake.BakeJob(material=material, node=node, socket=socket, source=getattr(source, "name", ""),
                                 positions=np.ascontiguousarray(local.positions[own], np.float32),
                                 uv_maps=uv_maps, render_uv=render, colors=colors, texspace=texspace,
                                 normals=np.ascontiguousarray(local.normals[own], np.float32))


#: Attribute data types an Attribute node reads as numbers, their `foreach_get` key and width.
_ATTRIBUTE_READS = {"FLOAT": ("value", 1), "INT": ("value", 1), "INT8": ("value", 1), "BOOLEAN": ("value", 1),
                    "FLOAT2": ("vector", 2), "FLOAT_VECTOR": ("vector", 3)}


def _generic_attributes(material, mesh, corners: np.ndarray, colors: dict, corner_vert=None) -> None:
    """colors[name] = (len(corners), 4) float32 for every generic attribute (float, integer,
    boolean, 2D or 3D vector; point, corner or face domain) that an Attribute node of `material`
    names and that is not a colour attribute: the bake mesh carries it as a colour attribute of
    that name, which the node reads as Cycles reads the original (a float f: Color and Vector
    (f, f, f), Fac f; a vector: its components, Fac their mean).

    Why: a Geometry Nodes field stored on the mesh (a height, a mask, a random value per point)
    into a Color Ramp read 0 in the bake: a floor striped by a float attribute came out one
    colour (Combined 0.394 against Cycles). corner_vert : `corner_verts(mesh)` if the caller
    read it already (None: read here if a point attribute needs it)."""
    names = {node.attribute_name for node in _tree_nodes(material.node_tree)
             if node.type == "ATTRIBUTE" and getattr(node, "attribute_type", "GEOMETRY") == "GEOMETRY"
             and node.attribute_name} - set(colors)
    corner_face = None
    for name in sorted(names):
        attr = mesh.attributes.get(name)
        read = None if attr is None else _ATTRIBUTE_READS.get(attr.data_type)
        if read is None or attr.domain not in ("POINT", "CORNER", "FACE"):
            continue
        key, width = read
        values = np.empty(len(attr.data) * width, bool if attr.data_type == "BOOLEAN" else
                          (np.int32 if attr.data_type in ("INT", "INT8") else np.float32))
        attr.data.foreach_get(key, values)
        values = values.astype(np.float32).reshape(-1, width)
        if attr.domain == "POINT":
            if corner_vert is None:
                corner_vert = corner_verts(mesh)
            values = values[corner_vert]
        elif attr.domain == "FACE":
            if corner_face is None:
                totals = np.empty(len(mesh.polygons), np.int32)
                mesh.polygons.foreach_get("loop_total", totals)
                corner_face = np.repeat(np.arange(totals.size, dtype=np.int64), totals)
            values = values[corner_face]
        rgba = np.ones((values.shape[0], 4), np.float32)
        rgba[:, :3] = values if width == 3 else (values[:, [0, 0, 0]] if width == 1 else
                                                 np.concatenate([values, np.zeros_like(values[:, :1])], axis=1))
        colors[name] = np.nan_to_num(rgba[corners], nan=0.0, posinf=0.0, neginf=0.0)


#: Texels along an atlas cell (two triangles, `material_bake.cell_texels`) a baked bump height
#: needs: a finer mesh's cells are a few texels wide, and the bump's differences read across its
#: triangles' borders (the Stanford dragon, 200k triangles under a Noise bump: 6 texels a cell,
#: Diffuse Direct 18% too dark; its Combined 0.153 -> 0.180 against Cycles). Such a mesh keeps
#: the smooth normal, noted.
MIN_BUMP_CELL_TEXELS = 16
#: Mask and bump-height bakes (`bake_plan`'s optional ones: without them the factor keeps its own
#: value and the normal is smooth, as before they were baked) one sync queues at most, each mesh
#: slot's together: a bake is 0.2-4 s of the first render (cached after), and a scene of a hundred
#: rocks under one Noise bump would have spent minutes on them. Past it, noted as before.
OPTIONAL_BAKE_JOBS = 24


def with_atlas(local, slots, baked_slots, bumped=frozenset()):
    """`_LocalMesh` whose triangles in `baked_slots` have corners of their own (appended) with
    the atlas UVs of their bake, in the order `bake_job` lists them. Slots in `bumped` baked
    their bump height too (`height_bakes`): their normal-map UVs are the atlas's as well."""
    positions, normals, uvs = [local.positions], [local.normals], [local.uvs]
    # The normal and bump maps keep reading the mesh's own UVs (their tangents follow those).
    own_uvs = local.uvs if local.normal_uvs is None else local.normal_uvs
    normal_uvs = [own_uvs]
    tangents = None if local.tangents is None else [local.tangents]
    sources = [local.blender_corners(np.arange(local.positions.shape[0]))]
    triangles = local.triangles.copy()
    start = local.positions.shape[0]
    for s in baked_slots:
        sel = np.nonzero(slots == s)[0]
        corners = local.triangles[sel].ravel()
        positions.append(local.positions[corners])
        normals.append(local.normals[corners])
        sources.append(local.blender_corners(corners))
        if tangents is not None:
            tangents.append(local.tangents[corners])
        atlas = material_bake.atlas_uvs(len(sel), material_bake.bake_size(len(sel))).reshape(-1, 2)
        normal_uvs.append(atlas if s in bumped else own_uvs[corners])
        uvs.append(atlas)
        triangles[sel] = start + np.arange(corners.size, dtype=np.int32).reshape(-1, 3)
        start += corners.size
    return _LocalMesh(positions=np.concatenate(positions), normals=np.concatenate(normals),
                      uvs=np.concatenate(uvs).astype(np.float32), triangles=triangles, slot=local.slot,
                      tangents=None if tangents is None else np.concatenate(tangents),
                      normal_uvs=np.concatenate(normal_uvs).astype(np.float32), source=np.concatenate(sources))


def _rgb(color):
    return np.asarray(tuple(color)[:3], np.float32)


def _value(socket):
    return np.float32(socket.default_value)


def srgb_to_linear(c):
    """sRGB EOTF (IEC 61966-2-1), elementwise on float32."""
    c = np.asarray(c, np.float32)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4).astype(np.float32)


#: Texels a material's texture keeps per side, per pixel of the render's longer side (rounded up
#: to a power of two), within MIN_TEXTURE_LIMIT..`snapshot.MAX_TEXTURE_SIZE` (`texture_limit`).
TEXELS_PER_PIXEL = 2
MIN_TEXTURE_LIMIT = 1024


def texture_limit(scene) -> int:
    """Texels per side the scene's material textures are read at, at most: twice the render's
    longer side (a UV island or a close-up magnifies its part of a texture), a power of two, 1024
    to 4096. Why: a PBR asset's 4k maps were read, filtered and uploaded whole for any image (four
    of them on a plate and a ball: the first 320x180 render 11.8 s, 7.9 s once cached, Cycles 16
    spp + OIDN 1.5 s), and a map minified 8 times or more aliases through the G-buffer's 8 x 8
    footprint taps where a smaller copy is its average."""
    render = scene.render
    side = max(int(render.resolution_x), int(render.resolution_y)) * float(render.resolution_percentage) / 100.0
    want = 1 << max(0, math.ceil(math.log2(max(TEXELS_PER_PIXEL * side, 1.0))))
    return int(min(snap.MAX_TEXTURE_SIZE, max(MIN_TEXTURE_LIMIT, want)))


class _TextureCache:
    """Image -> (h, w, 3) float32 linear RGB and (h, w) alpha (row 0 at v = 0), each image read
    once per sync, at most `limit` texels a side (`texture_limit`; None: the scene's)."""

    def __init__(self, limit: int | None = None):
        if limit is None:
            import bpy  # noqa: PLC0415

            limit = texture_limit(bpy.context.scene) if bpy.context.scene is not None else snap.MAX_TEXTURE_SIZE
        self.limit = int(limit)
        self._images = {}
        self.baked = {}  # (node name, input identifier) -> baked texture of the material being read
        self.pending = False
        self.queued = set()  # (node name, input identifier) of the material's bakes, when pending
        self.glossy = set()  # materials with glossy lobes
        self.approximated: dict[str, set[str]] = {}  # material -> what of its nodes is approximated

    def _read(self, image, material_name):
        if image is None:
            log.warning("material %r: image texture without an image; using the base colour", material_name)
            return None
        # The original datablock owns the pixel buffer; an evaluated copy may not have loaded one.
        image = image.original
        key = image.name_full
        if key not in self._images:
            self._images[key] = read_image(image, self.limit)
            if self._images[key] is None:
                # A file that is gone (a .blend moved away from its textures, a path of another
                # machine): Cycles reads it as its missing-texture magenta, opaque, and shows the
                # artist that colour; so does this reader (it used the base colour before).
                log.warning("material %r: image %r (%s) could not be read; it is Cycles' missing-texture magenta",
                            material_name, key, image.filepath or "no file")
                self._images[key] = (np.tile(MISSING_TEXTURE, (2, 2, 1)), None)
        return self._images[key]

    def get(self, image, material_name):
        read = self._read(image, material_name)
        return None if read is None else read[0]

    def alpha(self, image, material_name):
        """(h, w) float32 alpha of an image, None without an alpha channel."""
        read = self._read(image, material_name)
        return None if read is None else read[1]


def image_pixels(image):
    """(h, w, 3) float32 linear RGB of a Blender image, or None when it has no pixels."""
    read = read_image(image)
    return None if read is None else read[0]


def read_image(image, limit: int = snap.MAX_TEXTURE_SIZE):
    """((h, w, 3) float32 linear RGB, (h, w) float32 alpha or None without an alpha channel) of
    a Blender image, or None when it has no pixels. One read of the pixel buffer for both.

    An image larger than `limit` texels a side (at most what the core keeps,
    `snapshot.MAX_TEXTURE_SIZE`) is box-filtered down by an integer factor, in linear values:
    a file's image whose values are linear (float, or data such as Non-Color) is scaled by
    Blender on a copy first (a 16k texture is never copied whole into float32 arrays; 0.05 s for
    a 4k map); an sRGB one is read whole and averaged after decoding (Blender's scale averages
    the encoded bytes: a fine black and white checker read 0.21 for 0.5), as is an image Blender
    cannot scale on a copy (generated or painted ones come back blank)."""
    width, height = image.size
    largest = max(width, height)
    limit = min(int(limit), snap.MAX_TEXTURE_SIZE)
    factor = -(-largest // limit) if largest > limit else 1  # ceil: the box filter's integer factor
    space = image.colorspace_settings.name
    encoded = not image.is_float and space in SRGB_SPACES
    if factor > 1 and not encoded and image.source == "FILE" and not image.is_dirty:
        import bpy  # noqa: PLC0415

        copy = image.copy()
        try:
            copy.scale(max(width // factor, 1), max(height // factor, 1))
            log.info("image %r: %dx%d read at 1/%d size", image.name, width, height, factor)
            return read_image(copy, limit)
        finally:
            bpy.data.images.remove(copy)
    channels = image.channels
    count = width * height * channels
    if count == 0 or len(image.pixels) != count:
        return None
    pixels = np.empty(count, np.float32)
    image.pixels.foreach_get(pixels)
    pixels = pixels.reshape(height, width, channels)
    if channels >= 3:
        rgb = pixels[:, :, :3]
    else:
        rgb = np.repeat(pixels[:, :, :1], 3, axis=2)  # grey (+ alpha)
    # Byte buffers hold the file's encoded values; float buffers are already scene-linear.
    if encoded:
        rgb = _srgb_bytes_to_linear(rgb)
    elif not image.is_float and space not in LINEAR_SPACES:
        log.warning("image %r: colour space %r is read as linear Rec.709", image.name, space)
    alpha = np.ascontiguousarray(pixels[:, :, -1], np.float32) if channels in (2, 4) else None
    if factor > 1:
        rgb = _box_reduced(rgb, factor)
        alpha = None if alpha is None else _box_reduced(alpha[..., None], factor)[..., 0]
        log.info("image %r: %dx%d read at 1/%d size", image.name, width, height, factor)
    return np.ascontiguousarray(rgb, np.float32), alpha


#: sRGB decoding of the 256 values a byte image's texel holds (`_srgb_bytes_to_linear`).
_SRGB_BYTES = srgb_to_linear(np.arange(256, dtype=np.float32) / np.float32(255.0))


def _srgb_bytes_to_linear(rgb: np.ndarray) -> np.ndarray:
    """(h, w, 3) float32 linear values of a byte image's encoded sRGB values (k / 255): a table of
    256 entries, not the transfer curve per texel (0.6 s for a 4k map)."""
    index = (rgb * np.float32(255.0) + np.float32(0.5)).astype(np.uint8)  # exact: k / 255 in 0..1
    return _SRGB_BYTES[index]


def _box_reduced(values: np.ndarray, factor: int) -> np.ndarray:
    """(h / factor, w / factor, c) float32 means of factor x factor blocks of values (h, w, c),
    the edge repeated to a multiple of the factor."""
    h, w, c = values.shape
    ph, pw = -(-h // factor) * factor, -(-w // factor) * factor
    if (ph, pw) != (h, w):
        values = np.pad(values, ((0, ph - h), (0, pw - w), (0, 0)), mode="edge")
    values = values.reshape(ph // factor, factor, pw, c).mean(axis=1, dtype=np.float32)
    return values.reshape(ph // factor, pw // factor, factor, c).mean(axis=2, dtype=np.float32)


# --- lights and world ----------------------------------------------------------------------


def light_from_blender(light, matrix_world, name="", obj=None, notes=None):
    """`Light` of a Blender light placed by `matrix_world` (Cycles' sync_light conventions), or
    None for an area light that is a Portal (Cycles emits nothing from it).

    power = energy x 2^exposure (what diffuse surfaces see; 0 when the object `obj` is hidden
    from diffuse rays), glossy_power the same for glossy lobes (0 when hidden from glossy rays);
    EEVEE's diffuse and specular factors are not Cycles' and are not read; colour includes the blackbody tint and a light node tree's constant
    Emission colour x strength (`_light_nodes`). AREA size/size_y are Blender's (unscaled): the
    object's scale stays in `matrix` and the core applies it to the extents
    (hybridgi_core/lights.py), as Cycles does. An unnormalized area light keeps its radiance
    (strength / pi) by multiplying the power by the placed area. notes : optional dict, what this
    reader approximates -> lamp names, for one warning per sync (`warn_lamp_notes`); None warns here.
    """
    own_notes = notes is None
    notes = {} if own_notes else notes
    if light.type == "AREA" and compat.light_is_portal(light):
        log.debug("light %r is a portal: it emits nothing (as in Cycles); skipped", name)
        return None
    matrix = np.array(matrix_world, np.float64)
    use_temperature, exposure, normalize = compat.light_options(light)
    color = _rgb(light.color)
    if use_temperature:
        color = color * _rgb(light.temperature_color)
    factor, profile = _light_nodes(light, name, notes)
    color = color * factor
    if profile is not None and light.type not in ("POINT", "SPOT"):
        notes.setdefault("an IES profile on an area or sun lamp is not read (it renders at Strength 1)", set()).add(name)
        profile = None
    # The Diffuse and Specular factors are EEVEE's: Cycles renders a lamp with diffuse_factor 0.5
    # (or specular_factor 0) as with 1 (Cornell, Diffuse Direct mean 0.384 either way).
    power = glossy_power = float(light.energy) * 2.0**exposure
    if obj is not None:
        if not getattr(obj, "visible_diffuse", True):
            power = 0.0
        if not getattr(obj, "visible_glossy", True):
            glossy_power = 0.0
    kind = light.type
    fields = {"cast_shadow": compat.light_casts_shadow(light)}
    if kind in ("POINT", "SPOT"):
        fields["profile"] = profile
        fields["radius"] = float(light.shadow_soft_size)
        fields["soft_falloff"] = compat.soft_falloff(light)
        if kind == "SPOT":
            fields["spot_size"] = float(light.spot_size)
            fields["spot_blend"] = float(light.spot_blend)
        if not normalize and fields["radius"] > 0:
            log.warning("light %r: unnormalized point and spot lights are treated as normalized", name)
    elif kind == "SUN":
        fields["angle"] = float(light.angle)
        if not normalize:
            log.warning("light %r: unnormalized sun is treated as normalized", name)
    elif kind == "AREA":
        shape = light.shape
        size_y = light.size_y if shape in ("RECTANGLE", "ELLIPSE") else light.size
        fields.update(shape=shape, size=float(light.size), size_y=float(size_y),
                      spread=float(getattr(light, "spread", np.pi)))
        if not normalize:
            # Extents as the lamp is placed: the core scales size/size_y by the matrix the same way.
            extent_u = matrix[:3, 0] * light.size
            extent_v = matrix[:3, 1] * size_y
            area = float(np.linalg.norm(np.cross(extent_u, extent_v)))
            scale = area * (np.pi / 4 if shape in ("DISK", "ELLIPSE") else 1.0)
            power *= scale
            glossy_power *= scale
    # Cycles subtracts the light of a negative power (or colour); HybridGI's samplers and
    # penumbra estimates take light as positive: such a lamp left speckles and rings where it
    # reached, and lit nothing. It is switched off, named.
    negative = power < 0 or glossy_power < 0 or bool((color < 0).any())
    if negative:
        notes.setdefault(NEGATIVE_LIGHT, set()).add(name)
    if own_notes:
        warn_lamp_notes(notes)
    if negative:
        return None
    return snap.Light(kind=kind, color=color, power=power, matrix=matrix, name=name,
                      glossy_power=None if glossy_power == power else glossy_power, **fields)


#: The lamp note of a negative power or colour (a subtractive lamp: not rendered).
NEGATIVE_LIGHT = "negative power or colour: subtractive light is not rendered; switched off"


def warn_lamp_notes(notes) -> None:
    """One warning per kind of lamp setting approximated (`light_from_blender`'s notes), naming the lamps."""
    for meaning, names in sorted(notes.items()):
        log.warning("light %s: %s", _listed(names), meaning)


def _light_nodes(light, name, notes):
    """((3,) factor a light's node tree puts on its colour x strength, as Cycles multiplies the
    emission its Light Output receives; its IES profile or None): an Emission node's Color x
    Strength where both are constants or the Color a Blackbody node of a constant temperature
    (through reroutes), the Strength an IES Texture's (`_ies_profile`: the profile, times the
    factor); 1 without nodes; 0 with nothing linked to the output. Anything else keeps its own
    value and is noted."""
    one, zero = (np.ones(3, np.float32), None), (np.zeros(3, np.float32), None)
    tree = light.node_tree if getattr(light, "use_nodes", False) else None
    if tree is None:
        return one
    output = tree.get_output_node(OUTPUT_TARGET)
    surface = None if output is None else output.inputs.get("Surface")
    if surface is None or not surface.is_linked:
        if surface is not None and output is not None:
            # An output with nothing linked emits nothing in Cycles.
            return zero
        return one
    node, _ = _source(surface)
    if node is None:  # a muted link or node: nothing reaches the output
        return zero
    if node.type != "EMISSION":
        notes.setdefault(f"its node tree's {node.bl_idname} is not read (the lamp renders as without nodes)",
                         set()).add(name)
        return one
    color_in, strength_in = node.inputs["Color"], node.inputs["Strength"]
    color = _rgb(color_in.default_value)
    source = _source(color_in)[0]
    if source is not None and source.type == "BLACKBODY" and _source(source.inputs["Temperature"])[0] is None:
        # Cycles renders a Blackbody node as it renders the light's own Temperature.
        color, source = blackbody_rgb(source.inputs["Temperature"].default_value), None
    profile = None
    if _source(strength_in)[0] is not None:
        profile = _ies_profile(strength_in, name, notes)
    if source is not None or (_source(strength_in)[0] is not None and profile is None):
        notes.setdefault("an Emission Color or Strength fed by a node is not read (its own value is used)",
                         set()).add(name)
    strength = 1.0 if profile is not None else float(strength_in.default_value)
    return (color * strength).astype(np.float32), profile


def _ies_profile(socket, name, notes):
    """`ies.IESProfile` of an IES Texture node feeding a lamp's Emission Strength (directly, or
    times a constant by a Math Multiply), its own Strength and that constant folded in; its
    Vector must be unlinked (the lamp's own frame). None for anything else, or a file Cycles
    would not read (noted)."""
    node, _ = _source(socket)
    scale = 1.0
    if node is not None and node.type == "MATH" and node.operation == "MULTIPLY":
        a, b = (_source(node.inputs[i])[0] for i in (0, 1))
        constants = [float(node.inputs[i].default_value) for i, n in enumerate((a, b)) if n is None]
        linked = [n for n in (a, b) if n is not None]
        if len(linked) != 1 or len(constants) != 1:
            return None
        node, scale = linked[0], constants[0]
    if node is None or node.type != "TEX_IES" or _source(node.inputs["Vector"])[0] is not None:
        return None
    import bpy  # noqa: PLC0415

    try:
        if node.mode == "EXTERNAL":
            with open(bpy.path.abspath(node.filepath), encoding="latin-1") as handle:
                text = handle.read()
        else:
            text = node.ies.as_string() if node.ies is not None else ""
    except OSError as err:
        notes.setdefault(f"its IES file could not be read ({err.__class__.__name__}): it renders as without it",
                         set()).add(name)
        return None
    profile = ies.parse(text)
    if profile is None:
        notes.setdefault("its IES profile is not one Cycles reads (it renders as without it)", set()).add(name)
        return None
    factor = scale * float(node.inputs["Strength"].default_value)
    return ies.IESProfile(profile.h, profile.v, (profile.table * np.float32(factor)).astype(np.float32))


#: Environment maps already split, by what they depend on (`_environment_key`): a world that did
#: not change costs nothing on the next sync. A few entries: worlds are few and maps large.
_SPLITS: dict = {}
_SPLITS_KEPT = 4
#: The splits on disk (~3 MiB each), by `_split_disk_key`.
_SPLIT_STORE = BakeStore("environment", kept=1, disk_limit=256 << 20)


def _euler_matrix(euler):
    """(3, 3) rotation of Blender's XYZ Euler angles (X applied first)."""
    x, y, z = (float(a) for a in euler)
    cx, sx, cy, sy, cz, sz = np.cos(x), np.sin(x), np.cos(y), np.sin(y), np.cos(z), np.sin(z)
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return rz @ ry @ rx


def _texture_to_world(env_node, world_name):
    """(3, 3) map from the Environment Texture's lookup directions to world directions, or None
    when its Vector input is something this reader does not follow (a warning says what)."""
    node, output = _source(env_node.inputs["Vector"])
    if node is None:
        return np.eye(3)  # unlinked: the world direction itself
    if node.type == "TEX_COORD" and output in ("Generated", "Object"):
        return np.eye(3)
    if node.type != "MAPPING":
        log.warning("world %r: environment vector from %s is not supported; read unrotated", world_name, node.bl_idname)
        return np.eye(3)
    inner, inner_out = _source(node.inputs["Vector"])
    if inner is not None and not (inner.type == "TEX_COORD" and inner_out in ("Generated", "Object")):
        log.warning("world %r: mapping of %s is not supported; read unrotated", world_name, inner.bl_idname)
        return np.eye(3)
    rotation = _euler_matrix(node.inputs["Rotation"].default_value)
    scale = np.diag([float(v) or 1e-12 for v in node.inputs["Scale"].default_value])
    forward = rotation @ scale  # POINT, VECTOR, NORMAL: texture = R (S d) (+ location)
    if node.vector_type == "TEXTURE":
        forward = np.linalg.inv(forward)  # the inverse transform
    return np.linalg.inv(forward)


def _cached_split(key, read, to_world=None, disk_key=None):
    """The `EnvironmentSplit` cached under `key`, else of the map `read()` returns (None: none).
    disk_key : disk_key() -> the split's name on disk (`_SPLIT_STORE`) or None (kept in memory
    only), called only where memory misses (a file's stat and a hash per sync otherwise).

    Why on disk: a map's split costs 0.1-0.4 s at 1024x512 and over a second at 4096x2048 (the
    pixels' read besides), paid by every new process (each `hybridgi render`, each frame range),
    where a 640x360 render takes 1-3 s; the material and world bakes were already kept so."""
    split = _SPLITS.get(key)
    if split is not None:
        return split
    disk_key = None if disk_key is None else disk_key()
    if disk_key is not None:
        arrays = _SPLIT_STORE.load_arrays(disk_key)
        if arrays is not None:
            try:
                split = environment.split_from_arrays(arrays)
            except (KeyError, TypeError, ValueError) as err:
                log.debug("environment split %s unreadable (%s): split again", disk_key, err)
    if split is None:
        pixels = read()
        if pixels is None:
            return None
        split = environment.split_environment(pixels, to_world)
        if disk_key is not None:
            _SPLIT_STORE.save_arrays(disk_key, environment.split_arrays(split))
    _SPLITS[key] = split
    while len(_SPLITS) > _SPLITS_KEPT:
        _SPLITS.pop(next(iter(_SPLITS)))
    return split


def _split_disk_key(*parts) -> str:
    """A file name for a split of what `parts` name, with the split's version and Blender's."""
    import bpy  # noqa: PLC0415

    digest = hashlib.sha256(f"split={environment.SPLIT_VERSION}|{bpy.app.version_string}".encode())
    for part in parts:
        digest.update(part if isinstance(part, bytes) else repr(part).encode())
    return digest.hexdigest()[:32]


def _image_file_key(image, to_world) -> str | None:
    """`_split_disk_key` of an image read from a file unchanged since (its absolute path, size in
    bytes and modification time, its colour space, the map's rotation), or None: packed,
    generated, edited in Blender, or not found (memory only)."""
    import bpy  # noqa: PLC0415

    if image.source != "FILE" or image.packed_file is not None or image.is_dirty:
        return None
    try:
        path = os.path.realpath(bpy.path.abspath(image.filepath, library=image.library))
        stat = os.stat(path)
    except (OSError, ValueError):
        return None
    return _split_disk_key("file", path, stat.st_size, stat.st_mtime_ns, tuple(image.size),
                           image.colorspace_settings.name, to_world.round(6).tobytes())


#: Cycles' colour of an image texture whose file cannot be read (`TEX_IMAGE_MISSING_R/G/B`).
MISSING_TEXTURE = np.array([1.0, 0.0, 1.0], np.float32)


def _environment_split(source, world_name):
    """`EnvironmentSplit` of an Environment Texture node (cached), or None when it has no image."""
    image = source.image
    if image is None:
        return None
    if source.projection != "EQUIRECTANGULAR":
        log.warning("world %r: %s projection is read as equirectangular", world_name, source.projection.lower())
    to_world = _texture_to_world(source, world_name)
    image = image.original
    key = (image.name_full, image.filepath, tuple(image.size), image.is_dirty, to_world.round(6).tobytes(),
           image.colorspace_settings.name)
    split = _cached_split(key, lambda: image_pixels(image), to_world, lambda: _image_file_key(image, to_world))
    if split is None:
        # A file that is gone (a .blend moved away from its HDRI, a path of another machine):
        # Cycles lights and shows the world in its missing-texture magenta; so does this reader,
        # at once, rather than baking the tree through Cycles (~4 s) to the same colour.
        log.warning("world %r: environment image %r (%s) could not be read; the world is Cycles' missing-texture "
                    "magenta", world_name, image.name, image.filepath or "no file")
        split = _cached_split(("missing",), lambda: np.tile(MISSING_TEXTURE, (16, 32, 1)))
    return split


def _environment_source(node):
    """The Environment Texture a Background output `node` shows as it is (read directly, not
    baked: `_world_split`), or None."""
    if node.type != "BACKGROUND" or node.inputs["Strength"].is_linked:
        return None
    source, output = _source(node.inputs["Color"])
    if source is not None and source.type == "TEX_ENVIRONMENT" and output == "Color" and source.image is not None:
        return source
    return None


def start_world_bakes(world) -> None:
    """Start now, in the background, the bakes `read_world` will wait for (`world_bake`), so that
    a final render's sync reads its meshes and bakes its materials while Blender renders the
    world's map: they ran one after the other (a Sky Texture's bake was 1.1-1.9 s of the sync
    on top of the materials' bake process). A world read directly or already baked starts none."""
    if world is None or world.node_tree is None:
        return
    node = _output_node(world)
    if node is None or _is_uniform(node):
        return
    rays = ["camera"] if _environment_source(node) is None else []
    if _light_path_outputs(world.node_tree):
        rays = ["diffuse", "camera"]
    for kind in rays:
        key = world_bake.world_key(world, kind)
        if ("baked", key) not in _SPLITS:
            world_bake.bake_world(world, wait=False, key=key, rays=kind)


def _output_node(world):
    tree = world.node_tree
    return _linked_node(_surface_input(tree)) if tree is not None else None


def _is_uniform(node) -> bool:
    """Whether a world's output node gives the same radiance in every direction."""
    return (node.type == "BACKGROUND" and not node.inputs["Color"].is_linked
            and not node.inputs["Strength"].is_linked)


def _world_split(world, node, wait=True, rays="camera"):
    """(`EnvironmentSplit`, strength still to apply) of a world whose output `node` varies with
    direction; None for a uniform world, or one that could not be read (yet).

    An Environment Texture on the Background's colour is read directly (exact, fast); any other
    tree (Sky Texture, gradients, mixes) is baked by Blender itself (`world_bake`), both cached.
    rays : "camera", or "diffuse" for the world as diffuse bounce rays see it (a tree with Light
    Path nodes; always baked).
    """
    if _is_uniform(node):
        return None
    source = _environment_source(node) if rays == "camera" else None
    if source is not None:
        split = _environment_split(source, world.name)
        if split is not None:
            return split, float(_value(node.inputs["Strength"]))
    key = world_bake.world_key(world, rays)
    split = _cached_split(("baked", key), lambda: world_bake.bake_world(world, wait=wait, key=key, rays=rays),
                          disk_key=lambda: _split_disk_key("baked", key))
    if split is None:
        return None
    size = _sky_sun_size(world.node_tree)
    if size is not None and split.sun_direction is not None:
        # The bake's map is box-filtered to ~0.7 degree texels: a 0.545 degree disc spread over
        # several of them read as 1.56 degrees wide, and its shadows three times as soft as
        # Cycles' (sky_yard 640x360: the sun's penumbrae were most of the Combined error). The
        # node says how large it draws the disc.
        split = replace(split, sun_angle=size)
    return split, 1.0


def _sky_sun_size(tree) -> float | None:
    """The angular diameter (radians) of the sun disc that the Sky Textures of a world tree draw
    (nested groups too), or None: no disc, or discs of different sizes."""
    sizes = set()
    for node in _tree_nodes(tree):
        if (node.type == "TEX_SKY" and not node.mute and getattr(node, "sun_disc", False)
                and node.sky_type not in ("PREETHAM", "HOSEK_WILKIE") and any(o.is_linked for o in node.outputs)):
            sizes.add(round(float(node.sun_size), 9))
    return sizes.pop() if len(sizes) == 1 else None


def _tree_nodes(tree, seen=None):
    """Every node of a node tree and of the groups it uses, each group once."""
    seen = set() if seen is None else seen
    if tree is None or tree.name_full in seen:
        return
    seen.add(tree.name_full)
    for node in tree.nodes:
        yield node
        yield from _tree_nodes(getattr(node, "node_tree", None), seen)


def _light_path_outputs(tree) -> set[str]:
    """Names of the Light Path outputs a (world) node tree uses, in nested groups too."""
    return {o.name for n in _tree_nodes(tree) if n.type == "LIGHT_PATH" and not n.mute for o in n.outputs if o.is_linked}


def _sun_lights(split, strength, world_name) -> list:
    """The SUN `Light`s of a split map: its sun, then its further compact regions
    (`EnvironmentSplit.more_suns`: a studio map's softboxes); none without light."""
    if split.sun_direction is None:
        return []
    found = [_sun_light(split.sun_direction, split.sun_irradiance, split.sun_angle, strength, f"{world_name}/sun")]
    found += [_sun_light(d, e, a, strength, f"{world_name}/sun {k + 2}") for k, (d, e, a) in enumerate(split.more_suns)]
    return [lamp for lamp in found if lamp is not None]


def _sun_light(direction, irradiance, angle, strength, name):
    """A SUN `Light` towards `direction` of `irradiance` x strength (None without light)."""
    irradiance = np.asarray(irradiance, np.float64) * strength
    power = float(irradiance.max())
    if power <= 0.0:
        return None
    z = np.asarray(direction, np.float64)  # the lamp's local +Z points at the sun
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    matrix = np.eye(4)
    matrix[:3, 0], matrix[:3, 1], matrix[:3, 2] = x, np.cross(z, x), z
    return snap.Light(kind="SUN", color=(irradiance / power).astype(np.float32), power=power, matrix=matrix,
                      angle=float(angle), name=name)


def read_world(world, wait=True):
    """(`World`, [the lamps it brings]) of a Blender world, read once: a uniform Background
    colour x strength, or the sky of a world that varies with direction, whose sun becomes a
    shadowed SUN `Light` (see `environment.py`). wait=False (the viewport): a world whose map
    still bakes reads as its uniform colour, with no sun, meanwhile.

    Cycles' ray visibility of the world (`world.cycles_visibility`): hidden from the camera, the
    background is black; hidden from diffuse rays, it lights nothing (its glossy reflections
    then go too, with a warning, if it stays visible to glossy rays; hidden from glossy rays
    alone is warned about)."""
    found, lamps = _read_world(world, wait)
    visibility = getattr(world, "cycles_visibility", None) if world is not None else None
    if visibility is None:
        return found, lamps
    camera = bool(getattr(visibility, "camera", True))
    diffuse = bool(getattr(visibility, "diffuse", True))
    glossy = bool(getattr(visibility, "glossy", True))
    background = found.background_color if camera else np.zeros(3, np.float32)
    background_map = found.background_map if camera else None
    if not diffuse:
        if glossy:
            log.warning("world %r is hidden from diffuse rays only: it lights nothing, its glossy reflections "
                        "included (Cycles keeps those)", world.name)
        return snap.World(ao_distance=found.ao_distance, background=background, background_map=background_map), []
    if not glossy:
        log.warning("world %r: its visibility to glossy rays off is not followed (glossy surfaces still "
                    "reflect it)", world.name)
    if not camera:
        found = replace(found, background=background, background_map=None)
    return found, lamps


def _read_world(world, wait=True):
    if world is None:
        return snap.World(ao_distance=snap.NO_WORLD_AO_DISTANCE), []
    ao_distance = float(world.light_settings.distance)
    if world.node_tree is None:
        return snap.World(color=_rgb(world.color), ao_distance=ao_distance), []
    _warn_volume(world.node_tree, f"world {world.name!r}")
    node = _output_node(world)
    if node is None:
        # Cycles renders a world with nothing linked to its output as black.
        return snap.World(color=np.zeros(3, np.float32), ao_distance=ao_distance), []
    light_path = _light_path_outputs(world.node_tree)
    if light_path:
        return _read_light_path_world(world, node, ao_distance, light_path, wait)
    found = _world_split(world, node, wait)
    if found is not None:
        split, strength = found
        log.info("world %r: %s and a sky map", world.name,
                 "a shadowed sun" if split.sun_direction is not None else "no sun")
        suns = _sun_lights(split, strength, world.name)
        sky_map = None
        if split.sky_map is not None:
            sky_map = environment.SkyMap(split.sky_map * np.float32(strength), split.to_world)
        return snap.World(color=(split.sky * strength).astype(np.float32), ao_distance=ao_distance,
                          sky_sh=(split.sky_sh * strength).astype(np.float32),
                          sky_map=sky_map, background_map=_background_map(split, strength)), suns
    if node.type != "BACKGROUND":
        log.warning("world %r: %s could not be read; using the viewport colour", world.name, node.bl_idname)
        return snap.World(color=_rgb(world.color), ao_distance=ao_distance), []
    if not _is_uniform(node) and not world_bake.pending():
        log.warning("world %r: its background could not be read; using its colour value", world.name)
    radiance = (_rgb(node.inputs["Color"].default_value) * _value(node.inputs["Strength"])).astype(np.float32)
    return snap.World(color=radiance, ao_distance=ao_distance), []


def _read_light_path_world(world, node, ao_distance, outputs, wait):
    """A world whose tree reads a Light Path node (a backdrop for the camera, an HDRI for the
    light: "Is Camera Ray"): it lights the scene as a diffuse bounce ray sees it, and the
    background shows what the camera sees; each is baked by Blender (`world_bake`, cached)."""
    ambiguous = sorted(outputs & world_bake.AMBIGUOUS_OUTPUTS)
    if ambiguous:
        log.warning("world %r: Light Path %s read as a diffuse bounce ray sees it (Cycles' lamp sampling of the "
                    "world sees none of the ray flags)", world.name, ", ".join(ambiguous))
    light = _world_split(world, node, wait, rays="diffuse")
    seen = _world_split(world, node, wait)
    if light is None or seen is None:
        if not world_bake.pending():
            log.warning("world %r: its Light Path tree could not be baked; using its colour value", world.name)
        return snap.World(color=_rgb(world.color), ao_distance=ao_distance), []
    (split, strength), (camera_split, camera_strength) = light, seen
    log.info("world %r: lit as diffuse rays see it (%s), seen as the camera sees it", world.name,
             "a shadowed sun" if split.sun_direction is not None else "no sun")
    suns = _sun_lights(split, strength, world.name)
    sky_map = None if split.sky_map is None else environment.SkyMap(split.sky_map * np.float32(strength), split.to_world)
    return snap.World(color=(split.sky * strength).astype(np.float32), ao_distance=ao_distance,
                      sky_sh=(split.sky_sh * strength).astype(np.float32), sky_map=sky_map,
                      background=(camera_split.sky * camera_strength).astype(np.float32),
                      background_map=_background_map(camera_split, camera_strength)), suns


def _background_map(split, strength: float):
    """The `BackgroundMap` the camera sees of a split world map (None: none kept)."""
    if split.background is None:
        return None
    return environment.BackgroundMap(split.background, float(strength), split.to_world)


# --- partial re-reads (shading edits in the viewport) ---------------------------------------


def scene_shading(depsgraph, wait_for_world=True):
    """(every lamp instance as a `Light`, then the world's; the `World`): the snapshot's lamps
    and world read again, the world once."""
    world, world_lamps = read_world(depsgraph.scene.world, wait_for_world)
    notes = {}
    lamps = [light_from_blender(inst.object.data, inst.matrix_world, inst.object.name, inst.object, notes)
             for inst in depsgraph.object_instances if inst.object.type == "LIGHT"]
    warn_lamp_notes(notes)
    return [lamp for lamp in lamps if lamp is not None] + world_lamps, world


def scene_materials(snapshot, names=None) -> list:
    """The snapshot's materials, those named (None: all) read again from Blender; same order, so
    the triangles' material indices stay valid."""
    import bpy  # noqa: PLC0415

    out = []
    textures = _TextureCache()
    for material in snapshot.materials:
        source = bpy.data.materials.get(material.name) if names is None or material.name in names else None
        if source is None:
            out.append(material)
            continue
        jobs = _BAKE_JOBS.get(material.bake_id) if material.bake_id else None
        if jobs is None:
            out.append(material_from_blender(source, textures))
            continue
        # A baked material: bake its edited tree over the same triangles (in the background;
        # the old texture stays meanwhile).
        jobs = [material_bake.BakeJob(material=source, node=j.node, socket=j.socket, source=j.source, dynamic=j.dynamic,
                                      positions=j.positions,
                                      uv_maps=j.uv_maps, render_uv=j.render_uv, colors=j.colors, texspace=j.texspace,
                                      normals=j.normals, object_values=j.object_values)
                for j in jobs if (j.node, j.socket) in bake_sockets(source)]
        baked = material_bake.bake(jobs, wait=False)
        if jobs and not all(job.key in baked for job in jobs):
            out.append(material)
            continue
        converted = material_from_blender(source, textures, baked={(j.node, j.socket): baked[j.key] for j in jobs})
        converted.bake_id = jobs[0].key if jobs else None
        if jobs:
            _BAKE_JOBS[jobs[0].key] = jobs
        out.append(converted)
    return out

"""What changed between two scene snapshots, as named changes: the one diff every cache event
comes from.

`diff_snapshots(old, new)` compares two `SceneSnapshot`s and says, by name, which objects moved
rigidly, deformed, appeared, vanished or changed topology, whether lamps, the world or materials
changed, and how far the light jumped. `GISession.sync` turns these into the cache's events
(`on_geometry_changed(boxes)`, `on_lights_changed()`); the viewport worker and incremental final
renders only decide policy on top of them (urgency, warm-up). Pure numpy, no `bpy`: it runs on the
worker thread and is tested with hand-made snapshots.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .snapshot import Light, Material, SceneSnapshot, World

#: Vertices sampled per object to tell a rigid (affine) move from a deformation.
RIGID_SAMPLES = 64
#: Residual of the affine fit, relative to the object's size, under which a move counts as rigid.
RIGID_TOLERANCE = 1e-4

Box = tuple[np.ndarray, np.ndarray]


@dataclass
class SceneChanges:
    """Named differences between two snapshots (object names as `ObjectInfo.name`).

    moved : objects whose vertices all moved by one affine transform (same topology)
    deformed : objects whose vertices moved in any other way (same topology)
    appeared, vanished : objects only in the new / only in the old snapshot
    retopologised : objects in both whose triangles differ (a modifier level, an edit)
    resurfaced : objects whose triangles stayed where they were but read another surface: another
        material (a slot's material swapped), other UVs or other shading normals (smoothing);
        rays hit the same points, which shade otherwise
    lights_changed : a lamp was added, removed or edited
    world_changed : the world's radiance or AO distance changed
    materials_changed : names of materials whose shading inputs changed (added or removed count)
    colours_only : every material in materials_changed kept all but its diffuse colour (its base
        colour and its colour texture's texels, the texture's size kept): it reflects other
        light, nothing in the image or the rays' scene moved, no light source changed
    cutouts_changed : a material's holes for rays changed (alpha texels, clear glass, shadow
        skips; `cutout.Cutouts`), or a material with some was added or removed: rays meet other
        surfaces, so stored hits are stale as after a geometry edit
    light_flux_change : largest relative change of a lamp's flux, the sky's or an emitter's
        radiance (0 = none; 1 = doubled or gone); inf when lamps were added or removed
    light_moved : metres, the farthest any lamp moved
    boxes : world (lo, hi) boxes of every geometry change, where it was and where it is
    """

    moved: list[str] = field(default_factory=list)
    deformed: list[str] = field(default_factory=list)
    appeared: list[str] = field(default_factory=list)
    vanished: list[str] = field(default_factory=list)
    retopologised: list[str] = field(default_factory=list)
    resurfaced: list[str] = field(default_factory=list)
    lights_changed: bool = False
    world_changed: bool = False
    materials_changed: list[str] = field(default_factory=list)
    colours_only: bool = False
    cutouts_changed: bool = False
    light_flux_change: float = 0.0
    light_moved: float = 0.0
    boxes: list[Box] = field(default_factory=list)

    @property
    def topology_changed(self) -> bool:
        """The ray scene must be rebuilt: objects appeared, vanished or changed their triangles."""
        return bool(self.appeared or self.vanished or self.retopologised)

    @property
    def geometry_changed(self) -> bool:
        return self.topology_changed or bool(self.moved or self.deformed)

    @property
    def shading_changed(self) -> bool:
        """Lamps, world, materials or the surfaces of triangles changed: the cache's `on_lights_changed`."""
        return self.lights_changed or self.world_changed or bool(self.materials_changed) or bool(self.resurfaced)

    @property
    def displaced(self) -> list[str]:
        """Objects whose vertices moved with the topology kept (rigidly or not)."""
        return sorted(self.moved + self.deformed)

    @property
    def any(self) -> bool:
        return self.geometry_changed or self.shading_changed

    def light_jumped(self, reach: float, threshold: float) -> bool:
        """Whether the light changed by more than `threshold` (relative flux) or a lamp moved
        farther than `reach` metres (for example the cache's indirect range)."""
        return self.light_flux_change > threshold or self.light_moved > reach


def diff_snapshots(old: SceneSnapshot | None, new: SceneSnapshot) -> SceneChanges:
    """The named changes from `old` to `new`; with no `old`, everything in `new` appeared."""
    changes = SceneChanges()
    if old is None:
        changes.appeared = [o.name for o in new.objects]
        changes.lights_changed = bool(new.lights)
        changes.world_changed = True
        changes.materials_changed = [m.name for m in new.materials]
        changes.boxes = list(object_boxes(new).values())
        return changes
    _diff_geometry(old, new, changes)
    _diff_shading(old, new, changes)
    return changes


def object_boxes(snapshot: SceneSnapshot) -> dict[str, Box]:
    """Object name -> world (lo, hi) float32 box of its triangles, in one pass over all triangles
    (objects without triangles are absent)."""
    g = snapshot.geometry
    if g.triangle_count == 0:
        return {}
    order = np.argsort(g.object_index, kind="stable")
    obj = g.object_index[order]
    starts = np.flatnonzero(np.r_[True, obj[1:] != obj[:-1]])
    corners = g.positions[g.triangles[order]]  # (T, 3, 3)
    lo = np.minimum.reduceat(corners.min(axis=1), starts)
    hi = np.maximum.reduceat(corners.max(axis=1), starts)
    return {snapshot.objects[int(obj[s])].name: (lo[i], hi[i]) for i, s in enumerate(starts)}


# --- geometry ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _ObjectTopology:
    """One object's triangles in a snapshot: vertex rows it uses and its triangles relative to them."""

    vertices: np.ndarray  # (k,) int64 sorted rows of geometry.positions
    triangles: np.ndarray  # (t, 3) int64 indices into `vertices`


def _topologies(snapshot: SceneSnapshot, objects: np.ndarray | None = None) -> dict[str, _ObjectTopology]:
    """Name -> `_ObjectTopology` of every object (or of the object indices `objects`), from one
    sort of the triangles by object: no per-object scan of all triangles."""
    g = snapshot.geometry
    out = {}
    if g.triangle_count == 0:
        return out
    order = np.argsort(g.object_index, kind="stable")
    if objects is not None:
        order = order[np.isin(g.object_index[order], objects)]
        if order.size == 0:
            return out
    obj = g.object_index[order]
    starts = np.flatnonzero(np.r_[True, obj[1:] != obj[:-1]])
    ends = np.r_[starts[1:], obj.size]
    for s, e in zip(starts, ends, strict=True):
        tris = g.triangles[order[s:e]]
        vertices, inverse = np.unique(tris.ravel(), return_inverse=True)
        out[snapshot.objects[int(obj[s])].name] = _ObjectTopology(vertices, inverse.reshape(-1, 3))
    return out


def _same_arrays(a, b) -> bool:
    return a.shape == b.shape and np.array_equal(a, b)


def _diff_geometry(old: SceneSnapshot, new: SceneSnapshot, changes: SceneChanges) -> None:
    go, gn = old.geometry, new.geometry
    same_layout = (
        [o.name for o in old.objects] == [o.name for o in new.objects]
        and _same_arrays(go.triangles, gn.triangles)
        and _same_arrays(go.object_index, gn.object_index)
        and go.positions.shape == gn.positions.shape
    )
    if same_layout:
        if np.array_equal(go.positions, gn.positions):
            changes.resurfaced = _resurfaced(old, new)
            return
        # The common case (animation, a moved object): only vertex positions differ.
        changed = np.flatnonzero((go.positions != gn.positions).any(axis=1))
        tri_changed = np.isin(gn.triangles, changed).any(axis=1)
        # The same triangles in both: one topology of the changed objects serves old and new.
        old_topo = new_topo = _topologies(new, np.unique(gn.object_index[tri_changed]))
        names = set(new_topo)
    else:
        old_topo, new_topo = _topologies(old), _topologies(new)
        changes.appeared = sorted(new_topo.keys() - old_topo.keys())
        changes.vanished = sorted(old_topo.keys() - new_topo.keys())
        names = set()
        for name in old_topo.keys() & new_topo.keys():
            a, b = old_topo[name], new_topo[name]
            if not _same_arrays(a.triangles, b.triangles) or a.vertices.size != b.vertices.size:
                changes.retopologised.append(name)
            elif not np.array_equal(go.positions[a.vertices], gn.positions[b.vertices]):
                names.add(name)
        changes.retopologised.sort()
    for name in sorted(names):
        before = go.positions[old_topo[name].vertices]
        after = gn.positions[new_topo[name].vertices]
        (changes.moved if _is_affine(before, after) else changes.deformed).append(name)
    if same_layout:
        changes.resurfaced = _resurfaced(old, new, skip=set(changes.displaced))
    touched = set(changes.displaced) | set(changes.retopologised)
    old_boxes, new_boxes = object_boxes(old), object_boxes(new)
    for name in sorted(touched | set(changes.vanished)):
        if name in old_boxes:
            changes.boxes.append(old_boxes[name])
    for name in sorted(touched | set(changes.appeared)):
        if name in new_boxes:
            changes.boxes.append(new_boxes[name])


def _resurfaced(old: SceneSnapshot, new: SceneSnapshot, skip: frozenset | set = frozenset()) -> list[str]:
    """Objects of two snapshots with the same triangle layout whose triangles read another
    material (by name: the lists may differ in order), other UVs or other shading normals;
    `skip`: displaced objects, whose normals turn with them."""
    go, gn = old.geometry, new.geometry
    if go.triangle_count == 0 or go is gn:
        return []
    # Arrays shared by both snapshots (a lamp edit's, a move's UVs) are not compared: on 800k
    # vertices the three comparisons take ~13 ms.
    tri = np.zeros(gn.triangle_count, bool)
    if go.material_index is not gn.material_index or old.materials is not new.materials:
        ids: dict = {}
        old_ids = np.array([ids.setdefault((m.name, m.bake_id), len(ids)) for m in old.materials] + [-1], np.int64)
        new_ids = np.array([ids.setdefault((m.name, m.bake_id), len(ids)) for m in new.materials] + [-1], np.int64)
        # (-1 past the end: an index out of the list reads as no material in both.)
        tri |= old_ids[np.clip(go.material_index, -1, len(old.materials))] != \
            new_ids[np.clip(gn.material_index, -1, len(new.materials))]
    vertex = np.zeros(gn.positions.shape[0], bool)
    if go.normals is not gn.normals:
        vertex |= (go.normals != gn.normals).any(axis=1)
    if go.uvs is not gn.uvs:
        if go.uvs.shape == gn.uvs.shape:
            vertex |= ~((go.uvs == gn.uvs) | (np.isnan(go.uvs) & np.isnan(gn.uvs))).all(axis=1)
        else:
            vertex[:] = True
    if vertex.any():
        tri |= vertex[gn.triangles].any(axis=1)
    if not tri.any():
        return []
    names = {new.objects[int(i)].name for i in np.unique(gn.object_index[tri])}
    return sorted(names - set(skip))


def _is_affine(before: np.ndarray, after: np.ndarray) -> bool:
    """Whether one affine map takes the object's old vertices to its new ones (a rigid move, a
    rotation or a scale), fitted on up to RIGID_SAMPLES vertices and checked on those."""
    n = before.shape[0]
    pick = np.linspace(0, n - 1, min(n, RIGID_SAMPLES)).astype(np.int64)
    a = np.c_[before[pick].astype(np.float64), np.ones(pick.size)]
    b = after[pick].astype(np.float64)
    fit, *_ = np.linalg.lstsq(a, b, rcond=None)
    size = max(float(np.ptp(b, axis=0).max(initial=0.0)), float(np.ptp(before[pick], axis=0).max(initial=0.0)), 1e-12)
    return float(np.abs(a @ fit - b).max(initial=0.0)) <= RIGID_TOLERANCE * size


# --- shading -------------------------------------------------------------------------------------


def _light_key(light: Light) -> tuple:
    return (light.kind, light.color.tobytes(), float(light.power), light.matrix.tobytes(), light.radius,
            light.soft_falloff, light.spot_size, light.spot_blend, light.angle, light.shape, light.size, light.size_y,
            light.spread, light.cast_shadow, light.glossy_power,
            None if getattr(light, "profile", None) is None else light.profile.key())


def _material_key(material: Material) -> tuple:
    texture = material.texture
    # The sum, not the bytes: a hash of a 16k texture would copy it on every sync.
    texture_key = None if texture is None else (texture.shape, float(texture.sum(dtype=np.float64)))
    specular = None if material.specular is None else material.specular.key()
    normal_map = None if material.normal_map is None else material.normal_map.key()
    glow = getattr(material, "emission_texture", None)
    glow_key = None if glow is None else (glow.shape, float(glow.sum(dtype=np.float64)))
    metal = getattr(material, "metallic_map", None)
    metal_key = None if metal is None else (metal.shape, float(metal.sum(dtype=np.float64)))
    maps = tuple(None if a is None else (a.shape, float(a.sum(dtype=np.float64)))
                 for a in (getattr(material, "roughness_map", None), getattr(material, "metal_texture", None)))
    return (material.base_color.tobytes(), material.emission.tobytes(), texture_key, specular, normal_map, glow_key,
            metal_key, getattr(material, "holdout", False), getattr(material, "shadow_transparent", False),
            getattr(material, "clear", False), getattr(material, "refractive", False),
            _bytes_or_none(getattr(material, "translucent", None)),
            _bytes_or_none(getattr(material, "sheen", None)), getattr(material, "sheen_roughness", 0.5),
            getattr(material, "sheen_layered", False), maps,
            _cutout_key(material))  # last: `_diff_shading` reads it there


def _cutout_key(material: Material) -> tuple:
    """What of a material rays see through (`cutout.Cutouts`): its alpha texels, clear glass,
    shadow skips. A change moves the rays' hits, not only their light."""
    alpha = getattr(material, "alpha", None)
    return (None if alpha is None else (alpha.shape, float(alpha.sum(dtype=np.float64))),
            getattr(material, "clear", False), getattr(material, "refractive", False),
            getattr(material, "shadow_transparent", False))


def _colourless(key: tuple) -> tuple:
    """A `_material_key` without the diffuse colour: the base colour and the colour texture's
    texels (its size stays in), what `SceneChanges.colours_only` lets differ."""
    texture = key[2]
    return (None,) + key[1:2] + (None if texture is None else texture[0],) + key[3:]


def _bytes_or_none(array) -> bytes | None:
    return None if array is None else np.asarray(array).tobytes()


def _world_key(world: World) -> tuple:
    sky_map = getattr(world.sky_map, "pixels", None)
    return (world.color.tobytes(), world.background_color.tobytes(), float(world.ao_distance),
            None if world.sky_sh is None else world.sky_sh.tobytes(),
            None if sky_map is None else hash(sky_map.tobytes()))


def _relative_change(a, b) -> float:
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    scale = max(np.abs(a).max(initial=0.0), np.abs(b).max(initial=0.0))
    if scale == 0.0:
        return 0.0
    return float(np.abs(a - b).max(initial=0.0) / scale)


def _diff_shading(old: SceneSnapshot, new: SceneSnapshot, changes: SceneChanges) -> None:
    old_lights = [_light_key(lt) for lt in old.lights]
    new_lights = [_light_key(lt) for lt in new.lights]
    changes.lights_changed = old_lights != new_lights
    flux = 0.0
    if len(old.lights) != len(new.lights):
        flux = float("inf")
    elif changes.lights_changed:
        for a, b in zip(old.lights, new.lights, strict=True):
            if a.kind != b.kind:
                flux = float("inf")
                break
            flux = max(flux, _relative_change(a.color * a.power, b.color * b.power))
            changes.light_moved = max(changes.light_moved, float(np.linalg.norm(a.position - b.position)))
    changes.world_changed = _world_key(old.world) != _world_key(new.world)
    if changes.world_changed:
        flux = max(flux, _relative_change(old.world.color, new.world.color))
    # A material baked per mesh (`Material.bake_id`) appears once per mesh under its one name:
    # the k-th of a name pairs with the k-th before.
    old_materials = _by_name(old.materials)
    colours_only = True
    no_holes = _cutout_key(Material())
    for key, m in _by_name(new.materials).items():
        before = old_materials.pop(key, None)
        # Each key once (a colour texture's sum reads every texel).
        was, now = (None if before is None else _material_key(before)), _material_key(m)
        if was != now:
            changes.materials_changed.append(m.name)
            colours_only = colours_only and was is not None and _colourless(was) == _colourless(now)
            if now[-1] != (no_holes if was is None else was[-1]):  # `_cutout_key`, the key's last part
                changes.cutouts_changed = True
            if before is not None:
                flux = max(flux, _relative_change(before.emission, m.emission))
            elif np.any(m.emission > 0):
                flux = float("inf")
    changes.materials_changed += sorted({name for name, _k in old_materials})  # removed
    if any(_cutout_key(m) != no_holes for m in old_materials.values()):
        changes.cutouts_changed = True
    changes.colours_only = bool(changes.materials_changed) and colours_only and not old_materials
    if any(np.any(m.emission > 0) for m in old_materials.values()):
        flux = float("inf")
    changes.light_flux_change = flux


def _by_name(materials) -> dict:
    """(name, k) -> the k-th material of that name, in snapshot order."""
    out, seen = {}, {}
    for m in materials:
        k = seen[m.name] = seen.get(m.name, -1) + 1
        out[(m.name, k)] = m
    return out

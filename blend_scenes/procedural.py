"""HybridGI's own test scenes as plain numpy: one description, two forms.

Each scene is a `SceneDescription` (named parts with local meshes and transforms, materials,
lights, world, camera, frame range). `SceneDescription.snapshot()` turns it into the core's
`SceneSnapshot`; `build.py` turns the very same description into a .blend, so object and material
names, triangle order and world-space positions agree between the two forms.

Conventions: metres, Z up, Blender's. Lights follow Cycles (see GI_FACTS.md): AREA/POINT power in
watts, SUN strength in W/m^2, world and emission colours as radiance. Cameras look along local -Z
with +Y up. Nothing here imports bpy; no randomness, so every call returns identical arrays.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from hybridgi_core.snapshot import (
    Geometry,
    Light,
    Material,
    ObjectInfo,
    SceneSnapshot,
    World,
    concat_geometry,
    geometry_from_arrays,
    make_snapshot,
)

SCENE_NAMES = ("cornell", "atrium", "spheres", "car", "animated")
FPS = 24
GRAVITY = 9.81  # m/s^2, for the bouncing ball's parabola


# --------------------------------------------------------------------------------------------
# Description types
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Camera:
    """A perspective camera aimed at a point, world Z up (no roll).

    location, look_at : metres, world space
    lens_mm, sensor_width_mm : focal length and horizontal sensor width (sensor fit HORIZONTAL)
    resolution : (width, height) pixels
    clip_start, clip_end : metres
    """

    location: tuple[float, float, float]
    look_at: tuple[float, float, float]
    lens_mm: float = 35.0
    sensor_width_mm: float = 36.0
    resolution: tuple[int, int] = (640, 360)
    clip_start: float = 0.05
    clip_end: float = 200.0

    def matrix(self) -> np.ndarray:
        """(4, 4) float64 camera-to-world matrix; the camera looks along its local -Z, +Y up."""
        return _look_matrix(np.asarray(self.location, np.float64), np.asarray(self.look_at, np.float64) - self.location)

    @property
    def horizontal_fov(self) -> float:
        """Full horizontal field of view in radians."""
        return 2.0 * math.atan(0.5 * self.sensor_width_mm / self.lens_mm)


@dataclass(frozen=True)
class Transform:
    """Object transform as Blender stores it: location (m), Euler XYZ rotation (rad), scale."""

    location: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rotation: tuple[float, float, float] = (0.0, 0.0, 0.0)
    scale: tuple[float, float, float] = (1.0, 1.0, 1.0)

    def matrix(self) -> np.ndarray:
        """(4, 4) float64 world matrix T @ Rz @ Ry @ Rx @ S (Blender's XYZ Euler order)."""
        rx, ry, rz = self.rotation
        m = np.eye(4)
        m[:3, :3] = _rot_z(rz) @ _rot_y(ry) @ _rot_x(rx) @ np.diag(self.scale)
        m[:3, 3] = self.location
        return m


@dataclass
class Part:
    """One Blender object: a local mesh with one material.

    geometry : local-space triangles; its material_index / object_index are ignored (set on assembly)
    smooth : True when geometry.normals are authored shading normals (Blender: smooth shading with
        custom split normals); False for flat faces (Blender: flat shading, vertices welded)
    dynamic : moves over the animation (ObjectInfo.dynamic)
    """

    name: str
    geometry: Geometry
    material: str
    smooth: bool = False
    transform: Transform = field(default_factory=Transform)
    dynamic: bool = False


@dataclass
class SceneDescription:
    """Everything both forms of a scene are built from (see the module docstring)."""

    name: str
    parts: list[Part]
    materials: list[Material]
    lights: list[Light]
    world: World
    camera: Camera
    frame_start: int = 1
    frame_end: int = 1
    fps: int = FPS

    @property
    def triangle_count(self) -> int:
        return sum(p.geometry.triangle_count for p in self.parts)

    def snapshot(self) -> SceneSnapshot:
        """World-space SceneSnapshot: object i = parts[i], materials in list order."""
        index = {m.name: i for i, m in enumerate(self.materials)}
        placed = []
        for i, part in enumerate(self.parts):
            g = transformed(part.geometry, part.transform.matrix())
            g.material_index = np.full(g.triangle_count, index[part.material], np.int32)
            g.object_index = np.full(g.triangle_count, i, np.int32)
            placed.append(g)
        objects = [ObjectInfo(p.name, dynamic=p.dynamic) for p in self.parts]
        return make_snapshot(concat_geometry(placed), self.materials, self.lights, self.world, objects)


# --------------------------------------------------------------------------------------------
# Small linear-algebra helpers
# --------------------------------------------------------------------------------------------


def _rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]], np.float64)


def _rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]], np.float64)


def _rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]], np.float64)


def _look_matrix(location: np.ndarray, forward: np.ndarray) -> np.ndarray:
    """(4, 4) matrix whose local -Z points along `forward` and local +Y leans to world +Z."""
    z = -forward / np.linalg.norm(forward)
    up = np.array([0.0, 0.0, 1.0]) if abs(z[2]) < 0.999 else np.array([0.0, 1.0, 0.0])
    x = np.cross(up, z)
    x /= np.linalg.norm(x)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = x, np.cross(z, x), z, location
    return m


def _placement(location=(0.0, 0.0, 0.0), rot_z: float = 0.0, scale=(1.0, 1.0, 1.0)) -> np.ndarray:
    return Transform(tuple(location), (0.0, 0.0, rot_z), tuple(scale)).matrix()


def _light(kind: str, name: str, color, power: float, location, direction=(0.0, 0.0, -1.0), **kw) -> Light:
    """Light at `location` shining along `direction` (its local -Z)."""
    m = _look_matrix(np.asarray(location, np.float64), np.asarray(direction, np.float64))
    return Light(kind=kind, color=np.asarray(color, np.float32), power=power, matrix=m, name=name, **kw)


def _sun_direction(elevation_deg: float, azimuth_deg: float) -> np.ndarray:
    """Unit direction the sunlight travels, for a sun at this elevation and compass azimuth
    (0 = the sun stands towards +Y, 90 = towards +X)."""
    el, az = math.radians(elevation_deg), math.radians(azimuth_deg)
    to_sun = np.array([math.cos(el) * math.sin(az), math.cos(el) * math.cos(az), math.sin(el)])
    return -to_sun


# --------------------------------------------------------------------------------------------
# Mesh generators (local space, material/object index 0)
# --------------------------------------------------------------------------------------------


def transformed(g: Geometry, matrix: np.ndarray) -> Geometry:
    """Geometry moved by a (4, 4) matrix; normals by its inverse transpose, renormalized."""
    return instances(g, np.asarray(matrix, np.float64)[None])


def instances(g: Geometry, matrices: np.ndarray) -> Geometry:
    """N copies of g, one per (N, 4, 4) matrix, concatenated in order (vectorized)."""
    m = np.asarray(matrices, np.float64).reshape(-1, 4, 4)
    n, nv = m.shape[0], g.positions.shape[0]
    pos = np.einsum("nij,vj->nvi", m[:, :3, :3], g.positions.astype(np.float64)) + m[:, None, :3, 3]
    nrm_mat = np.linalg.inv(m[:, :3, :3]).transpose(0, 2, 1)
    nrm = np.einsum("nij,vj->nvi", nrm_mat, g.normals.astype(np.float64))
    nrm /= np.maximum(np.linalg.norm(nrm, axis=2, keepdims=True), 1e-30)
    tris = g.triangles[None] + (np.arange(n) * nv)[:, None, None]
    flip = np.linalg.det(m[:, :3, :3]) < 0  # a mirroring matrix turns faces inside out: swap winding back
    tris[flip] = tris[flip][:, :, ::-1]
    return Geometry(
        positions=pos.reshape(-1, 3).astype(np.float32),
        triangles=tris.reshape(-1, 3).astype(np.int32),
        normals=nrm.reshape(-1, 3).astype(np.float32),
        uvs=np.tile(g.uvs, (n, 1)),
        material_index=np.tile(g.material_index, n),
        object_index=np.tile(g.object_index, n),
    )


def _grid_triangles(nu: int, nv: int) -> np.ndarray:
    """(2 nu nv, 3) triangles over a (nv+1, nu+1) row-major vertex grid (u fastest); normal du x dv."""
    a = (np.arange(nv)[:, None] * (nu + 1) + np.arange(nu)[None, :]).ravel()
    b, c, d = a + 1, a + nu + 2, a + nu + 1
    return np.stack([np.stack([a, b, c], 1), np.stack([a, c, d], 1)], 1).reshape(-1, 3)


def _oriented(positions: np.ndarray, tris: np.ndarray, want: np.ndarray) -> np.ndarray:
    """Triangles with their winding flipped where the face normal opposes `want` ((T, 3) or (3,))."""
    p = positions[tris]
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    flip = np.einsum("ij,ij->i", n, np.broadcast_to(want, n.shape)) < 0
    tris = tris.copy()
    tris[flip] = tris[flip][:, ::-1]
    return tris


def _smooth(positions, tris, normals) -> Geometry:
    """Geometry with authored normals; windings follow the normals so geometric and shading agree."""
    positions = np.asarray(positions, np.float64)
    normals = np.asarray(normals, np.float64)
    normals = normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-30)
    tris = np.asarray(tris, np.int64)
    tris = _oriented(positions, tris, normals[tris].sum(axis=1))
    return geometry_from_arrays(positions, tris, normals=normals)


def box(size=(1.0, 1.0, 1.0)) -> Geometry:
    """Flat-shaded box centred on the origin; size (x, y, z) in metres."""
    corners = (np.array([[i & 1, (i >> 1) & 1, (i >> 2) & 1] for i in range(8)], np.float64) - 0.5) * size
    quads = np.array([[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [2, 6, 7, 3], [0, 4, 6, 2], [1, 3, 7, 5]])
    tris = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    return geometry_from_arrays(corners, tris)


def rectangle(origin, u, v, nu: int = 1, nv: int = 1) -> Geometry:
    """Flat parallelogram origin + s u + t v (s, t in [0, 1]), nu x nv quads; faces along u x v."""
    s, t = np.meshgrid(np.linspace(0, 1, nu + 1), np.linspace(0, 1, nv + 1))
    pos = np.asarray(origin, np.float64) + s.reshape(-1, 1) * np.asarray(u, np.float64) + t.reshape(-1, 1) * np.asarray(v, np.float64)
    return geometry_from_arrays(pos, _grid_triangles(nu, nv))


def cylinder(radius: float, height: float, segments: int = 48, rings: int = 1, radius_top: float | None = None,
             caps: bool = True) -> Geometry:
    """Z-axis cylinder (or frustum) from z = 0 to height: smooth sides, flat caps (split vertices).

    radius, radius_top : metres at the bottom and top (tapering shafts); segments around, rings along Z
    """
    r1 = radius if radius_top is None else radius_top
    theta = np.linspace(0.0, 2 * math.pi, segments + 1)
    v = np.linspace(0.0, 1.0, rings + 1)
    r = radius + (r1 - radius) * v
    shape = (rings + 1, segments + 1)
    ct, st = np.broadcast_to(np.cos(theta), shape), np.broadcast_to(np.sin(theta), shape)
    side = np.stack([r[:, None] * ct, r[:, None] * st, np.broadcast_to(height * v[:, None], shape)], -1)
    slope = (radius - r1) / height  # a tapering side leans its normal upwards
    side_n = np.stack([ct, st, np.full(shape, slope)], -1)
    pos, nrm, tris = [side.reshape(-1, 3)], [side_n.reshape(-1, 3)], [_grid_triangles(segments, rings)]
    if caps:
        base = sum(len(p) for p in pos)
        for z, rr, sign in ((0.0, radius, -1.0), (height, r1, 1.0)):
            ring = np.stack([rr * np.cos(theta[:-1]), rr * np.sin(theta[:-1]), np.full(segments, z)], -1)
            pos.append(np.vstack([[0.0, 0.0, z], ring]))
            nrm.append(np.tile([0.0, 0.0, sign], (segments + 1, 1)))
            j = np.arange(segments)
            tris.append(np.stack([np.zeros(segments, int), 1 + j, 1 + (j + 1) % segments], 1) + base)
            base += segments + 1
    return _smooth(np.vstack(pos), np.vstack(tris), np.vstack(nrm))


def uv_sphere(radius: float, segments: int = 48, rings: int = 24) -> Geometry:
    """Smooth UV sphere centred on the origin (pole fans, no degenerate triangles)."""
    phi = np.linspace(math.pi, 0.0, rings + 1)[1:-1]  # polar angle, bottom row first
    theta = np.linspace(0.0, 2 * math.pi, segments + 1)
    grid = np.stack([np.sin(phi)[:, None] * np.cos(theta), np.sin(phi)[:, None] * np.sin(theta),
                     np.broadcast_to(np.cos(phi)[:, None], (rings - 1, segments + 1))], -1).reshape(-1, 3)
    tris = [_grid_triangles(segments, rings - 2)]
    bottom, top = len(grid), len(grid) + 1
    j = np.arange(segments)
    last = (rings - 2) * (segments + 1)
    tris.append(np.stack([np.full(segments, bottom), j + 1, j], 1))
    tris.append(np.stack([last + j, last + j + 1, np.full(segments, top)], 1))
    unit = np.vstack([grid, [[0.0, 0.0, -1.0], [0.0, 0.0, 1.0]]])
    return _smooth(radius * unit, np.vstack(tris), unit)


def rounded_box(size=(1.0, 1.0, 1.0), radius: float = 0.1, steps: int = 4) -> Geometry:
    """Box with edges and corners rounded by `radius` (m), centred on the origin, smooth normals.

    Each face is a grid whose rim rows are placed so the rounded band is sampled in even angles
    (steps per 45 degrees on each side of an edge).
    """
    h = 0.5 * np.asarray(size, np.float64)
    alpha = np.linspace(0.0, math.pi / 4, steps + 1)

    def coords(half: float) -> np.ndarray:
        inner = half - radius
        rim = inner + radius * np.tan(alpha)
        return np.concatenate([-rim[::-1], rim])

    faces = []  # (normal axis, sign, first tangent axis, second tangent axis): e_t1 x e_t2 = sign e_n
    for axis, sign, t1, t2 in ((2, 1, 0, 1), (2, -1, 1, 0), (0, 1, 1, 2), (0, -1, 2, 1), (1, 1, 2, 0), (1, -1, 0, 2)):
        cu, cv = coords(h[t1]), coords(h[t2])
        uu, vv = np.meshgrid(cu, cv)
        s = np.zeros(uu.shape + (3,))
        s[..., t1], s[..., t2], s[..., axis] = uu, vv, sign * h[axis]
        faces.append((s.reshape(-1, 3), _grid_triangles(len(cu) - 1, len(cv) - 1)))
    pos, nrm, tris, base = [], [], [], 0
    for s, t in faces:
        c = np.clip(s, -(h - radius), h - radius)
        n = s - c
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        pos.append(c + radius * n)
        nrm.append(n)
        tris.append(t + base)
        base += len(s)
    return _smooth(np.vstack(pos), np.vstack(tris), np.vstack(nrm))


def _arch_angles(half_width: float, height: float, segments: int) -> np.ndarray:
    """Angles 0..pi (even steps) plus the two that aim at the spandrel rectangle's top corners."""
    corner = math.atan2(height, half_width)
    return np.unique(np.concatenate([np.linspace(0.0, math.pi, segments + 1), [corner, math.pi - corner]]))


def arch(inner_radius: float, outer_radius: float, depth: float, segments: int = 48,
         angles: np.ndarray | None = None) -> Geometry:
    """Semicircular arch ring (an extruded ring segment): local X along the span, Z up, depth along Y.

    Centred on the springing-line midpoint; the ring spans angles 0..pi. Curved soffit and extrados
    carry smooth normals, the flat faces their own split vertices.
    """
    t = np.linspace(0.0, math.pi, segments + 1) if angles is None else np.asarray(angles, np.float64)
    radial = np.stack([np.cos(t), np.zeros_like(t), np.sin(t)], -1)
    y = np.array([0.0, 0.5 * depth, 0.0])
    inner, outer = inner_radius * radial, outer_radius * radial
    n = len(t)
    seg = np.arange(n - 1)
    quad_tris = np.concatenate([np.stack([seg, seg + 1, seg + n + 1], 1), np.stack([seg, seg + n + 1, seg + n], 1)])
    pos, nrm, tris, base = [], [], [], 0
    strips = (  # (row A, row B, normal of every vertex)
        (inner - y, outer - y, np.tile([0.0, -1.0, 0.0], (2 * n, 1))),
        (inner + y, outer + y, np.tile([0.0, 1.0, 0.0], (2 * n, 1))),
        (inner - y, inner + y, np.vstack([-radial, -radial])),
        (outer - y, outer + y, np.vstack([radial, radial])),
    )
    for a, b, normals in strips:
        pos.append(np.vstack([a, b]))
        nrm.append(normals)
        tris.append(quad_tris + base)
        base += 2 * n
    for k in (0, n - 1):  # the two feet, resting on the capitals
        pos.append(np.array([inner[k] - y, outer[k] - y, outer[k] + y, inner[k] + y]))
        nrm.append(np.tile([0.0, 0.0, -1.0], (4, 1)))
        tris.append(np.array([[0, 1, 2], [0, 2, 3]]) + base)
        base += 4
    return _smooth(np.vstack(pos), np.vstack(tris), np.vstack(nrm))


def spandrel(half_width: float, height: float, opening_radius: float, depth: float, angles: np.ndarray) -> Geometry:
    """Flat wall panel x in [-hw, hw], z in [0, height], depth along Y, pierced by a semicircular
    opening of `opening_radius` centred at the origin (the arch ring fills the opening's edge).

    angles : the arch's sample angles (from `_arch_angles`) so both meshes share the curve
    """
    t = np.asarray(angles, np.float64)
    d = np.stack([np.cos(t), np.sin(t)], -1)
    with np.errstate(divide="ignore"):
        reach = np.minimum(half_width / np.abs(d[:, 0]), height / np.abs(d[:, 1]))
    circle = opening_radius * d
    rect = reach[:, None] * d
    n = len(t)
    seg = np.arange(n - 1)
    face = np.concatenate([np.stack([seg, seg + 1, seg + n + 1], 1), np.stack([seg, seg + n + 1, seg + n], 1)])
    pos, tris, want, base = [], [], [], 0
    for yy, sign in ((-0.5 * depth, -1.0), (0.5 * depth, 1.0)):
        ring = np.vstack([circle, rect])
        pos.append(np.stack([ring[:, 0], np.full(2 * n, yy), ring[:, 1]], -1))
        tris.append(face + base)
        want.append(np.tile([0.0, sign, 0.0], (len(face), 1)))
        base += 2 * n
    y0, y1, hw, r = -0.5 * depth, 0.5 * depth, half_width, opening_radius
    extra = [  # top, and the two springing-line strips beside the opening (they sit on the capitals)
        ([[-hw, y0, height], [hw, y0, height], [hw, y1, height], [-hw, y1, height]], [0.0, 0.0, 1.0]),
        ([[r, y0, 0.0], [hw, y0, 0.0], [hw, y1, 0.0], [r, y1, 0.0]], [0.0, 0.0, -1.0]),
        ([[-hw, y0, 0.0], [-r, y0, 0.0], [-r, y1, 0.0], [-hw, y1, 0.0]], [0.0, 0.0, -1.0]),
    ]
    for quad, normal in extra:
        pos.append(np.asarray(quad, np.float64))
        tris.append(np.array([[0, 1, 2], [0, 2, 3]]) + base)
        want.append(np.tile(normal, (2, 1)))
        base += 4
    positions, tris = np.vstack(pos), np.vstack(tris)
    return geometry_from_arrays(positions, _oriented(positions, tris, np.vstack(want)))


def drape(width: float, height: float, nu: int = 112, nv: int = 96, folds: float = 5.5,
          depth: float = 0.12, phase: float = 0.0) -> Geometry:
    """Hanging cloth: a finely subdivided wavy sheet, smooth normals, facing -Y.

    Spans x in [-width/2, width/2], hangs from z = height down to z = 0; folds deepen towards the
    hem (fold depth `depth` m at the bottom, a third of it at the rod).
    """
    u, v = np.meshgrid(np.linspace(0.0, 1.0, nu + 1), np.linspace(0.0, 1.0, nv + 1))  # v = 0 at the rod
    amp = depth * (1.0 + 2.0 * v) / 3.0
    wave = 2.0 * math.pi * folds * u + phase
    pos = np.stack([width * (u - 0.5), amp * np.sin(wave), height * (1.0 - v)], -1).reshape(-1, 3)
    du = np.stack([np.full_like(u, width), amp * 2.0 * math.pi * folds * np.cos(wave), np.zeros_like(u)], -1)
    dv = np.stack([np.zeros_like(u), depth * 2.0 / 3.0 * np.sin(wave), np.full_like(u, -height)], -1)
    n = -np.cross(du, dv).reshape(-1, 3)  # du x dv points to +Y: the cloth's front faces -Y
    return _smooth(pos, _grid_triangles(nu, nv), n)


BUNNY_HEIGHT = 0.5  # metres, the Stanford bunny's height once placed in the animated scene


def bunny_standin() -> Geometry:
    """Procedural bunny-shaped blob (body, head, ears, tail), smooth, facing -Y.

    Base centred on the origin, BUNNY_HEIGHT tall: the same frame `build.py` normalizes the real
    Stanford bunny to, so either can ride the same animation.
    """
    sphere = uv_sphere(1.0, 32, 16)
    blobs = [  # (centre, radii)
        ((0.0, 0.03, 0.115), (0.11, 0.135, 0.115)),  # body
        ((0.0, -0.1, 0.2), (0.065, 0.07, 0.06)),  # head
        ((-0.028, -0.07, 0.29), (0.018, 0.03, 0.07)),  # ears
        ((0.028, -0.07, 0.29), (0.018, 0.03, 0.07)),
        ((0.0, 0.165, 0.1), (0.03, 0.03, 0.03)),  # tail
    ]  # designed 0.36 m tall, then scaled to BUNNY_HEIGHT
    k = BUNNY_HEIGHT / 0.36
    return instances(sphere, np.stack([_placement(np.multiply(c, k), 0.0, np.multiply(r, k)) for c, r in blobs]))



# --------------------------------------------------------------------------------------------
# Scenes
# --------------------------------------------------------------------------------------------


def _mat(name: str, color, emission=(0.0, 0.0, 0.0)) -> Material:
    return Material(name=name, base_color=np.asarray(color, np.float32), emission=np.asarray(emission, np.float32))


CORNELL_WHITE = (0.8, 0.8, 0.8)
CORNELL_RED = (0.63, 0.065, 0.05)
CORNELL_GREEN = (0.14, 0.45, 0.09)


def cornell_description() -> SceneDescription:
    """Cornell box: x, y in [-1, 1], z in [0, 2] (m), open at y = -1 where the camera looks in.

    Walls are single-sided rectangles facing inwards; a 0.5 m square AREA light of 40 W hangs
    2 cm below the ceiling, pointing down; the world is black.
    """
    parts = [
        Part("floor", rectangle((-1, -1, 0), (2, 0, 0), (0, 2, 0)), "white"),
        Part("ceiling", rectangle((-1, -1, 2), (0, 2, 0), (2, 0, 0)), "white"),
        Part("back_wall", rectangle((-1, 1, 0), (2, 0, 0), (0, 0, 2)), "white"),
        Part("left_wall", rectangle((-1, -1, 0), (0, 2, 0), (0, 0, 2)), "red"),
        Part("right_wall", rectangle((1, -1, 0), (0, 0, 2), (0, 2, 0)), "green"),
        Part("tall_block", transformed(box((0.6, 0.6, 1.2)), _placement((-0.35, 0.3, 0.6), math.radians(-17.0))), "white"),
        Part("short_block", transformed(box((0.6, 0.6, 0.6)), _placement((0.35, -0.35, 0.3), math.radians(17.0))), "white"),
    ]
    materials = [_mat("white", CORNELL_WHITE), _mat("red", CORNELL_RED), _mat("green", CORNELL_GREEN)]
    lights = [_light("AREA", "ceiling_light", (1.0, 1.0, 1.0), 40.0, (0.0, 0.0, 1.98), shape="SQUARE", size=0.5, size_y=0.5)]
    camera = Camera(location=(0.0, -4.5, 1.0), look_at=(0.0, 0.0, 1.0), lens_mm=35.0)
    return SceneDescription("cornell", parts, materials, lights, World(np.zeros(3, np.float32), ao_distance=0.5), camera)


# Atrium layout (m). The courtyard runs along Y between two colonnades at x = +-COLONNADE_X;
# galleries behind them reach the outer walls; the roof is open above the courtyard.
ATRIUM_HALF_X, ATRIUM_HALF_Y, ATRIUM_TOP = 8.5, 16.5, 12.0  # outer extents: bounds are +-X, +-Y, [0, TOP]
COLONNADE_X, BAY = 5.0, 4.0
BAY_CENTRES = np.arange(-14.0, 14.1, BAY)  # 8 bays along Y; supports between them and the end walls
COLUMN_Y = BAY_CENTRES[:-1] + 0.5 * BAY  # 7 free-standing columns per row


@dataclass(frozen=True)
class _Storey:
    floor: float  # z of the plinth's base
    plinth: float  # plinth height
    shaft: float  # shaft height
    capital: float  # capital height
    block: float  # plinth/capital width
    radius: float  # shaft radius at the base (entasis narrows it by 10% at the top)
    wall: float  # spandrel wall thickness (along X)
    top: float  # z of the spandrel's top
    ring_width: float  # radial width of the arch ring

    @property
    def spring(self) -> float:
        return self.floor + self.plinth + self.shaft + self.capital

    @property
    def opening(self) -> float:
        """Outer radius of the arch ring; with ring_width its feet stay on the capitals."""
        return 0.5 * BAY - 0.1


_LOWER = _Storey(floor=0.0, plinth=0.3, shaft=2.65, capital=0.25, block=0.9, radius=0.35, wall=0.6, top=5.4, ring_width=0.3)
_UPPER = _Storey(floor=5.6, plinth=0.25, shaft=2.35, capital=0.2, block=0.7, radius=0.25, wall=0.5, top=10.5, ring_width=0.22)


def _colonnade_matrices(ys: np.ndarray, z: float) -> np.ndarray:
    """One placement per (side, y): both colonnades, local X turned to run along world Y."""
    return np.stack([_placement((side * COLONNADE_X, y, z), math.pi / 2) for side in (-1.0, 1.0) for y in ys])


def _storey_parts(s: _Storey) -> dict[str, Geometry]:
    shaft = cylinder(s.radius, s.shaft, segments=48, rings=12, radius_top=0.9 * s.radius)
    shafts = instances(shaft, _colonnade_matrices(COLUMN_Y, s.floor + s.plinth))
    plinth = instances(box((s.block, s.block, s.plinth)), _colonnade_matrices(COLUMN_Y, s.floor + 0.5 * s.plinth))
    capital = instances(box((s.block, s.block, s.capital)), _colonnade_matrices(COLUMN_Y, s.spring - 0.5 * s.capital))
    angles = _arch_angles(0.5 * BAY, s.top - s.spring, 64)
    # The ring stands 5 cm proud of both wall faces: a moulding that hides the seam with the panel.
    ring = arch(s.opening - s.ring_width, s.opening, s.wall + 0.1, angles=angles)
    panel = spandrel(0.5 * BAY, s.top - s.spring, s.opening, s.wall, angles)
    # Half piers against the end walls carry the end arches' outer feet.
    pier = box((s.block, 0.5 * s.block, s.spring - s.floor))
    y_pier = ATRIUM_HALF_Y - 0.5 - 0.25 * s.block
    piers = instances(pier, np.stack([_placement((side * COLONNADE_X, end * y_pier, 0.5 * (s.floor + s.spring)))
                                      for side in (-1.0, 1.0) for end in (-1.0, 1.0)]))
    return {
        "shafts": shafts,
        "blocks": concat_geometry([plinth, capital, piers]),
        "arches": instances(ring, _colonnade_matrices(BAY_CENTRES, s.spring)),
        "spandrels": instances(panel, _colonnade_matrices(BAY_CENTRES, s.spring)),
    }


def _box_between(lo, hi) -> Geometry:
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    return transformed(box(hi - lo), _placement(0.5 * (lo + hi)))


def _atrium_masonry() -> Geometry:
    """Outer walls, gallery slabs and roofs, cornices and the attic above the colonnades."""
    hx, hy, cx = ATRIUM_HALF_X, ATRIUM_HALF_Y, COLONNADE_X
    boxes = [
        ((-hx, hy - 0.5, 0.0), (hx, hy, ATRIUM_TOP)),  # end walls
        ((-hx, -hy, 0.0), (hx, -hy + 0.5, ATRIUM_TOP)),
    ]
    for side in (-1.0, 1.0):
        def span(a: float, b: float, side: float = side) -> tuple[float, float]:
            return (min(side * a, side * b), max(side * a, side * b))

        x_wall, x_slab, x_cornice = span(hx - 0.5, hx), span(cx + 0.3, hx - 0.5), span(cx - 0.4, cx + 0.4)
        x_attic, x_roof = span(cx - 0.3, cx + 0.3), span(cx + 0.25, hx)
        y0, y1 = -hy + 0.5, hy - 0.5
        boxes += [
            ((x_wall[0], y0, 0.0), (x_wall[1], y1, 10.2)),  # outer wall
            ((x_slab[0], y0, 5.1), (x_slab[1], y1, 5.4)),  # gallery floor slab
            ((x_cornice[0], y0, 5.4), (x_cornice[1], y1, 5.6)),  # cornice the upper columns stand on
            ((x_roof[0], y0, 10.2), (x_roof[1], y1, 10.5)),  # gallery roof
            ((x_cornice[0], y0, 10.5), (x_cornice[1], y1, 10.65)),  # cornice under the attic
            ((x_attic[0], y0, 10.65), (x_attic[1], y1, 11.2)),  # attic
        ]
    return concat_geometry([_box_between(lo, hi) for lo, hi in boxes])


def _atrium_drapes() -> dict[str, Geometry]:
    """Red, green and blue cloths in the ground-floor arches, hung from rods on the courtyard side."""
    width = BAY - _LOWER.block - 0.2
    height = _LOWER.spring - 0.7
    out: dict[str, list[Geometry]] = {"red": [], "green": [], "blue": []}
    colours = ("red", "green", "blue")
    for k, y in enumerate(BAY_CENTRES[1:-1]):  # the six inner bays of each side
        for side in (-1.0, 1.0):
            x = side * (COLONNADE_X - 0.5 * _LOWER.wall - 0.25)
            # Local -Y (the cloth's front) turned to face the courtyard centre.
            m = _placement((x, y, _LOWER.spring - 0.05 - height), -side * math.pi / 2)
            g = drape(width, height, phase=0.7 * k + (0.0 if side < 0 else 1.9))
            out[colours[(k + (side > 0)) % 3]].append(transformed(g, m))
    return {c: concat_geometry(gs) for c, gs in out.items()}


ATRIUM_SKY = (0.35, 0.45, 0.6)


def atrium_description() -> SceneDescription:
    """Sponza-class courtyard, ~320k triangles, bounds x +-8.5, y +-16.5, z [0, 12] (m).

    Two storeys of colonnades (tapered 48-segment shafts, arch rings, spandrel walls) line a
    courtyard open to the sky; twelve drapes hang in the ground-floor arches. A SUN (4.5 W/m^2,
    1 degree) shines through the open roof from the +X side at 62 degrees elevation, so one side of
    the floor and the -X colonnade are sunlit and the rest is bounce-lit.
    """
    lower, upper = _storey_parts(_LOWER), _storey_parts(_UPPER)
    drapes = _atrium_drapes()
    hx, hy = ATRIUM_HALF_X, ATRIUM_HALF_Y
    parts = [
        Part("floor", rectangle((-hx, -hy, 0.0), (2 * hx, 0, 0), (0, 2 * hy, 0)), "floor_stone"),
        Part("masonry", _atrium_masonry(), "plaster"),
        Part("columns_lower", lower["shafts"], "column_stone", smooth=True),
        Part("columns_upper", upper["shafts"], "column_stone", smooth=True),
        Part("column_blocks", concat_geometry([lower["blocks"], upper["blocks"]]), "column_stone"),
        Part("arches_lower", lower["arches"], "arch_stone", smooth=True),
        Part("arches_upper", upper["arches"], "arch_stone", smooth=True),
        Part("spandrels", concat_geometry([lower["spandrels"], upper["spandrels"]]), "plaster"),
        Part("drapes_red", drapes["red"], "drape_red", smooth=True),
        Part("drapes_green", drapes["green"], "drape_green", smooth=True),
        Part("drapes_blue", drapes["blue"], "drape_blue", smooth=True),
    ]
    materials = [
        _mat("floor_stone", (0.55, 0.5, 0.42)),
        _mat("plaster", (0.72, 0.66, 0.55)),
        _mat("column_stone", (0.62, 0.58, 0.5)),
        _mat("arch_stone", (0.66, 0.6, 0.5)),
        _mat("drape_red", (0.6, 0.05, 0.04)),
        _mat("drape_green", (0.08, 0.45, 0.1)),
        _mat("drape_blue", (0.06, 0.12, 0.55)),
    ]
    sun_dir = _sun_direction(62.0, 75.0)
    lights = [_light("SUN", "sun", (1.0, 0.96, 0.9), 4.5, (0.0, 0.0, 14.0), sun_dir, angle=math.radians(1.0))]
    camera = Camera(location=(0.0, -15.2, 1.8), look_at=(0.0, 0.0, 4.2), lens_mm=18.0)
    world = World(np.asarray(ATRIUM_SKY, np.float32), ao_distance=2.0)
    return SceneDescription("atrium", parts, materials, lights, world, camera)


def spheres_description() -> SceneDescription:
    """Four diffuse spheres and a small emissive one on a floor (x +-4, y +-3) before a back wall
    (y = 3, 4 m high); a 150 W 1 m square AREA light and a 100 W POINT light."""
    sphere = uv_sphere(0.5, 64, 32)
    parts = [
        Part("floor", rectangle((-4, -3, 0), (8, 0, 0), (0, 6, 0)), "floor"),
        Part("back_wall", rectangle((-4, 3, 0), (8, 0, 0), (0, 0, 4)), "wall"),
    ]
    colours = [("white", (0.8, 0.8, 0.8)), ("red", (0.7, 0.08, 0.06)), ("blue", (0.08, 0.15, 0.65)),
               ("yellow", (0.75, 0.6, 0.08))]
    for (name, _), x in zip(colours, (-2.1, -0.7, 0.7, 2.1), strict=True):
        parts.append(Part(f"sphere_{name}", transformed(sphere, _placement((x, 0.6, 0.5))), f"sphere_{name}", smooth=True))
    parts.append(Part("sphere_glow", transformed(uv_sphere(0.25, 48, 24), _placement((-1.4, -0.9, 0.25))), "glow", smooth=True))
    materials = [_mat("floor", (0.7, 0.7, 0.7)), _mat("wall", (0.75, 0.72, 0.68))]
    materials += [_mat(f"sphere_{n}", c) for n, c in colours]
    materials.append(_mat("glow", (0.8, 0.8, 0.8), emission=(4.0, 1.8, 0.5)))
    lights = [
        _light("AREA", "area_light", (1.0, 1.0, 1.0), 150.0, (-1.5, -1.0, 3.5), (0.25, 0.2, -1.0), shape="SQUARE", size=1.0, size_y=1.0),
        _light("POINT", "point_light", (1.0, 0.9, 0.8), 100.0, (2.5, -1.5, 2.0), radius=0.1),
    ]
    camera = Camera(location=(0.0, -7.0, 2.2), look_at=(0.0, 0.3, 0.6), lens_mm=35.0)
    return SceneDescription("spheres", parts, materials, lights, World(np.asarray((0.05, 0.06, 0.08), np.float32)), camera)


def car_description() -> SceneDescription:
    """Stylized car (4.2 m long along X) on a 30 m floor under a sun (2.5 W/m^2) and a blue sky.

    Rounded-box body and cabin in diffuse red paint, a dark window band, bumpers, and four wheels
    that touch the floor, so the floor under the car shows contact occlusion and red bounce.
    """
    wheel = cylinder(0.34, 0.26, segments=48, rings=1)
    hub = cylinder(0.18, 0.02, segments=32, rings=1)
    wheel_at, hub_at = [], []
    for x in (-1.35, 1.35):
        for side in (-1.0, 1.0):
            # Cylinder axis Z turned to Y: Rx(-90) maps +Z to +Y, so shift each by its width.
            rot = np.eye(4)
            rot[:3, :3] = _rot_x(-math.pi / 2)
            wheel_at.append(_placement((x, side * 0.86 - 0.13, 0.34)) @ rot)
            hub_at.append(_placement((x, side * 0.99 - (0.0 if side > 0 else 0.02), 0.34)) @ rot)
    parts = [
        Part("floor", rectangle((-15, -15, 0), (30, 0, 0), (0, 30, 0)), "floor"),
        Part("body", transformed(rounded_box((4.2, 1.8, 0.62), 0.18, 4), _placement((0.0, 0.0, 0.59))), "paint", smooth=True),
        Part("cabin", transformed(rounded_box((2.2, 1.6, 0.6), 0.22, 4), _placement((-0.25, 0.0, 1.17))), "paint", smooth=True),
        Part("windows", transformed(rounded_box((2.24, 1.64, 0.32), 0.12, 3), _placement((-0.25, 0.0, 1.2))), "glass", smooth=True),
        Part("bumpers", concat_geometry([_box_between((-2.16, -0.85, 0.3), (-1.95, 0.85, 0.5)),
                                         _box_between((1.95, -0.85, 0.3), (2.16, 0.85, 0.5))]), "trim"),
        Part("wheels", instances(wheel, np.stack(wheel_at)), "rubber", smooth=True),
        Part("hubcaps", instances(hub, np.stack(hub_at)), "trim", smooth=True),
    ]
    materials = [
        _mat("floor", (0.7, 0.7, 0.68)),
        _mat("paint", (0.8, 0.05, 0.04)),
        _mat("glass", (0.04, 0.05, 0.07)),
        _mat("trim", (0.35, 0.35, 0.37)),
        _mat("rubber", (0.03, 0.03, 0.03)),
    ]
    lights = [_light("SUN", "sun", (1.0, 0.97, 0.92), 2.5, (0.0, 0.0, 10.0), _sun_direction(58.0, 215.0), angle=math.radians(2.0))]
    camera = Camera(location=(6.5, -6.0, 2.4), look_at=(0.0, 0.0, 0.6), lens_mm=40.0)
    return SceneDescription("car", parts, materials, lights, World(np.asarray((0.3, 0.38, 0.5), np.float32)), camera)


# Animated scene: 48 frames at 24 fps; the ball's impacts fall on frames 13 and 37.
ANIMATED_FRAMES = (1, 48)
BALL_RADIUS = 0.3
BALL_IMPACT_FRAME, BALL_PERIOD = 13, 24  # frames
BALL_SQUASH, BALL_CONTACT = 0.4, 2.0  # height lost at impact (fraction); contact half-window (frames)


def ball_transform(frame: float) -> Transform:
    """The squashing ball at `frame`: falls from 1.23 m (frame 1), squashes at impact, bounces.

    The arc is free fall (GRAVITY); within BALL_CONTACT frames of an impact the ball squashes
    along Z (volume kept: X and Y grow by 1/sqrt), and it stretches a little while fastest.
    """
    dt = (frame - BALL_IMPACT_FRAME + 0.5 * BALL_PERIOD) % BALL_PERIOD - 0.5 * BALL_PERIOD  # frames from impact
    d = abs(dt)
    bottom = 0.5 * GRAVITY * (dt / FPS) ** 2
    if d < BALL_CONTACT:
        sz = 1.0 - BALL_SQUASH * math.cos(0.5 * math.pi * d / BALL_CONTACT) ** 2
    elif d < BALL_CONTACT + 3.0:
        sz = 1.0 + 0.12 * math.sin(math.pi * (d - BALL_CONTACT) / 3.0)
    else:
        sz = 1.0
    sxy = 1.0 / math.sqrt(sz)
    return Transform((-1.0, 0.4, bottom + BALL_RADIUS * sz), (0.0, 0.0, 0.0), (sxy, sxy, sz))


def bunny_transform(frame: float) -> Transform:
    """The bunny at `frame`: hops (16-frame period, 0.22 m high) round a circle, facing its way."""
    a = 2.0 * math.pi * (frame - 1.0) / (ANIMATED_FRAMES[1] - ANIMATED_FRAMES[0] + 1)
    phase = ((frame - 1.0) % 16.0) / 16.0
    z = 4.0 * 0.22 * phase * (1.0 - phase)
    # Local -Y is the bunny's front; the yaw a + pi turns it along the circle's tangent.
    return Transform((0.8 + 0.5 * math.cos(a), 0.4 + 0.5 * math.sin(a), z), (0.0, 0.0, a + math.pi))


def moving_light_location(frame: float) -> tuple[float, float, float]:
    """The moving POINT light's path: an ellipse 2.2 m above the floor, once round per 48 frames."""
    a = 2.0 * math.pi * (frame - 1.0) / (ANIMATED_FRAMES[1] - ANIMATED_FRAMES[0] + 1)
    return (1.8 * math.cos(a), 0.3 + 1.2 * math.sin(a), 2.2)


def animated_description(frame: float = 1, bunny: Geometry | None = None) -> SceneDescription:
    """Small room (floor x, y in [-3, 3], walls 3 m, blue back wall) with a squashing ball, a
    hopping bunny and a POINT light moving along an ellipse, at `frame` (24 fps, frames 1-48).

    bunny : local Stanford-bunny mesh (base centred on the origin, BUNNY_HEIGHT tall, facing -Y);
        None uses `bunny_standin()`, since reading the .blend needs bpy. `build.py` appends the
        real bunny from ../shared/scenes/bunny_npm.blend into the .blend file.
    """
    parts = [
        Part("floor", rectangle((-3, -3, 0), (6, 0, 0), (0, 6, 0)), "floor"),
        Part("back_wall", rectangle((-3, 3, 0), (6, 0, 0), (0, 0, 3)), "blue_wall"),
        Part("left_wall", rectangle((-3, -3, 0), (0, 6, 0), (0, 0, 3)), "white_wall"),
        Part("right_wall", rectangle((3, -3, 0), (0, 0, 3), (0, 6, 0)), "white_wall"),
        Part("ball", uv_sphere(BALL_RADIUS, 48, 24), "ball", smooth=True, transform=ball_transform(frame), dynamic=True),
        Part("bunny", bunny if bunny is not None else bunny_standin(), "bunny", smooth=True,
             transform=bunny_transform(frame), dynamic=True),
    ]
    materials = [
        _mat("floor", (0.7, 0.68, 0.65)),
        _mat("blue_wall", (0.12, 0.3, 0.6)),
        _mat("white_wall", (0.78, 0.78, 0.78)),
        _mat("ball", (0.8, 0.25, 0.05)),
        _mat("bunny", (0.75, 0.72, 0.65)),
    ]
    lights = [_light("POINT", "moving_light", (1.0, 0.95, 0.85), 150.0, moving_light_location(frame), radius=0.1)]
    camera = Camera(location=(0.0, -5.6, 1.6), look_at=(0.1, 0.4, 0.6), lens_mm=30.0)
    world = World(np.asarray((0.03, 0.035, 0.045), np.float32), ao_distance=0.5)
    return SceneDescription("animated", parts, materials, lights, world, camera, *ANIMATED_FRAMES)


DESCRIPTIONS: dict[str, Callable[[], SceneDescription]] = {
    "cornell": cornell_description,
    "atrium": atrium_description,
    "spheres": spheres_description,
    "car": car_description,
    "animated": animated_description,
}


def describe(name: str, frame: float | None = None) -> SceneDescription:
    """The named scene's description; animated scenes at `frame` (default: their first frame)."""
    if name not in DESCRIPTIONS:
        raise KeyError(f"unknown scene {name!r}; known: {', '.join(SCENE_NAMES)}")
    if name == "animated":
        return animated_description(ANIMATED_FRAMES[0] if frame is None else frame)
    return DESCRIPTIONS[name]()


def camera(name: str) -> Camera:
    """The named scene's camera."""
    return describe(name).camera


def cornell() -> SceneSnapshot:
    return cornell_description().snapshot()


def atrium() -> SceneSnapshot:
    return atrium_description().snapshot()


def spheres() -> SceneSnapshot:
    return spheres_description().snapshot()


def car() -> SceneSnapshot:
    return car_description().snapshot()


def animated_frame(frame: float, bunny: Geometry | None = None) -> SceneSnapshot:
    """The animated scene at `frame` (1-48); ball and bunny are ObjectInfo(dynamic=True).

    The motion is the analytic one `build.py` keyframes, so at integer frames this equals the
    .blend evaluated at that frame. The bunny is the procedural stand-in unless `bunny` is given.
    """
    return animated_description(frame, bunny).snapshot()

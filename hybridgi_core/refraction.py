"""Refraction seen by the camera: smooth glass shows the view its interfaces bend, and reflects.

Why: refractive glass (`snapshot.Material.refractive`: a Glass or Refraction BSDF, a Principled
BSDF's transmission) is clear thin glass for the G-buffer and every ray (`cutout.py`): a glass
ball showed the floor straight through it, without its inverted, magnified image, the world it
reflects or its tint (160x90 against Cycles 1024 spp: Combined 0.0425, where Cycles 16 spp +
OIDN has 0.0088). Here, after a final render's frame, RAYS_PER_PIXEL stratified camera rays per
pixel meet the glass where it comes first (`EmbreeTracer.intersect_glass`), and each follows its
paths: the first interface's Fresnel reflection, and its refraction through up to MAX_INTERFACES
interfaces (at each further one reflected or through, drawn by its Fresnel as Cycles' paths are;
total internal reflection included), tinted at each refraction by the material's colour (and at
each reflection too for a Glass BSDF's, as Cycles tints them), to the surface or the world it ends
on, the frame's own see-through Combined where the image shows that surface (a pane's view), else
shaded as the pixel rays' hits are (`pixel_gather.hit_radiance`: lamp light through shadow rays,
the cache for the rest), or the world as the camera sees it (the environment image itself). A
pixel's Combined becomes the see-through image where its rays missed the glass and the paths' mean
where they met it; its Diffuse and Glossy Color keep the share of rays that missed (Cycles counts
light through glass in its Transmission passes, not there).

Not rendered: caustics (light refracted onto diffuse surfaces: glass casts the lamps' shadows),
rough (frosted) glass (a Translucent BSDF's light, `sync.FROSTED_ROUGHNESS`), glass seen in
reflections or by the GI's rays (clear thin glass still), dispersion and absorption in volume. The
viewport shows clear glass.

numpy + embreex (worker threads or the render thread; no bpy).
"""

from __future__ import annotations

import numpy as np

from .settings import MULTI_BOUNCE
from .specular import fresnel_dielectric
from .trace import Hits

_F32 = np.float32
#: Camera rays per pixel (stratified 2 x 2): the glass's silhouette anti-aliased as the film's.
RAYS_PER_PIXEL = 4
#: Interfaces a refracted path meets at most (a ball: 2; a bottle's walls: 4; a pane seen by its
#: edge reflects inside many times); one still inside glass after them brings no light.
MAX_INTERFACES = 10
#: Added to the settings' seed: the refraction paths' own stream of the frame.
SEED_OFFSET = 29


def refractive_materials(scene) -> np.ndarray:
    """(M,) bool: the scene's refractive clear materials (`Material.refractive`)."""
    return np.array([bool(getattr(m, "clear", False) and getattr(m, "refractive", False)) for m in scene.materials],
                    bool)


def camera_objects(scene) -> np.ndarray:
    """(O,) bool: the scene's objects the camera sees as themselves (not hidden from it, not a
    holdout); at least one entry."""
    seen = [bool(getattr(o, "camera_visible", True)) and not bool(getattr(o, "holdout", False)) for o in scene.objects]
    return np.array(seen or [True], bool)


def camera_glass(scene, geometry, hits: Hits) -> np.ndarray:
    """(n,) bool: the hits (`EmbreeTracer.intersect_glass`'s) on refractive glass the camera sees
    (`refractive_materials`, `camera_objects`): glass hidden from it or a holdout keeps the
    raster's image."""
    out = np.zeros(hits.prim.shape[0], bool)
    hit = np.flatnonzero(hits.prim >= 0)
    prim = hits.prim[hit]
    shown = camera_objects(scene)
    out[hit] = (refractive_materials(scene)[np.asarray(geometry.material_index)[prim]]
                & shown[np.clip(np.asarray(geometry.object_index)[prim], 0, shown.size - 1)])
    return out


def camera_rays(view: np.ndarray, proj: np.ndarray, width: int, height: int, offset: tuple[float, float],
                pix: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(origins, unit directions) (n, 3) float32 of rays through the pixels `pix` (flat indices,
    rows bottom-up as the film's; None: every pixel) at `offset` (pixels from their lower-left
    corner, 0..1): from the near plane along the camera's projection (perspective or orthographic)."""
    inv = np.linalg.inv(np.asarray(proj, np.float64) @ np.asarray(view, np.float64))
    pix = np.arange(width * height) if pix is None else np.asarray(pix)
    x = (pix % width + offset[0]) / width * 2.0 - 1.0
    y = (pix // width + offset[1]) / height * 2.0 - 1.0
    ends = []
    for z in (-1.0, 1.0):
        world = [inv[r, 0] * x + inv[r, 1] * y + (inv[r, 2] * z + inv[r, 3]) for r in range(4)]
        ends.append(np.stack([world[c] / world[3] for c in range(3)], axis=1))
    d = ends[1] - ends[0]
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)
    return ends[0].astype(_F32), d.astype(_F32)


def _smooth_normals(geometry, prim: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(n, 3) float64 the interpolated vertex normals of hits (triangles prim, barycentrics u, v)."""
    tri = np.asarray(geometry.triangles)[prim]
    normals = np.asarray(geometry.normals, np.float64)
    w = np.stack([1.0 - u - v, u, v], axis=1).astype(np.float64)
    n = sum(normals[tri[:, k]] * w[:, k : k + 1] for k in range(3))
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)


def _geometric_normals(geometry, prim: np.ndarray) -> np.ndarray:
    p = np.asarray(geometry.positions, np.float64)[np.asarray(geometry.triangles)[prim]]
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)


def _reflect(d: np.ndarray, n: np.ndarray) -> np.ndarray:
    """(n, 3) the mirror directions of rays d (n, 3) off surfaces of unit normals n (n, 3)."""
    return d - 2.0 * np.einsum("ij,ij->i", d, n)[:, None] * n


def _refract(d: np.ndarray, n: np.ndarray, eta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(directions (n, 3), total internal reflection (n,) bool) of unit rays d crossing an
    interface of unit normal n (facing the ray: d . n < 0) with relative index eta (n,) = n_from /
    n_to; where light cannot pass, the mirror direction."""
    cos_i = -np.einsum("ij,ij->i", d, n)
    k = 1.0 - eta * eta * (1.0 - cos_i * cos_i)
    tir = k < 0.0
    t = eta[:, None] * d + (eta * cos_i - np.sqrt(np.maximum(k, 0.0)))[:, None] * n
    out = np.where(tir[:, None], _reflect(d, n), t)
    return out / np.maximum(np.linalg.norm(out, axis=1, keepdims=True), 1e-300), tir


def _interface(geometry, d, hits: Hits, ior, tint):
    """At refractive hits of rays d: (geometric normal, shading normal (the smooth one, unless it
    turned past the ray), both facing the ray, float64; eta = n_from / n_to; the Fresnel
    reflectance; the material's tint). Whether the ray enters is the geometric normal's say, as
    in Cycles: a glass object whose normals point inwards is entered where it is left."""
    prim = hits.prim
    ng = _geometric_normals(geometry, prim)
    ns = _smooth_normals(geometry, prim, hits.u, hits.v)
    entering = np.einsum("ij,ij->i", d, ng) < 0.0
    sign = np.where(entering, 1.0, -1.0)[:, None]
    n = ns * sign
    # A smooth normal turned past the ray (near silhouettes) takes the geometric one.
    bad = np.einsum("ij,ij->i", d, n) >= 0.0
    n[bad] = (ng * sign)[bad]
    mat = np.asarray(geometry.material_index)[prim]
    eta = np.where(entering, 1.0 / ior[mat], ior[mat])
    fresnel = fresnel_dielectric(np.einsum("ij,ij->i", d, n), 1.0 / eta)
    return ng * sign, n, eta, fresnel, tint[mat]


def glass_paths(system, lookup, origins: np.ndarray, dirs: np.ndarray, rng, screen=None
                ) -> tuple[np.ndarray, np.ndarray]:
    """((n,) bool the rays whose first hit is refractive glass, (n, 3) float32 the radiance their
    paths bring back, 0 elsewhere): see the module docstring. screen : as `_shade`'s."""
    scene, tracer = system.scene, system.tracer
    geometry = tracer.geometry
    refractive = refractive_materials(scene)
    ior = np.array([float(getattr(m, "ior", 1.5)) for m in scene.materials], np.float64)
    ior = np.where(np.isfinite(ior) & (ior > 0.0), ior, 1.5)  # (sync clamps it to 1..4)
    tint = np.array([np.ones(3) if getattr(m, "tint", None) is None else np.asarray(m.tint, np.float64)
                     for m in scene.materials]).reshape(-1, 3)
    # The reflections' tint: a Glass BSDF's colour, white for the others (`Material.tint_reflection`).
    mirror_tint = np.where(np.array([bool(getattr(m, "tint_reflection", False)) for m in scene.materials])[:, None],
                           tint, 1.0)
    out = np.zeros((origins.shape[0], 3), _F32)
    first = tracer.intersect_glass(origins, dirs)
    glass = camera_glass(scene, geometry, first)
    rows = np.flatnonzero(glass)
    if rows.size == 0:
        return glass, out
    eps = float(tracer.epsilon)
    d = dirs[rows].astype(np.float64)
    h = Hits(first.t[rows], first.prim[rows], first.u[rows], first.v[rows])
    p = origins[rows].astype(np.float64) + d * h.t[:, None].astype(np.float64)
    ng, nrm, eta, fresnel, colour = _interface(geometry, d, h, ior, tint)
    # The reflection off the first interface.
    first_mat = np.asarray(geometry.material_index)[h.prim]
    out[rows] = fresnel[:, None] * mirror_tint[first_mat] * _shade(system, lookup, p + ng * eps, _reflect(d, nrm), rng,
                                                                    screen=screen)
    # The refracted path.
    weight = ((1.0 - fresnel)[:, None] * colour)
    d, _tir = _refract(d, nrm, eta)  # entering: no total internal reflection
    origin = p - ng * eps
    live = np.arange(rows.size)
    for _ in range(MAX_INTERFACES):
        hits = tracer.intersect_glass(origin.astype(_F32), d.astype(_F32))
        inside = hits.prim >= 0
        inside[inside] = refractive[np.asarray(geometry.material_index)[hits.prim[inside]]]
        done = np.flatnonzero(~inside)
        if done.size:
            ended = Hits(hits.t[done], hits.prim[done], hits.u[done], hits.v[done])
            light = _shade(system, lookup, origin[done], d[done], rng, ended, screen)
            out[rows[live[done]]] += (weight[done] * light).astype(_F32)
        keep = np.flatnonzero(inside)
        if keep.size == 0:
            break
        live, d, origin, weight = live[keep], d[keep], origin[keep], weight[keep]
        h = Hits(hits.t[keep], hits.prim[keep], hits.u[keep], hits.v[keep])
        p = origin + d * h.t[:, None].astype(np.float64)
        ng, nrm, eta, fresnel, colour = _interface(geometry, d, h, ior, tint)
        through, tir = _refract(d, nrm, eta)
        # Reflected (all of it where light cannot pass) or through, by the Fresnel, as Cycles'
        # paths choose: the tint on the way through.
        back = tir | (rng.random(d.shape[0]) < fresnel)
        d = np.where(back[:, None], _reflect(d, nrm), through)
        weight = weight * np.where(back[:, None], mirror_tint[np.asarray(geometry.material_index)[h.prim]], colour)
        origin = p + np.where(back[:, None], ng, -ng) * eps
    return glass, out


def _shade(system, lookup, origins: np.ndarray, dirs: np.ndarray, rng, hits: Hits | None = None,
           screen=None) -> np.ndarray:
    """(n, 3) float64 radiance back along rays: what they hit (`tracer.intersect`, clear glass
    passed, unless `hits` are given) or the world. A hit on a surface the image shows (`screen`,
    a `screen_light.ScreenLight` of the frame's see-through Combined, or None) takes that pixel's
    radiance: the film's own shading of it, glossy light included; the rest are shaded as the
    pixel rays' hits (`pixel_gather.hit_radiance`, diffuse light only)."""
    from .pixel_gather import hit_radiance

    o = np.ascontiguousarray(origins, _F32)
    d = np.ascontiguousarray(dirs / np.maximum(np.linalg.norm(dirs, axis=1, keepdims=True), 1e-300), _F32)
    if hits is None:
        hits = system.tracer.intersect(o, d)
    out = np.zeros((o.shape[0], 3), np.float64)
    # Rays that leave the scene see the world as the camera does (the environment image at its
    # own resolution), not the lighting's coarse sky map: a window's view of an HDRI.
    background = getattr(system.scene.world, "background_map", None)
    rest = np.arange(o.shape[0])
    if background is not None:
        missed = np.flatnonzero(hits.prim < 0)
        out[missed] = background.radiance(d[missed])
        rest = np.flatnonzero(hits.prim >= 0)
    seen = np.flatnonzero(hits.prim >= 0)
    if screen is not None and seen.size:
        geometry = system.tracer.geometry
        normal = _smooth_normals(geometry, hits.prim[seen], hits.u[seen], hits.v[seen])
        normal *= np.where(np.einsum("ij,ij->i", normal, d[seen]) > 0, -1.0, 1.0)[:, None]
        position = o[seen] + d[seen] * hits.t[seen, None]
        found, value = screen.lookup(np.ascontiguousarray(position, _F32), np.ascontiguousarray(normal, _F32))
        out[seen[found]] = value
        rest = np.setdiff1d(rest, seen[found])
    if rest.size:
        part = Hits(hits.t[rest], hits.prim[rest], hits.u[rest], hits.v[rest])
        radiance = hit_radiance(system, lookup, o[rest], d[rest], part, rng, glossy_lamps=False)
        out[rest] = radiance[:, 0:3] + radiance[:, 3:6]
    return out


def render_glass(system, lookup, view: np.ndarray, proj: np.ndarray, width: int, height: int, rng,
                 seen=None) -> tuple[np.ndarray, np.ndarray] | None:
    """(coverage (h, w) float32, radiance (h, w, 3) float32) of the camera's refractive glass
    (rows bottom-up): the share of each pixel's RAYS_PER_PIXEL rays that met it first and their
    paths' mean radiance; None where no ray met any. seen : (points, normals, flat pixels, see-
    through Combined (h w, >= 3)) of the frame's G-buffer, or None: the paths' ends the image
    shows take their pixel's radiance (`_shade`). lookup : what the paths' hits read of the cache
    (the frame's), or None: built here once glass is seen (`levels.hit_lookup`)."""
    from .levels import hit_lookup
    from .penumbra import dilate
    from .screen_light import ScreenLight

    if not getattr(system.tracer, "has_glass", False) or not refractive_materials(system.scene).any():
        return None
    # The pixels whose centre ray meets glass first, and their neighbours (a silhouette crossing
    # a pixel its centre ray misses): only those trace the stratified rays and their paths.
    o, d = camera_rays(view, proj, width, height, (0.5, 0.5))
    first = system.tracer.intersect_glass(o, d)
    centre = camera_glass(system.scene, system.tracer.geometry, first)
    if not centre.any():
        return None
    todo = np.flatnonzero(dilate(centre.reshape(height, width), 1).reshape(-1))
    if lookup is None:
        lookup = hit_lookup(system, bounced=system.settings.indirect_quality == MULTI_BOUNCE)
    screen = None
    if seen is not None:
        points, normals, pix, combined = seen
        screen = ScreenLight.from_pixels(view, proj, (width, height), points, normals, pix,
                                         np.asarray(combined, np.float32)[pix, :3])
    side = int(round(np.sqrt(RAYS_PER_PIXEL)))
    hits = np.zeros(todo.size, _F32)
    light = np.zeros((todo.size, 3), np.float64)
    for i in range(side):
        for j in range(side):
            o, d = camera_rays(view, proj, width, height, ((i + 0.5) / side, (j + 0.5) / side), todo)
            glass, radiance = glass_paths(system, lookup, o, d, rng, screen)
            hits += glass
            light += radiance
    coverage = np.zeros(width * height, _F32)
    mean = np.zeros((width * height, 3), _F32)
    coverage[todo] = hits / np.float32(side * side)
    mean[todo] = np.divide(light, hits[:, None], out=np.zeros_like(light), where=hits[:, None] > 0)
    return coverage.reshape(height, width), mean.reshape(height, width, 3)

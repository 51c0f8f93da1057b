"""The glossy light of an image's pixels in two parts, as final renders compute it
(`FramePipeline._glossy`: the same `GISystem.glossy`, `glossy_color` and `cache_reflection` calls).

Final renders compute both parts once per frame at the centre raster's pixels. The viewport's
worker computes them at its GI pixels and refreshes each on its own clock: the lamps' part
(`lamp_glossy`, shadow rays, noisy: averaged over passes while the view holds still, traced again
at once after a lamp edit) and the cache's split-sum part (`cache_glossy`, no rays: read again
when the cache changes). `FramePipeline._glossy` keeps its own copy of these steps (main has
since added traced reflections there, which the viewport does not compute yet).

Pure numpy (no bpy, no gpu): the worker thread calls it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import glossy
from .glossy import cache_reflection, glossy_color


def has_glossy(system) -> bool:
    """Whether any material's glossy lobes reflect anything (`GlossyMaterials.reflects`; else nothing to compute)."""
    return hasattr(system, "glossy") and bool(system.glossy_materials.reflects.any())


def material_rows(material: np.ndarray, mats=None) -> np.ndarray:
    """(n,) int64 glossy rows from G-buffer `material` texels (index + 1, 0 = background; a
    material with a Metallic texture adds half its texel's metallic). With `mats`
    (`glossy.GlossyMaterials`), such a pixel's row is its material's variant nearest that
    metallic; without, the material's own row."""
    r = np.asarray(material, np.float32).reshape(-1)
    whole = np.floor(r)
    rows = whole.astype(np.int64) - 1
    variants = getattr(mats, "variants", None)
    if variants is None or not (variants >= 0).any():
        return rows
    known = (rows >= 0) & (rows < variants.shape[0])
    first = np.where(known, variants[np.clip(rows, 0, variants.shape[0] - 1)], -1)
    mapped = first >= 0
    steps = glossy.METALLIC_STEPS - 1
    step = np.clip(np.rint((r - whole) * 2.0 * steps), 0, steps).astype(np.int64)
    rows[mapped] = first[mapped] + step[mapped]
    return rows


def directions_to_eye(points: np.ndarray, eye) -> np.ndarray:
    """(n, 3) unit directions from points to the camera; eye = `gbuffer.camera_eye` (w = 1: a
    position, w = 0: an orthographic camera's direction)."""
    eye = np.asarray(eye, np.float64)
    points = np.asarray(points).reshape(-1, 3)
    to_eye = eye[:3] - points * eye[3] if eye[3] > 0.5 else np.broadcast_to(eye[:3], points.shape)
    return to_eye / np.maximum(np.linalg.norm(to_eye, axis=1, keepdims=True), 1e-30)


@dataclass
class CacheGlossy:
    """The cache's split-sum glossy light at n receivers, each (n, 3) float32.

    colour : Glossy Color at the view angle; sky : the sky's and emitters' reflected radiance
    (part of Glossy Direct, colour applied); bounced : other surfaces' light before its colour
    (Glossy Indirect)."""

    colour: np.ndarray
    sky: np.ndarray
    bounced: np.ndarray

    @property
    def radiance(self) -> np.ndarray:
        """(n, 3) what the deferred pass adds to Combined for this part: sky + colour x bounced."""
        return self.sky + self.colour * self.bounced


def lamp_glossy(system, points, normals, to_eye, rows, frame: int, samples: int) -> np.ndarray:
    """(n, 3) float32 lamp radiance the glossy lobes reflect to the eye (`GISystem.glossy`)."""
    return system.glossy(points, normals, to_eye, rows, frame, samples=samples)


def cache_glossy(system, points, normals, to_eye, rows) -> CacheGlossy:
    """`CacheGlossy` at the receivers: Glossy Color and `glossy.cache_reflection` of the cache as
    it is now (receivers without a glossy colour read no cache)."""
    n = np.asarray(points).reshape(-1, 3).shape[0]
    normals = np.asarray(normals).reshape(-1, 3)
    mu = np.clip(np.einsum("ij,ij->i", normals, to_eye), 0.0, 1.0)
    colour = glossy_color(system.glossy_materials, rows, mu)
    sky = np.zeros((n, 3), np.float32)
    bounced = np.zeros((n, 3), np.float32)
    lit = np.flatnonzero(colour.max(axis=1) > 0)
    if lit.size:
        rough = system.glossy_materials.rough[rows[lit]]
        s, b = cache_reflection(system.cache, np.asarray(points).reshape(-1, 3)[lit], normals[lit], to_eye[lit], rough)
        sky[lit] = colour[lit] * s
        bounced[lit] = b
    return CacheGlossy(colour, sky, bounced)

"""Mix and Add Shaders of diffuse and glossy closures, as Cycles' SVM weighs them (bpy-free: the
add-on's sync reads the nodes and builds the parts; this module combines them).

A shader node becomes a `SurfacePart`: a diffuse colour (base x texture) times a weight over the
view cosine mu, emission, alpha, and glossy closures (`specular.GlossyLobe`). Cycles' Mix Shader
multiplies every closure of its first input by 1 - Fac and of its second by Fac (svm_node_mix_closure),
the Add Shader by 1; Fac is evaluated per shading point, so a Fresnel or Layer Weight factor makes
the weights functions of mu (`fresnel_factor`, `layer_weight_factor`, the nodes' svm/fresnel.h):
(also through Math, Color Ramp and the like: `math_factor`, `ramp_factor`, the add-on's
`_factor_table`); a glossy closure keeps it as its view factor, and the diffuse part's weight is the sum of its
inputs' weights, so Diffuse Color = base x (1 - F(mu)) under Mix(Diffuse, Glossy, Fresnel), as
Cycles' pass shows per pixel. Weights are tables over `specular.view_grid`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace

import numpy as np

from . import sheen
from . import specular as sp

log = logging.getLogger(__name__)


@dataclass
class SurfacePart:
    """What a shader node contributes to a material.

    base : (3,) diffuse colour (times `texture` where there is one); texture : (h, w, 3) or None;
    emission : (3,) radiance; alpha : (h, w) opacity or None; diffuse : (V,) weight of the diffuse
    colour over the view cosine, or None (1); lobes : the glossy closures; layer : the
    `SpecularLayer` of a Principled BSDF read on its own (its layering, exactly as Cycles'),
    dropped once the part is mixed (its lobes and diffuse weight carry it on); normal : the
    `snapshot.NormalMap` on its Normal input, or None; emission_texture : (h, w, 3) emitted
    radiance per texel (then `emission` is its mean), or None; metallic_map : (h, w) a lone
    Principled BSDF's Metallic per texel of `texture`'s UVs (`snapshot.Material.metallic_map`),
    dropped once the part is mixed (its mean stays in the lobes); roughness_map : (h, w) its
    Roughness per texel, the same way (`snapshot.Material.roughness_map`); metal_texture : the
    colour texture under a Metallic texture, the metal's own colour (`Material.metal_texture`); clear : the share of the light
    that passes straight through (a Transparent BSDF's 1, glass's, a Principled BSDF's
    transmission), mixed by the cosine-weighted mean of each part's weight; refract : the share
    of it that passes by refraction (glass, transmission, a Refraction BSDF), mixed alike; translucent : (3,)
    per channel the share of the diffuse colour that is lit from behind (a Translucent BSDF's 1),
    or None (0), mixed by each part's share of the diffuse light; sheen : (3,) a Sheen closure's
    colour or None, `sheen_roughness` its roughness and `sheen_layered` whether it lies over the
    part's base (a Principled BSDF's: `sheen.py`), mixed by the cosine-weighted mean of each
    part's weight (a layered sheen's weight on its base folded into the mixed diffuse weight).
    """

    base: np.ndarray = field(default_factory=lambda: np.zeros(3, np.float32))
    texture: np.ndarray | None = None
    emission: np.ndarray = field(default_factory=lambda: np.zeros(3, np.float32))
    alpha: np.ndarray | None = None
    diffuse: np.ndarray | None = None
    lobes: list = field(default_factory=list)
    layer: sp.SpecularLayer | None = None
    normal: object | None = None
    emission_texture: np.ndarray | None = None
    metallic_map: np.ndarray | None = None
    roughness_map: np.ndarray | None = None
    metal_texture: np.ndarray | None = None
    clear: float = 0.0
    refract: float = 0.0
    #: the share of the light the part's surface stops, the rest passing straight through (a
    #: constant alpha, a Transparent BSDF mixed in): its other values are the surface's where it
    #: is seen (`snapshot.Material.coverage`); mixed by the cosine-weighted mean of each part's weight
    cover: float = 1.0
    #: (index of refraction, (3,) colour, whether the colour tints its reflection too) of the light
    #: it refracts, or None (`snapshot.Material.ior`)
    glass: tuple | None = None
    translucent: np.ndarray | None = None
    sheen: np.ndarray | None = None
    sheen_roughness: float = 0.5
    sheen_layered: bool = False

    def diffuse_table(self) -> np.ndarray:
        """(V,) the diffuse weight over `specular.view_grid`."""
        return np.ones(sp.VIEW_SAMPLES) if self.diffuse is None else sp.sample_view(self.diffuse, sp.view_grid())

    def base_table(self) -> np.ndarray:
        """(V,) the base's diffuse weight over `specular.view_grid`, a layered sheen's share on it
        included (`sheen.weight_row`'s red)."""
        table = self.diffuse_table()
        if self.sheen is None or not self.sheen_layered:
            return table
        return table * sheen.weight_row(self, sp.view_grid())[:, 0]

    def mean_colour(self) -> np.ndarray:
        """(3,) the diffuse colour (base times its texture's mean)."""
        return self.base if self.texture is None else self.base * self.texture.reshape(-1, 3).mean(axis=0)

    def surface(self):
        """`Material.specular` of a material made of this part: the lone Principled BSDF's layer,
        a `specular.GlossySurface`, or None for a plain diffuse surface."""
        if self.layer is not None:
            return self.layer
        live = [lobe for lobe in self.lobes if lobe.active]
        diffuse = None if self.diffuse is None or np.all(self.diffuse == 1.0) else self.diffuse
        if not live and diffuse is None:
            return None
        return sp.GlossySurface(lobes=live, diffuse=diffuse)


def constant_factor(value: float) -> np.ndarray:
    """(V,) a constant Fac, clamped as the Mix Shader clamps it."""
    return np.full(sp.VIEW_SAMPLES, float(np.clip(value, 0.0, 1.0)))


def fresnel_factor(ior: float) -> np.ndarray:
    """(V,) the Fresnel node's output over the view cosine on front faces: the dielectric
    Fresnel of IOR max(ior, 1e-5) (Cycles' svm_node_fresnel)."""
    return np.clip(sp.fresnel_dielectric(sp.view_grid(), max(float(ior), 1e-5)), 0.0, 1.0)


def layer_weight_factor(blend: float, output: str) -> np.ndarray:
    """(V,) the Layer Weight node's output ('Fresnel' or 'Facing') over the view cosine on front
    faces (Cycles' svm_node_layer_weight): Fresnel is the dielectric Fresnel of IOR
    1 / max(1 - blend, 1e-5); Facing is 1 - mu^p, p = 2 blend below 0.5, 0.5 / (1 - blend) above."""
    mu = sp.view_grid()
    blend = float(blend)
    if output == "Fresnel":
        return np.clip(sp.fresnel_dielectric(mu, 1.0 / max(1.0 - blend, 1e-5)), 0.0, 1.0)
    if blend == 0.5:
        return 1.0 - mu
    b = float(np.clip(blend, 0.0, 1.0 - 1e-5))
    p = 2.0 * b if b < 0.5 else 0.5 / (1.0 - b)
    with np.errstate(divide="ignore"):
        return 1.0 - np.power(mu, p)


def _cosine_mean(table: np.ndarray) -> np.ndarray:
    """Cosine-weighted mean over the hemisphere, 2 int f(mu) mu dmu, of (V, ...) values."""
    mu = sp.view_grid()
    f = 2.0 * table * mu.reshape(-1, *([1] * (table.ndim - 1)))
    return ((f[1:] + f[:-1]) * 0.5 * np.diff(mu).reshape(-1, *([1] * (table.ndim - 1)))).sum(axis=0)


def _weighted_lobe(lobe: sp.GlossyLobe, weight: np.ndarray) -> sp.GlossyLobe:
    """A lobe under a mix weight (V,): a constant scales its weight, anything else its view factor."""
    if np.all(weight == weight[0]):
        return replace(lobe, weight=lobe.weight * weight[0])
    view = weight if lobe.view is None else sp.sample_view(lobe.view, sp.view_grid()) * weight
    return replace(lobe, view=view)


def mix(parts: list[SurfacePart], weights: list[np.ndarray], name: str = "") -> tuple[SurfacePart, list[str]]:
    """(the part of Mix / Add Shader over `parts` with weights (V,) each, notes on what it
    approximates).

    Lobes keep their weights (a view factor where the weight depends on mu). The diffuse light
    D(mu) = sum w_i(mu) d_i(mu) c_i must be one colour times one weight: its cosine-weighted mean
    colour times D's relative brightness, exact where the parts' diffuse weights are proportional
    (one diffuse input, or constant factors), noted where they are not. With a texture, colour =
    base x texture: the other parts' mean colours enter divided by the texture's mean."""
    notes = []
    lobes = [_weighted_lobe(lobe, w) for part, w in zip(parts, weights, strict=True) for lobe in part.lobes]
    textured = [i for i, part in enumerate(parts) if part.texture is not None and np.any(weights[i] > 0)]
    if len(textured) > 1:
        log.warning("material %r: a mix of two image textures keeps the stronger one", name)
    texture = parts[max(textured, key=lambda i: float(weights[i].mean()))].texture if textured else None
    mean = texture.reshape(-1, 3).mean(axis=0) if texture is not None else np.ones(3)
    colours = [part.base if part.texture is texture else part.mean_colour() / np.maximum(mean, 1e-6) for part in parts]
    light = sum(w[:, None] * part.base_table()[:, None] * np.asarray(c, np.float64)[None, :]
                for part, w, c in zip(parts, weights, colours, strict=True))  # (V, 3)
    base = _cosine_mean(light)
    brightness = light.mean(axis=1)
    scale = float(base.mean())
    if scale > 0:
        diffuse = brightness / scale
        residual = np.abs(light - diffuse[:, None] * base[None, :]).max()
        if residual > 0.02 * max(float(light.max()), 1e-6):
            notes.append("diffuse inputs of different colours mixed by a view-dependent factor (one colour kept)")
    else:
        diffuse = np.ones(sp.VIEW_SAMPLES)
    translucent = None
    if any(part.translucent is not None for part in parts):
        # Per channel, the translucent parts' share of the mixed diffuse light (cosine means).
        each = [_cosine_mean(w * part.base_table())[()] * np.asarray(c, np.float64) for part, w, c in
                zip(parts, weights, colours, strict=True)]
        back = sum(e * (0.0 if part.translucent is None else np.asarray(part.translucent, np.float64))
                   for part, e in zip(parts, each, strict=True))
        total = sum(each)
        translucent = np.divide(back, total, out=np.zeros(3), where=total > 0).astype(np.float32)
    sheen_colour, sheen_roughness = _mixed_sheen(parts, weights)
    emission = sum(float(_cosine_mean(w)) * part.emission for part, w in zip(parts, weights, strict=True))
    clear = sum(float(_cosine_mean(w)) * part.clear for part, w in zip(parts, weights, strict=True))
    cover = sum(float(_cosine_mean(w)) * part.cover for part, w in zip(parts, weights, strict=True))
    refract = sum(float(_cosine_mean(w)) * part.refract for part, w in zip(parts, weights, strict=True))
    # The refracting part that weighs most gives the mix its index and colour.
    refracting = [(float(_cosine_mean(w)) * part.refract, i) for i, (part, w) in enumerate(zip(parts, weights, strict=True))
                  if part.glass is not None]
    glass = parts[max(refracting)[1]].glass if refracting else None
    glow = _mixed_emission_texture(parts, weights, notes)
    alpha = next((part.alpha for part in parts if part.alpha is not None), None)
    # One shading normal per material: the normal map of the part weighing most (Cycles bends
    # each closure by its own; a mix of differently mapped closures keeps one map, noted).
    mapped = [i for i, part in enumerate(parts) if part.normal is not None and np.any(weights[i] > 0)]
    normal = parts[max(mapped, key=lambda i: float(weights[i].mean()))].normal if mapped else None
    shading = [part for i, part in enumerate(parts) if np.any(weights[i] > 0) and (np.any(part.base > 0) or part.lobes)]
    if mapped and any(part.normal is not normal for part in shading):
        notes.append("closures with different normal inputs mixed (one normal map kept for all)")
    part = SurfacePart(base=np.asarray(base, np.float32), texture=texture, emission=np.asarray(emission, np.float32),
                       alpha=alpha, diffuse=None if np.allclose(diffuse, 1.0) else diffuse, lobes=lobes, normal=normal,
                       emission_texture=glow, clear=float(np.clip(clear, 0.0, 1.0)), cover=float(np.clip(cover, 0.0, 1.0)),
                       refract=float(np.clip(refract, 0.0, 1.0)), glass=glass, translucent=translucent,
                       sheen=sheen_colour, sheen_roughness=sheen_roughness)
    return part, notes


def _mixed_sheen(parts: list[SurfacePart], weights: list[np.ndarray]) -> tuple[np.ndarray | None, float]:
    """((3,) the mixed sheen colour or None, its roughness): each part's sheen colour times the
    cosine-weighted mean of its weight, the roughness the mean of theirs weighted by it."""
    each = [(float(_cosine_mean(w)) * np.asarray(part.sheen, np.float64), part.sheen_roughness)
            for part, w in zip(parts, weights, strict=True) if part.sheen is not None]
    colour = sum((c for c, _ in each), np.zeros(3))
    strength = [float(c.max()) for c, _ in each]
    if not each or sum(strength) <= 0:
        return None, 0.5
    roughness = sum(s * r for s, (_, r) in zip(strength, each, strict=True)) / sum(strength)
    return colour.astype(np.float32), float(roughness)


def _mixed_emission_texture(parts: list[SurfacePart], weights: list[np.ndarray], notes: list[str]) -> np.ndarray | None:
    """(h, w, 3) the emitted radiance per texel of a mix whose parts have emission textures, or
    None: the textured part's texture times its weight plus the other parts' emission (Cycles
    adds the emission closures, each times its mix weight; emission does not depend on the view
    factor's angle beyond its mean here). Two textures: the stronger one is kept, its mean standing
    for the other's, noted."""
    textured = [i for i, part in enumerate(parts) if part.emission_texture is not None and np.any(weights[i] > 0)]
    if not textured:
        return None
    keep = max(textured, key=lambda i: float(_cosine_mean(weights[i])) * float(parts[i].emission.mean()))
    if len(textured) > 1:
        notes.append("emission textures mixed (the stronger kept, the other's mean colour added)")
    glow = np.float32(_cosine_mean(weights[keep])) * parts[keep].emission_texture
    rest = sum((float(_cosine_mean(w)) * part.emission for i, (part, w) in enumerate(zip(parts, weights, strict=True))
                if i != keep), np.zeros(3))
    return (glow + np.asarray(rest, np.float32)).astype(np.float32)


#: Math node operations a factor table goes through (Cycles' svm_math, safe division and power).
MATH_OPERATIONS = ("ADD", "SUBTRACT", "MULTIPLY", "DIVIDE", "POWER", "MINIMUM", "MAXIMUM")
#: Rec.709 luminance: how Cycles turns a colour into a float input (linear_rgb_to_gray).
GRAY = np.array([0.2126, 0.7152, 0.0722])


def math_factor(operation: str, a: np.ndarray, b: np.ndarray, clamp: bool) -> np.ndarray | None:
    """(V,) a Math node's output over factor tables (or constants) a and b; None for an
    operation this reader does not follow."""
    a, b = np.broadcast_arrays(np.asarray(a, np.float64), np.asarray(b, np.float64))
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        if operation == "ADD":
            out = a + b
        elif operation == "SUBTRACT":
            out = a - b
        elif operation == "MULTIPLY":
            out = a * b
        elif operation == "DIVIDE":
            out = np.where(b != 0.0, a / np.where(b != 0.0, b, 1.0), 0.0)
        elif operation == "POWER":
            out = np.where((a >= 0.0) | (b == np.round(b)), np.power(a, b), 0.0)
        elif operation == "MINIMUM":
            out = np.minimum(a, b)
        elif operation == "MAXIMUM":
            out = np.maximum(a, b)
        else:
            return None
    out = np.nan_to_num(out, nan=0.0, posinf=0.0, neginf=0.0)
    return np.clip(out, 0.0, 1.0) if clamp else out


def ramp_factor(fac: np.ndarray, positions, colours, interpolation: str) -> np.ndarray | None:
    """(V, 4) a Color Ramp's RGBA over a factor table: linear between its stops or constant
    (the stop at or below), the factor clamped to 0..1; None for its other interpolations."""
    positions = np.asarray(positions, np.float64)
    colours = np.asarray(colours, np.float64).reshape(-1, 4)
    order = np.argsort(positions, kind="stable")
    positions, colours = positions[order], colours[order]
    f = np.clip(np.asarray(fac, np.float64), 0.0, 1.0)
    if interpolation == "LINEAR":
        return np.stack([np.interp(f, positions, colours[:, c]) for c in range(4)], axis=-1)
    if interpolation == "CONSTANT":
        return colours[np.clip(np.searchsorted(positions, f, side="right") - 1, 0, len(positions) - 1)]
    return None

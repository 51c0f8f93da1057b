"""The Principled BSDF's dielectric specular layer as Cycles 4.x/5.x layers it over the diffuse base.

Cycles (svm/closure.h, CLOSURE_BSDF_PRINCIPLED_ID) allocates the specular GGX closure first and
weights every closure below it by `closure_layering_weight`: 1 - max over channels of the layer's
directional albedo at the view angle. That albedo (closure/bsdf_microfacet.h,
`bsdf_microfacet_estimate_albedo` times the multiscatter darkening of
`microfacet_ggx_preserve_energy`) is

    albedo(mu) = (E + Fms (1 - E)) * mix(f0, 1, s(rough, mu, z))

with E(rough, mu) the single-scattering albedo of GGX without Fresnel, E_avg its cosine-weighted
mean, s the remapped dielectric Fresnel (F - F0) / (1 - F0) averaged over the visible normals as
Cycles' precompute averages it (plain mean, a normal reflecting below the horizon counting 0;
the masking-weighted mean made Glossy Color 3% low: 0.037 -> 0.009 L1 on a test scene), Fss the
average Fresnel and Fms = Fss E_avg / (1 - Fss (1 - E_avg)) (Kulla & Conty 2017). So the Diffuse
Color pass of a Principled BSDF is base x (1 - metallic)(1 - transmission)(1 - albedo(mu)): at
the default IOR 1.5, roughness 0.5, a few percent facing the camera and far more at grazing
angles.

The tables are computed here by deterministic quadrature (a midpoint grid over the two random
numbers of visible-normal sampling, so sharp lobes are integrated as well as rough ones) on the
grids of Cycles' own tables: rough = i / (n - 1), mu = j / (n - 1), and z = F0^(1/4) for the IOR.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import lru_cache
from pathlib import Path

import numpy as np

from . import shipped

#: Grid sizes: (rough, mu) of the GGX albedo, (z, rough, mu) of the Fresnel average (Cycles: 32, 16).
E_SIZE = 32
S_SIZE = 16
#: Quadrature points per table entry: a midpoint grid over the two numbers of VNDF sampling.
_QUAD_U = 48
_QUAD_PHI = 48
#: Cosines at which a material's diffuse weight is tabulated for the G-buffer (0..1, inclusive).
WEIGHT_SAMPLES = 32


def f0_from_ior(ior):
    """Normal-incidence reflectance of a dielectric interface of relative IOR `ior`."""
    ior = np.asarray(ior, np.float64)
    return ((ior - 1.0) / (ior + 1.0)) ** 2


def ior_from_f0(f0):
    """Inverse of `f0_from_ior` (for f0 < 1)."""
    r = np.sqrt(np.clip(np.asarray(f0, np.float64), 0.0, 0.99999))
    return (1.0 + r) / (1.0 - r)


def fresnel_dielectric(cos_i, eta):
    """Unpolarised Fresnel reflectance of a dielectric (Cycles' fresnel_dielectric_cos)."""
    c = np.abs(np.asarray(cos_i, np.float64))
    g2 = eta * eta - 1.0 + c * c
    g = np.sqrt(np.maximum(g2, 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        a = (g - c) / (g + c)
        b = (c * (g + c) - 1.0) / (c * (g - c) + 1.0)
        f = 0.5 * a * a * (1.0 + b * b)
    return np.where(g2 > 0.0, np.nan_to_num(f, nan=1.0), 1.0)


def fresnel_dielectric_fss(eta: float) -> float:
    """Cosine-weighted mean of the dielectric Fresnel (Kulla & Conty's fit, as Cycles uses it)."""
    if eta < 1.0:
        return 0.997118 + eta * (0.1014 - eta * (0.965241 + eta * 0.130607))
    return (eta - 1.0) / (4.08567 + 1.00071 * eta)


def _lambda(alpha2, cos_n):
    """Smith Lambda of GGX."""
    cos2 = np.maximum(cos_n * cos_n, 1e-30)
    return 0.5 * (np.sqrt(1.0 + alpha2 * np.maximum(1.0 / cos2 - 1.0, 0.0)) - 1.0)


def _lobe_samples(rough, mu):
    """(weights, cos(h, i)) of the GGX reflection lobe (F = 1) seen from cos theta = mu, for K
    (rough, mu) pairs at once ((K, N) arrays; scalars give (N,)): the weights sum to the lobe's
    directional albedo E, so sum(w F(cos_hi)) is the albedo with Fresnel F.

    Half vectors are the visible normals of Heitz (JCGT 2018) at a midpoint grid of its two
    random numbers; each weighs G2 / G1(i), which falls to 0 as the reflection reaches the
    horizon, so the integrand is continuous and the grid converges fast at every roughness."""
    scalar = np.ndim(rough) == 0 and np.ndim(mu) == 0
    rough, mu = np.broadcast_arrays(np.atleast_1d(np.asarray(rough, np.float64)), np.atleast_1d(np.asarray(mu, np.float64)))
    alpha = (np.maximum(rough, 1e-4) ** 2)[:, None, None]
    alpha2 = alpha * alpha
    mu = np.clip(mu, 1e-4, 1.0)[:, None, None]
    sin_i = np.sqrt(1.0 - mu * mu)
    # The view stretched by the roughness; its tangent frame: t1 = y, t2 = vh x y.
    length = np.sqrt((alpha * sin_i) ** 2 + mu * mu)
    vx, vz = alpha * sin_i / length, mu / length
    u1 = (np.arange(_QUAD_U) + 0.5) / _QUAD_U
    # The lobe is mirror-symmetric about the plane of incidence (t1 <-> -t1, phi <-> pi - phi):
    # the half of the midpoints with t1 <= 0, each counted twice.
    u2 = (np.arange(_QUAD_PHI // 4, 3 * _QUAD_PHI // 4) + 0.5) / _QUAD_PHI
    r = np.sqrt(u1)[None, :, None]
    phi = 2.0 * np.pi * u2[None, None, :]
    t1 = r * np.cos(phi)
    t2 = r * np.sin(phi)
    s = 0.5 * (1.0 + vz)
    t2 = (1.0 - s) * np.sqrt(np.maximum(1.0 - t1 * t1, 0.0)) + s * t2
    tn = np.sqrt(np.maximum(1.0 - t1 * t1 - t2 * t2, 0.0))
    # nh = t1 (0, 1, 0) + t2 (-vz, 0, vx) + tn (vx, 0, vz), then unstretched.
    hx = alpha * (-t2 * vz + tn * vx)
    hy = alpha * t1
    hz = np.maximum(t2 * vx + tn * vz, 0.0)
    inv = 1.0 / np.sqrt(hx * hx + hy * hy + hz * hz)
    hx, hz = hx * inv, hz * inv
    cos_hi = hx * sin_i + hz * mu
    mu_o = 2.0 * cos_hi * hz - mu
    ok = (cos_hi > 0) & (mu_o > 0)
    lam_i = _lambda(alpha2, mu)
    g2 = 1.0 / (1.0 + lam_i + _lambda(alpha2, np.where(ok, mu_o, 1.0)))
    w = np.where(ok, g2 * (1.0 + lam_i), 0.0) * (2.0 / (_QUAD_U * _QUAD_PHI))
    w, cos_hi = w.reshape(w.shape[0], -1), np.where(ok, cos_hi, 1.0).reshape(w.shape[0], -1)
    return (w[0], cos_hi[0]) if scalar else (w, cos_hi)


def _grid(n: int) -> np.ndarray:
    return np.arange(n) / (n - 1)


#: The tables as `compute_tables` makes them, shipped so that a render does not spend ~0.6 s of a
#: core on quadrature in every process (a one-frame headless render pays it each time). Rebuild
#: with `python -m hybridgi_core.specular`; tests/test_specular checks that it matches.
TABLES_FILE = Path(__file__).with_name("specular_tables.npz")
#: What the shipped file was computed from: a file of other sizes is ignored (then computed here).
TABLES_KEY = np.array([E_SIZE, S_SIZE, _QUAD_U, _QUAD_PHI])


def _shipped(*names: str) -> tuple | None:
    """The arrays `names` of `TABLES_FILE` when it was made for these grid sizes, else None."""
    return shipped.load(TABLES_FILE, TABLES_KEY, *names)


@lru_cache(maxsize=1)
def tables():
    """(E (rough, mu), E_avg (rough,), s (z, rough, mu)) float64: the shipped `TABLES_FILE` when
    it was made for these grid sizes, else `compute_tables()`; once per process."""
    return _shipped("e", "e_avg", "s") or compute_tables()


def write_tables(path: Path = TABLES_FILE) -> None:
    """Write `compute_tables()` and `compute_schlick_table()` to `path` (the shipped file), keyed
    by the grid sizes."""
    e, e_avg, s = compute_tables()
    shipped.write(path, TABLES_KEY, e=e, e_avg=e_avg, s=s, s5=compute_schlick_table())


def compute_tables():
    """(E (rough, mu), E_avg (rough,), s (z, rough, mu)) float64 by quadrature (~0.6 s)."""
    r, mu = np.meshgrid(_grid(E_SIZE), _grid(E_SIZE), indexing="ij")
    e = _lobe_samples(r.ravel(), mu.ravel())[0].sum(axis=1).reshape(E_SIZE, E_SIZE)
    # E_avg = 2 int E(mu) mu dmu, trapezoids over the table's own cosines.
    mus = _grid(E_SIZE)
    f = 2.0 * e * mus[None, :]
    e_avg = ((f[:, 1:] + f[:, :-1]) * 0.5 * np.diff(mus)[None, :]).sum(axis=1)
    z = np.clip(_grid(S_SIZE), 1e-4, 0.99)
    iors = ior_from_f0(z**4)
    f0 = f0_from_ior(iors)
    r, mu = np.meshgrid(_grid(S_SIZE), _grid(S_SIZE), indexing="ij")
    w, cos_hi = _lobe_samples(r.ravel(), mu.ravel())
    # As Cycles' precompute: the plain mean over visible-normal samples of the remapped Fresnel,
    # a sample reflected below the horizon counting 0 (not weighted by its masking).
    valid = (w > 0) / w.shape[1]
    s = np.zeros((S_SIZE, S_SIZE * S_SIZE))
    for k in range(S_SIZE):
        remap = np.clip((fresnel_dielectric(cos_hi, iors[k]) - f0[k]) / (1.0 - f0[k]), 0.0, 1.0)
        s[k] = (valid * remap).sum(axis=1)
    return np.clip(e, 0.0, 1.0), np.clip(e_avg, 0.0, 1.0), np.clip(s.reshape(S_SIZE, S_SIZE, S_SIZE), 0.0, 1.0)


@lru_cache(maxsize=1)
def schlick_table() -> np.ndarray:
    """(rough, mu) visible-normal mean of (1 - cos(h, i))^5, Cycles' ggx_gen_schlick_s at exponent
    5: the metallic lobe's albedo is mix(F0, 1, this) (F82 tint's extra term ignored, as Cycles does).
    The shipped `TABLES_FILE`'s when it has it (a metal's first render computed it: 20 ms), else
    `compute_schlick_table()`; once per process."""
    table = _shipped("s5")
    return table[0] if table is not None else compute_schlick_table()


def compute_schlick_table() -> np.ndarray:
    """`schlick_table` by quadrature."""
    r, mu = np.meshgrid(_grid(S_SIZE), _grid(S_SIZE), indexing="ij")
    w, cos_hi = _lobe_samples(r.ravel(), mu.ravel())
    s5 = ((w > 0) * (1.0 - cos_hi) ** 5).sum(axis=1) / w.shape[1]  # as the Fresnel table above
    return np.clip(s5.reshape(S_SIZE, S_SIZE), 0.0, 1.0)


def multiscatter_factor(fss, e, e_avg):
    """Kulla & Conty's multiple-scattering factor as Cycles' microfacet_ggx_preserve_energy
    applies it to a lobe of single-scattering albedo e: the BRDF's 1 + Fms (1 - E) / E and its
    albedo's E + Fms (1 - E) are this factor times the single-scattering ones."""
    fms = fss * e_avg / (1.0 - fss * (1.0 - e_avg))
    return 1.0 + fms * (1.0 - e) / np.maximum(e, 1e-6)


def metal_albedo(layer: SpecularLayer, mu) -> np.ndarray:
    """(..., 3) directional albedo of the metallic lobe (F82 with a white tint: Schlick on F0 =
    the base colour), not times its weight."""
    mu = np.clip(np.asarray(mu, np.float64), 0.0, 1.0)
    f0 = layer.metal_color.astype(np.float64)
    s5 = _lerp_table(schlick_table(), [layer.roughness, mu])[..., None]
    albedo = f0 + (1.0 - f0) * s5
    if layer.multiscatter:
        e_table, e_avg_table, _ = tables()
        e = _lerp_table(e_table, [layer.roughness, mu])[..., None]
        e_avg = float(_lerp_table(e_avg_table, [layer.roughness]))
        albedo = albedo * e * multiscatter_factor(f0 + (1.0 - f0) / 21.0, e, e_avg)
    return albedo


def glossy_color(layer, mu) -> np.ndarray:
    """(..., 3) Cycles' Glossy Color at cosines mu: the glossy closures' albedos times their
    weights (a `SpecularLayer`'s dielectric layer and metallic lobe, a `GlossySurface`'s lobes)."""
    return lobes_color(surface_lobes(layer), mu)


def lobes_color(lobes, mu) -> np.ndarray:
    """(..., 3) the Glossy Color at cosines mu of these lobes: the sum of their `lobe_color`s."""
    mu = np.asarray(mu, np.float64)
    out = np.zeros((*mu.shape, 3))
    for lobe in lobes:
        out = out + lobe_color(lobe, mu)
    return out


def _lerp_table(table: np.ndarray, coords: list) -> np.ndarray:
    """Multilinear lookup of a table over [0, 1]^d (coordinates clamped, as Cycles' lookup_table_read)."""
    coords = [np.clip(np.asarray(c, np.float64), 0.0, 1.0) for c in coords]
    shape = np.broadcast_shapes(*(c.shape for c in coords))
    coords = [np.broadcast_to(c, shape) for c in coords]
    out = np.zeros(shape)
    lo, frac = [], []
    for axis, c in enumerate(coords):
        x = c * (table.shape[axis] - 1)
        i0 = np.minimum(np.floor(x).astype(np.int64), table.shape[axis] - 2)
        lo.append(i0)
        frac.append(x - i0)
    for corner in range(1 << len(coords)):
        idx, weight = [], np.ones(shape)
        for axis in range(len(coords)):
            bit = (corner >> axis) & 1
            idx.append(lo[axis] + bit)
            weight = weight * (frac[axis] if bit else 1.0 - frac[axis])
        out += weight * table[tuple(idx)]
    return out


@dataclass
class SpecularLayer:
    """A Principled BSDF's dielectric specular layer (its inputs as Blender names them).

    roughness : 0..1 (alpha = roughness^2); ior : the IOR input; level : Specular IOR Level
    (0.5 keeps the IOR's own F0, 0 switches the layer off); tint : (3,) Specular Tint;
    multiscatter : the node's distribution is Multiscatter GGX (Cycles' default), whose energy
    compensation darkens the layer by E + Fms (1 - E).
    weight : the layer's share of the surface, (1 - metallic)(1 - transmission) as Cycles weights
    it; metallic, metal_color : the metallic lobe's weight and F0 (the clamped base colour);
    transmission : the Transmission Weight, whose glass closure (weight transmission x
    (1 - metallic)) reflects with the real Fresnel of the IOR (not level-adjusted) and the tint.
    coat, coat_roughness, coat_ior, coat_tint : the Coat layer over all of it (car paint,
    varnish): a GGX lobe of weight `coat` with the dielectric Fresnel of `coat_ior` (Cycles'
    coat closure), the layers under it weighted 1 - coat x max(its albedo) at the view angle
    (closure_layering_weight) and tinted 1 + coat (tint - 1) (Cycles' absorption at normal
    incidence; the diffuse base's tint is in the material's colour).
    """

    roughness: float = 0.5
    ior: float = 1.5
    level: float = 0.5
    tint: np.ndarray = field(default_factory=lambda: np.ones(3, np.float32))
    multiscatter: bool = True
    weight: float = 1.0
    metallic: float = 0.0
    metal_color: np.ndarray = field(default_factory=lambda: np.zeros(3, np.float32))
    transmission: float = 0.0
    coat: float = 0.0
    coat_roughness: float = 0.03
    coat_ior: float = 1.5
    coat_tint: np.ndarray = field(default_factory=lambda: np.ones(3, np.float32))

    def __post_init__(self) -> None:
        def finite(value, default, lo, hi):
            value = float(value)
            return float(np.clip(value, lo, hi)) if np.isfinite(value) else default

        self.roughness = finite(self.roughness, 0.5, 0.0, 1.0)
        self.ior = finite(self.ior, 1.5, 1e-5, 1e6)
        self.level = finite(self.level, 0.5, 0.0, 1e6)
        tint = np.asarray(self.tint, np.float32).reshape(-1)[:3]
        self.tint = np.where(np.isfinite(tint), np.maximum(tint, 0.0), 1.0).astype(np.float32)
        self.weight = finite(self.weight, 1.0, 0.0, 1.0)
        self.metallic = finite(self.metallic, 0.0, 0.0, 1.0)
        metal = np.asarray(self.metal_color, np.float32).reshape(-1)[:3]
        self.metal_color = np.clip(np.where(np.isfinite(metal), metal, 0.0), 0.0, 1.0).astype(np.float32)
        self.transmission = finite(self.transmission, 0.0, 0.0, 1.0)
        self.coat = finite(self.coat, 0.0, 0.0, 1.0)
        self.coat_roughness = finite(self.coat_roughness, 0.03, 0.0, 1.0)
        self.coat_ior = finite(self.coat_ior, 1.5, 1.0, 1e6)
        coat_tint = np.asarray(self.coat_tint, np.float32).reshape(-1)[:3]
        self.coat_tint = np.where(np.isfinite(coat_tint), np.clip(coat_tint, 0.0, 1.0), 1.0).astype(np.float32)

    @property
    def eta(self) -> float:
        """The IOR the layer's Fresnel uses: Specular IOR Level scales F0 (Cycles' IOR adjustment)."""
        ior = self.ior
        if self.level == 0.5:
            return ior
        eta = float(ior_from_f0(f0_from_ior(ior) * 2.0 * self.level))
        return 1.0 / eta if ior < 1.0 else eta

    @property
    def f0(self) -> np.ndarray:
        """(3,) reflectance at normal incidence, tinted and clamped as Cycles' setup does."""
        return np.clip(float(f0_from_ior(self.eta)) * self.tint.astype(np.float64), 0.0, 1.0)

    @property
    def active(self) -> bool:
        """Cycles allocates no specular closure when the adjusted IOR is 1."""
        return self.eta != 1.0 and bool(np.any(self.f0 > 0.0))

    def key(self) -> bytes:
        return np.array([self.roughness, self.ior, self.level, *self.tint, self.multiscatter, self.weight,
                         self.metallic, *self.metal_color, self.transmission, self.coat, self.coat_roughness,
                         self.coat_ior, *self.coat_tint], np.float64).tobytes()

    @property
    def coated(self) -> bool:
        """Whether a coat lies over the layer (a weight and an IOR other than 1)."""
        return self.coat > 0.0 and self.coat_ior != 1.0

    def coat_layer(self) -> SpecularLayer:
        """The coat as a bare dielectric layer (GGX, no multiscatter): its albedo weighs the rest."""
        return SpecularLayer(roughness=self.coat_roughness, ior=self.coat_ior, multiscatter=False)

    def coat_factor(self, mu) -> np.ndarray:
        """(...) the weight of what lies under the coat at cosines mu: 1 - coat x max(its albedo)
        (1 without a coat)."""
        mu = np.asarray(mu, np.float64)
        if not self.coated:
            return np.ones(mu.shape)
        return np.clip(1.0 - self.coat * layer_albedo(self.coat_layer(), mu).max(axis=-1), 0.0, 1.0)


def layer_albedo(layer: SpecularLayer, mu) -> np.ndarray:
    """(..., 3) directional albedo of the layer (what Cycles' layering subtracts) at cosines mu."""
    mu = np.clip(np.asarray(mu, np.float64), 0.0, 1.0)
    if not layer.active:
        return np.zeros((*mu.shape, 3))
    e_table, e_avg_table, s_table = tables()
    eta = layer.eta
    eta_up = 1.0 / eta if eta < 1.0 else eta
    z = np.sqrt(abs(eta_up - 1.0) / (eta_up + 1.0))
    rough = layer.roughness
    s = _lerp_table(s_table, [z, rough, mu])
    f0 = layer.f0
    albedo = f0 + (1.0 - f0) * s[..., None]
    if layer.multiscatter:
        e = _lerp_table(e_table, [rough, mu])[..., None]
        e_avg = float(_lerp_table(e_avg_table, [rough]))
        f0_real = float(f0_from_ior(eta))
        s_avg = float(np.clip((fresnel_dielectric_fss(eta) - f0_real) / max(1.0 - f0_real, 1e-12), 0.0, 1.0))
        fss = f0 + (1.0 - f0) * s_avg
        albedo = albedo * e * multiscatter_factor(fss, e, e_avg)
    return albedo


def diffuse_weight(layer, mu) -> np.ndarray:
    """(...) weight of the diffuse base under the layer at cosines mu: Cycles'
    closure_layering_weight, 1 - max over channels of the layer's albedo (1 without a layer);
    a `GlossySurface`'s own table of it."""
    mu = np.asarray(mu, np.float64)
    if isinstance(layer, GlossySurface):
        return np.ones(mu.shape) if layer.diffuse is None else sample_view(layer.diffuse, mu)
    if layer is None:
        return np.ones(mu.shape)
    coat = layer.coat_factor(mu)
    if not layer.active:
        return coat
    return coat * np.clip(1.0 - layer_albedo(layer, mu).max(axis=-1), 0.0, 1.0)


def diffuse_weight_row(layer, n: int = WEIGHT_SAMPLES) -> np.ndarray:
    """(n,) float32 diffuse weight at cosines i / (n - 1): one row of the G-buffer's table."""
    return diffuse_weight(layer, _grid(n)).astype(np.float32)


#: Cycles' Filter Glossy (`cycles.blur_glossy`, its default): the setting the hits' lobes are blurred by.
FILTER_GLOSSY = 1.0


def hit_blur_roughness(filter_glossy: float = FILTER_GLOSSY, n: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """((n,) roughness, (n,) weight) of Cycles' Filter Glossy at a ray hit after a diffuse bounce.

    Cycles (surface_shader_prepare_closures) blurs every BSDF of a hit whose path's smallest pdf
    so far (`min_ray_pdf`), divided by Filter Glossy, is below 1: alpha = max(alpha, 0.5 sqrt(1 -
    pdf / filter)), after the closures' setup, so the specular layer keeps the diffuse weight and
    the multiscatter compensation of its own roughness and loses what the rougher lobe no longer
    reflects. After a diffuse bounce the pdf is cos / pi (cosine-weighted: density 2 cos), so
    the blurred roughness spans sqrt(0.41)..sqrt(0.5) = 0.64..0.71 at the default 1; 0 = off."""
    if not filter_glossy > 0.0:
        return np.zeros(1), np.ones(1)
    c = (np.arange(n) + 0.5) / n
    pdf = c / (np.pi * filter_glossy)
    alpha = np.where(pdf < 1.0, 0.5 * np.sqrt(np.clip(1.0 - pdf, 0.0, 1.0)), 0.0)
    weight = 2.0 * c / n
    return np.sqrt(alpha), weight / weight.sum()


def _hit_lobe_albedo(lobe: GlossyLobe, mu, rough_blur) -> np.ndarray:
    """(..., 3) the energy a lobe blurred to roughness max(its own, rough_blur) reflects at cosines
    mu (broadcast with rough_blur), before its weight and view factor: its Fresnel average and GGX
    albedo at the blurred roughness, the multiscatter factor of its own (set up before the blur).
    Where the blur does not reach the lobe's roughness, `lobe_albedo`."""
    mu = np.clip(np.asarray(mu, np.float64), 0.0, 1.0)
    rough = lobe.roughness
    rb = np.maximum(np.asarray(rough_blur, np.float64), rough)
    mu, rb = np.broadcast_arrays(mu, rb)
    if lobe.fresnel == "none":
        fresnel = np.ones((*mu.shape, 3))
    elif lobe.fresnel == "dielectric":
        eta = lobe.eta
        z = np.sqrt(abs(eta - 1.0) / (eta + 1.0))
        fresnel = lobe.f0 + (1.0 - lobe.f0) * _lerp_table(tables()[2], [z, rb, mu])[..., None]
    elif lobe.fresnel == "f82":
        fresnel = lobe.f0 + (1.0 - lobe.f0) * _lerp_table(schlick_table(), [rb, mu])[..., None]
    else:
        fresnel = fresnel_conductor(mu, lobe.n, lobe.k)
    e_table, e_avg_table, _ = tables()
    e = _lerp_table(e_table, [rough, mu])[..., None]
    loss = _lerp_table(e_table, [rb, mu])[..., None] / np.maximum(e, 1e-6)  # 1 where unblurred
    if lobe.distribution == "MULTI_GGX":
        e_avg = float(_lerp_table(e_avg_table, [rough]))
        return fresnel * e * multiscatter_factor(lobe.average_fresnel(), e, e_avg) * loss
    return fresnel * loss  # the model's single-scattering lobe (`lobe_albedo`), darkened by the blur


def _hit_lobe_mean(lobe: GlossyLobe, filter_glossy: float) -> np.ndarray:
    """(3,) cosine-weighted mean over the view of a lobe's colour at a hit (`_hit_lobe_albedo`),
    averaged over the blurs of `hit_blur_roughness`."""
    mu = (np.arange(64) + 0.5) / 64
    view = 1.0 if lobe.view is None else sample_view(lobe.view, mu)[:, None]
    rough_blur, w = hit_blur_roughness(filter_glossy)
    albedo = _hit_lobe_albedo(lobe, mu[None, :], rough_blur[:, None])  # (blur, mu, 3)
    per_blur = np.mean(2.0 * view * albedo * mu[:, None], axis=1)
    return lobe.weight * (w[:, None] * per_blur).sum(axis=0)


def hemispherical_glossy_albedo(layer, filter_glossy: float = FILTER_GLOSSY) -> np.ndarray:
    """(3,) cosine-weighted mean albedo of the glossy lobes at a ray hit: the dielectric layer's
    (times its weight) and the metallic lobe's (its average Fresnel, F0 + (1 - F0) / 21, times its
    weight), each as Cycles' Filter Glossy blurs it at a hit after a diffuse bounce
    (`hit_blur_roughness`; filter_glossy 0: unblurred). Probe-ray hits reflect this share of their
    light as if it were diffuse: a cache of irradiance cannot hold the lobe's direction, but
    Cycles' bounce light carries its energy."""
    if layer is None:
        return np.zeros(3, np.float32)
    if isinstance(layer, GlossySurface):
        return sum((_hit_lobe_mean(lobe, filter_glossy) for lobe in layer.lobes), np.zeros(3)).astype(np.float32)
    out = np.zeros(3)
    for lobe in layer_lobes(layer):
        if lobe.fresnel == "f82":
            # The metal's average Fresnel, less what the blur takes (the lobe's own mean, blurred / not).
            sharp = _hit_lobe_mean(lobe, 0.0)
            blur = _hit_lobe_mean(lobe, filter_glossy)
            ratio = np.where(sharp > 0, blur / np.maximum(sharp, 1e-12), 1.0)
            out += layer.metallic * (layer.metal_color + (1.0 - layer.metal_color) / 21.0) * ratio
        else:
            out += _hit_lobe_mean(lobe, filter_glossy)
    return out.astype(np.float32)


def hemispherical_diffuse_weight(layer) -> float:
    """Cosine-weighted mean of the diffuse weight over the hemisphere, 2 int w(mu) mu dmu: what
    a probe-ray hit, seen from every direction at once, reflects of its diffuse base."""
    if layer is None or (not isinstance(layer, GlossySurface) and not layer.active and not layer.coated):
        return 1.0
    mu = (np.arange(64) + 0.5) / 64
    return float(np.mean(2.0 * diffuse_weight(layer, mu) * mu))


# --- glossy closures of any shader node ---------------------------------------------------------

#: Cosines at which a lobe's view-dependent factor (a Mix Shader's Fresnel / Layer Weight Fac) and a
#: `GlossySurface`'s diffuse weight are tabulated (0..1, inclusive; finer than the G-buffer's row:
#: the Fresnel factor is steep at grazing angles).
VIEW_SAMPLES = 64
DISTRIBUTIONS = ("GGX", "MULTI_GGX", "BECKMANN")
FRESNELS = ("none", "dielectric", "f82", "conductor")


def view_grid(n: int = VIEW_SAMPLES) -> np.ndarray:
    """(n,) the cosines i / (n - 1) the view-dependent tables are sampled at."""
    return _grid(n)


def sample_view(table, mu) -> np.ndarray:
    """A (n,) table over the view cosine (`view_grid`) linearly interpolated at cosines mu."""
    table = np.asarray(table, np.float64)
    return np.interp(np.clip(np.asarray(mu, np.float64), 0.0, 1.0), _grid(table.shape[0]), table)


def fresnel_conductor(cos_i, n, k) -> np.ndarray:
    """(..., 3) unpolarised reflectance of a conductor of complex IOR n + ik (Cycles' fresnel_conductor)."""
    c = np.clip(np.asarray(cos_i, np.float64), 0.0, 1.0)[..., None]
    n, k = np.asarray(n, np.float64), np.asarray(k, np.float64)
    t1 = n * n - k * k - (1.0 - c * c)
    t2 = np.sqrt(t1 * t1 + (2.0 * n * k) ** 2)
    u2, v2 = np.maximum(0.5 * (t2 + t1), 0.0), np.maximum(0.5 * (t2 - t1), 0.0)
    u, v = np.sqrt(u2), np.sqrt(v2)
    with np.errstate(divide="ignore", invalid="ignore"):
        rs = np.nan_to_num(((c - u) ** 2 + v2) / ((c + u) ** 2 + v2))
        t3, t4 = (n * n - k * k) * c, 2.0 * n * k * c
        rp = np.nan_to_num(((t3 - u) ** 2 + (t4 - v) ** 2) / ((t3 + u) ** 2 + (t4 + v) ** 2))
    return 0.5 * (rs + rp)


_F82_F = 6.0 / 7.0
_F82_F5 = _F82_F**5


def f82_b_from_tint(f0, tint) -> np.ndarray:
    """Cycles' fresnel_f82tint_B: the B that makes the F82 model Schlick x tint at cos = 1/7."""
    f0 = np.asarray(f0, np.float64)
    return (f0 + (1.0 - f0) * _F82_F5) * (7.0 / (_F82_F5 * _F82_F)) * (1.0 - np.asarray(tint, np.float64))


def f82_b_from_value(f0, f82) -> np.ndarray:
    """Cycles' fresnel_f82_B: the B that makes the F82 model equal f82 at cos = 1/7."""
    f0 = np.asarray(f0, np.float64)
    return (7.0 / (_F82_F5 * _F82_F)) * (f0 + (1.0 - f0) * _F82_F5 - np.asarray(f82, np.float64))


@dataclass
class GlossyLobe:
    """One glossy closure as Cycles sets it up (svm/closure.h): its BRDF is
    weight x view(mu) x F(cos(h, i)) x the microfacet lobe (x the multiscatter factor of
    Multiscatter GGX), its Glossy Color weight x view(mu) x Cycles' albedo estimate.

    weight : (3,) the closure weight: a Glossy BSDF's colour, a Glass BSDF's reflection tint, a
        Principled lobe's share, times the constant factors of the Mix / Add Shaders above it
    roughness : 0..1 (alpha = roughness^2); distribution : one of DISTRIBUTIONS
    fresnel : 'none' (F = 1: Glossy BSDF), 'dielectric' (the real Fresnel of `ior` remapped from
        its own F0..1 to f0..1: Principled specular, Glass), 'f82' (Schlick on f0 less
        b cos (1 - cos)^6: Principled metallic, Metallic BSDF's F82), 'conductor' (n + ik:
        the Metallic BSDF's Physical Conductor; its BRDF uses the F82 model fitted at 0 and 82
        degrees, as Cycles fits it for the conductor's average Fresnel, its Glossy Color the
        exact Fresnel at the view angle, as Cycles estimates it)
    ior, f0, b, n, k : the Fresnel's parameters (f0, b, n, k (3,))
    fss : (3,) average Fresnel of Multiscatter GGX's darkening, or None for the model's own (a
        Glossy BSDF's is its colour: Cycles' bsdf_microfacet_setup_fresnel_constant)
    view : (VIEW_SAMPLES,) factor over the view cosine (`view_grid`) or None (1): the Fac of a
        Mix Shader read from a Fresnel or Layer Weight node
    """

    weight: np.ndarray = field(default_factory=lambda: np.ones(3))
    roughness: float = 0.5
    distribution: str = "MULTI_GGX"
    fresnel: str = "none"
    ior: float = 1.5
    f0: np.ndarray = field(default_factory=lambda: np.zeros(3))
    b: np.ndarray = field(default_factory=lambda: np.zeros(3))
    n: np.ndarray = field(default_factory=lambda: np.ones(3))
    k: np.ndarray = field(default_factory=lambda: np.zeros(3))
    fss: np.ndarray | None = None
    view: np.ndarray | None = None

    def __post_init__(self) -> None:
        def colour(value, default, lo=0.0, hi=np.inf):
            c = np.broadcast_to(np.asarray(value, np.float64).reshape(-1)[:3], (3,))
            return np.clip(np.where(np.isfinite(c), c, default), lo, hi)

        self.weight = colour(self.weight, 0.0)
        rough = float(self.roughness)
        self.roughness = float(np.clip(rough, 0.0, 1.0)) if np.isfinite(rough) else 0.5
        if self.distribution not in DISTRIBUTIONS:
            self.distribution = "GGX"
        if self.fresnel not in FRESNELS:
            raise ValueError(f"unknown Fresnel mode {self.fresnel!r}")
        ior = float(self.ior)
        self.ior = float(np.clip(ior, 1e-5, 1e6)) if np.isfinite(ior) else 1.5
        self.f0 = colour(self.f0, 0.0, 0.0, 1.0)
        self.b = colour(self.b, 0.0, -np.inf)
        self.n, self.k = colour(self.n, 1.0), colour(self.k, 0.0)
        if self.fresnel == "conductor":
            # The F82 model through the conductor's values at 0 and ~82 degrees (Cycles' fit).
            self.f0 = fresnel_conductor(1.0, self.n, self.k)
            self.b = f82_b_from_value(self.f0, fresnel_conductor(1.0 / 7.0, self.n, self.k))
        if self.fss is not None:
            self.fss = colour(self.fss, 1.0, 0.0, 1.0)
        if self.view is not None:
            view = np.asarray(self.view, np.float64).reshape(-1)
            self.view = np.clip(np.where(np.isfinite(view), view, 0.0), 0.0, None)

    @property
    def eta(self) -> float:
        """The dielectric IOR above 1 (a relative IOR below 1 reflects as its inverse)."""
        return 1.0 / self.ior if self.ior < 1.0 else self.ior

    @property
    def active(self) -> bool:
        if not np.any(self.weight > 0) or (self.view is not None and not np.any(self.view > 0)):
            return False
        return not (self.fresnel == "dielectric" and self.ior == 1.0)

    def coefficients(self) -> np.ndarray:
        """(4, 3) the Fresnel as k0 + k1 remap(cos) + k2 (1 - cos)^5 + k3 cos (1 - cos)^6, remap
        the real dielectric Fresnel of `eta` mapped from its F0..1 to 0..1."""
        k = np.zeros((4, 3))
        if self.fresnel == "none":
            k[0] = 1.0
        elif self.fresnel == "dielectric":
            k[0], k[1] = self.f0, 1.0 - self.f0
        else:
            k[0], k[2], k[3] = self.f0, 1.0 - self.f0, -self.b
        return k

    def average_fresnel(self) -> np.ndarray:
        """(3,) Fss of Multiscatter GGX's darkening, as Cycles computes it for each model."""
        if self.fss is not None:
            return self.fss
        if self.fresnel == "none":
            return np.ones(3)
        if self.fresnel == "dielectric":
            f0_real = float(f0_from_ior(self.ior))
            s = float(np.clip((fresnel_dielectric_fss(self.ior) - f0_real) / max(1.0 - f0_real, 1e-12), 0.0, 1.0))
            return self.f0 + (1.0 - self.f0) * s
        return np.clip(self.f0 + (1.0 - self.f0) / 21.0 - self.b / 126.0, 0.0, 1.0)

    def key(self) -> bytes:
        parts = [self.weight, [self.roughness, DISTRIBUTIONS.index(self.distribution), FRESNELS.index(self.fresnel),
                               self.ior], self.f0, self.b, self.n, self.k,
                 self.fss if self.fss is not None else [-1.0], self.view if self.view is not None else [-1.0]]
        return np.concatenate([np.asarray(p, np.float64).reshape(-1) for p in parts]).tobytes()


def lobe_albedo(lobe: GlossyLobe, mu) -> np.ndarray:
    """(..., 3) Cycles' albedo estimate of a lobe at cosines mu (bsdf_microfacet_estimate_albedo
    times Multiscatter GGX's darkening E + Fms (1 - E)), before its weight and view factor."""
    mu = np.clip(np.asarray(mu, np.float64), 0.0, 1.0)
    rough = lobe.roughness
    if lobe.fresnel == "none":
        albedo = np.ones((*mu.shape, 3))
    elif lobe.fresnel == "dielectric":
        eta = lobe.eta
        z = np.sqrt(abs(eta - 1.0) / (eta + 1.0))
        s = _lerp_table(tables()[2], [z, rough, mu])[..., None]
        albedo = lobe.f0 + (1.0 - lobe.f0) * s
    elif lobe.fresnel == "f82":
        albedo = lobe.f0 + (1.0 - lobe.f0) * _lerp_table(schlick_table(), [rough, mu])[..., None]
    else:
        albedo = fresnel_conductor(mu, lobe.n, lobe.k)  # Cycles: "assume smooth surface"
    if lobe.distribution == "MULTI_GGX":
        e_table, e_avg_table, _ = tables()
        e = _lerp_table(e_table, [rough, mu])[..., None]
        e_avg = float(_lerp_table(e_avg_table, [rough]))
        albedo = albedo * e * multiscatter_factor(lobe.average_fresnel(), e, e_avg)
    return albedo


def lobe_color(lobe: GlossyLobe, mu) -> np.ndarray:
    """(..., 3) the lobe's share of Cycles' Glossy Color at cosines mu."""
    mu = np.asarray(mu, np.float64)
    out = lobe.weight * lobe_albedo(lobe, mu)
    return out if lobe.view is None else out * sample_view(lobe.view, mu)[..., None]


@dataclass
class GlossySurface:
    """A surface of glossy closures over a diffuse part whose weight depends on the view angle:
    what a node tree other than one Principled BSDF makes (Glossy, Metallic and Glass BSDFs, Mix
    and Add Shaders, a Fresnel or Layer Weight factor). `Material.specular` holds it where it
    holds a `SpecularLayer` for a lone Principled BSDF; the functions of this module take both.

    lobes : the glossy closures; diffuse : (VIEW_SAMPLES,) weight of the material's diffuse
    colour over the view cosine (`view_grid`), None for 1 (Cycles' Diffuse Color is
    base_color x this: 1 - F at the pixel's view angle under a Mix with a Fresnel factor).
    """

    lobes: list = field(default_factory=list)
    diffuse: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.lobes = [lobe for lobe in self.lobes if lobe.active]
        if self.diffuse is not None:
            d = np.asarray(self.diffuse, np.float64).reshape(-1)
            self.diffuse = np.clip(np.where(np.isfinite(d), d, 1.0), 0.0, None)

    def key(self) -> bytes:
        parts = [lobe.key() for lobe in self.lobes]
        parts.append(b"" if self.diffuse is None else np.asarray(self.diffuse, np.float64).tobytes())
        return b"|".join(parts)


def layer_lobes(layer: SpecularLayer) -> list:
    """The `GlossyLobe`s of a Principled BSDF's layer: the dielectric specular (when Cycles
    allocates it) and the metallic F82 lobe (its edge tint is the Specular Tint, as in Cycles)."""
    distribution = "MULTI_GGX" if layer.multiscatter else "GGX"
    out = []
    if layer.active and layer.weight > 0:
        out.append(GlossyLobe(weight=np.full(3, layer.weight), roughness=layer.roughness, distribution=distribution,
                              fresnel="dielectric", ior=layer.eta, f0=layer.f0))
    out += _transmission_lobes(layer)
    if layer.metallic > 0:
        tint = np.minimum(layer.tint, 1.0)
        b = np.zeros(3) if np.all(tint == 1.0) else f82_b_from_tint(layer.metal_color, tint)
        out.append(GlossyLobe(weight=np.full(3, layer.metallic), roughness=layer.roughness, distribution=distribution,
                              fresnel="f82", f0=layer.metal_color, b=b))
    if layer.coated:
        # Under the coat: its tint and its layering weight at the view angle; then the coat's own lobe.
        under = layer.coat_factor(view_grid())
        absorb = 1.0 + layer.coat * (layer.coat_tint.astype(np.float64) - 1.0)
        out = [replace(lobe, weight=lobe.weight * absorb,
                       view=under if lobe.view is None else sample_view(lobe.view, view_grid()) * under) for lobe in out]
        coat = layer.coat_layer()
        out.append(GlossyLobe(weight=np.full(3, layer.coat), roughness=layer.coat_roughness, distribution="GGX",
                              fresnel="dielectric", ior=coat.eta, f0=coat.f0))
    return out


def _transmission_lobes(layer: SpecularLayer) -> list:
    """The reflection of a Principled BSDF's transmission (Cycles' glass closure of weight
    transmission x (1 - metallic), F0 of the IOR times the Specular Tint; its multiscatter glass
    compensation is not modelled: rendered as GGX). Its transmitted light is not rendered."""
    weight = layer.transmission * (1.0 - layer.metallic)
    if weight <= 0 or layer.ior == 1.0:
        return []
    f0 = np.clip(float(f0_from_ior(layer.ior)) * layer.tint.astype(np.float64), 0.0, 1.0)
    return [GlossyLobe(weight=np.full(3, weight), roughness=layer.roughness, distribution="GGX",
                       fresnel="dielectric", ior=layer.ior, f0=f0)]


def surface_lobes(surface) -> list:
    """The `GlossyLobe`s of a material's `specular` (a SpecularLayer, a GlossySurface or None)."""
    if surface is None:
        return []
    if isinstance(surface, GlossySurface):
        return surface.lobes
    return layer_lobes(surface)


if __name__ == "__main__":
    write_tables()
    print(f"wrote {TABLES_FILE}")  # noqa: T201 (a developer command)

"""Specular antialiasing (hybridgi_core/specular_aa.py): a pixel's one glossy sample, through a
lobe widened by its normals' spread, says what the pixel's whole area reflects of a lamp."""

from __future__ import annotations

import numpy as np

from hybridgi_core import glossy, specular_aa
from hybridgi_core import specular as sp
from hybridgi_core.snapshot import Light, Material

#: Tilt of the normal per pixel (radians) of the curved surface the tests look at.
CURVE = 0.06


def _normal(x, y):
    """Unit normals of a dome whose normal tilts by CURVE per pixel, at pixel coordinates x, y."""
    n = np.stack(np.broadcast_arrays(CURVE * np.asarray(x, float), CURVE * np.asarray(y, float), 1.0), axis=-1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def _image_normals(h, w):
    y, x = np.mgrid[0:h, 0:w]
    return _normal(x - w // 2, y - h // 2).reshape(-1, 3)


def _sun_glossy(normals, widen=None, roughness=0.1):
    """The sun's (straight down, seen from straight above) glossy radiance at unit `normals`."""
    mats = glossy.GlossyMaterials.from_materials([Material(specular=sp.SpecularLayer(roughness=roughness))])
    sun = Light(kind="SUN", color=np.ones(3, np.float32), power=3.0, matrix=np.eye(4))
    n = normals.shape[0]
    view = np.tile([0.0, 0.0, 1.0], (n, 1))
    return glossy.glossy_direct([sun], np.zeros((n, 3)), normals, view, np.zeros(n, np.int32), mats, None,
                                np.random.default_rng(0), samples=1, widen=widen)[:, 0]


def test_the_spread_of_a_domes_normals_sets_the_added_alpha2():
    h, w = 9, 9
    add = specular_aa.footprint_alpha2(_image_normals(h, w), np.arange(h * w), (h, w)).reshape(h, w)
    # At the top, each axis' one-sided change is about CURVE: 2 sigma^2 (2 CURVE^2).
    assert np.isclose(add[4, 4], 2 * specular_aa.SIGMA2 * 2 * CURVE**2, rtol=0.02)
    # A flat image adds nothing; a steep one stops at KAPPA.
    flat = np.tile([0.0, 0.0, 1.0], (h * w, 1))
    assert not specular_aa.footprint_alpha2(flat, np.arange(h * w), (h, w)).any()
    steep = _normal(*np.mgrid[0:h, 0:w][::-1] * 30.0).reshape(-1, 3)
    assert np.allclose(specular_aa.footprint_alpha2(steep, np.arange(h * w), (h, w)).max(), specular_aa.KAPPA)


def test_a_crease_or_a_silhouette_does_not_widen_its_neighbours():
    """Two flat faces meeting at a right angle, the right one ending at the background: every
    pixel has a neighbour on its own face along each axis, so none widens."""
    h, w = 4, 8
    n = np.zeros((h, w, 3))
    n[:, :4] = (0.0, 0.0, 1.0)
    n[:, 4:] = (1.0, 0.0, 0.0)
    pix = np.flatnonzero(np.arange(w)[None, :].repeat(h, 0).reshape(-1) < 7)  # column 7: background
    add = specular_aa.footprint_alpha2(n.reshape(-1, 3)[pix], pix, (h, w))
    assert not add.any()
    # A lone pixel (no neighbour with geometry) keeps its lobe.
    assert not specular_aa.footprint_alpha2(np.array([[0.0, 0.0, 1.0]]), np.array([5]), (3, 3)).any()


def _patch(offset, widened: bool):
    """A 9 x 9 pixel patch of the dome with its top `offset` (pixels) from the middle pixel's
    centre: (the centre samples' glossy light (9, 9), the pixels' means by 16 x 16 samples each)."""
    h = w = 9
    y, x = np.mgrid[0:h, 0:w]
    px, py = x - w // 2 + offset[0], y - h // 2 + offset[1]
    centres = _normal(px, py).reshape(-1, 3)
    add = specular_aa.footprint_alpha2(centres, np.arange(h * w), (h, w)) if widened else None
    k = 16
    sub = (np.arange(k) + 0.5) / k - 0.5
    inside = _normal(px[..., None, None] + sub[None, None, None, :], py[..., None, None] + sub[None, None, :, None])
    mean = _sun_glossy(inside.reshape(-1, 3)).reshape(h, w, k * k).mean(axis=-1)
    return _sun_glossy(centres, add).reshape(h, w), mean


def test_a_subpixel_highlight_no_longer_depends_on_where_it_falls():
    """A roughness-0.1 lobe's sun highlight on a dome is a fraction of a pixel across. The centre
    samples alone read its light 11x too bright where it falls on a pixel's centre and 7x too dim
    where it falls between four; through the widened lobes they read within 35% of it wherever it
    falls, and the pixel it falls in within 10% of that pixel's mean."""
    offsets = [(0.0, 0.0), (0.5, 0.5), (0.37, -0.21), (0.25, 0.0)]
    sharp = [(lambda a, m: a.sum() / m.sum())(*_patch(o, False)) for o in offsets]
    assert max(sharp) > 10.0 and min(sharp) < 0.2, sharp
    for o in offsets:
        wide, mean = _patch(o, True)
        assert 0.65 < wide.sum() / mean.sum() < 1.35, (o, wide.sum(), mean.sum())
    wide, mean = _patch((0.0, 0.0), True)
    assert np.isclose(wide[4, 4], mean[4, 4], rtol=0.1), (wide[4, 4], mean[4, 4])


def test_widened_roughness_adds_alpha2_and_keeps_unwidened_lobes():
    rough = np.array([0.3, 0.3, 0.05, 1.0], np.float32)
    add = np.array([0.0, 0.01, 0.01, 0.5], np.float32)
    wide = specular_aa.widened_roughness(rough, add)
    assert wide[0] == rough[0]  # nothing added: the very same value
    assert np.isclose(wide[1] ** 4, 0.3**4 + 0.01, rtol=1e-5)
    assert np.isclose(wide[2] ** 4, 0.05**4 + 0.01, rtol=1e-5)
    assert wide[3] == 1.0  # at most 1


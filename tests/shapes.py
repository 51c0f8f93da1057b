"""Small analytic test geometry shared by the core tests."""

import numpy as np

from hybridgi_core.snapshot import geometry_from_arrays

# Box corners and inward-facing quads (normals point into the box).
_CORNERS = np.array([[x, y, z] for z in (0, 1) for y in (0, 1) for x in (0, 1)], np.float32)
_QUADS_INWARD = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]


def box(lo, hi, inward=True, material=0, obj=0):
    """12 flat-shaded triangles of the box [lo, hi]; inward = a room, else a solid object."""
    p = np.asarray(lo, np.float32) + _CORNERS * (np.asarray(hi, np.float32) - np.asarray(lo, np.float32))
    tris = []
    for a, b, c, d in _QUADS_INWARD:
        tris += [(a, b, c), (a, c, d)] if inward else [(a, c, b), (a, d, c)]
    return geometry_from_arrays(p, np.array(tris), material, obj)

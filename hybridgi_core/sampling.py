"""Probe-ray directions: spherical Fibonacci points with a per-frame random rotation.

The rotation decorrelates frames so the EMA integrates many more directions than one frame traces;
it is drawn from (seed, frame) alone, so a frame's rays never depend on what was rendered before.
"""

from __future__ import annotations

import numpy as np

GOLDEN_ANGLE = np.pi * (3.0 - np.sqrt(5.0))


def spherical_fibonacci(n: int) -> np.ndarray:
    """(n, 3) float32 near-uniform unit directions (equal-area spiral)."""
    i = np.arange(n, dtype=np.float64) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    phi = GOLDEN_ANGLE * i
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1).astype(np.float32)


def frame_rng(seed: int, frame: int) -> np.random.Generator:
    """Deterministic generator for one (seed, frame); frames may be negative (warm-up)."""
    return np.random.default_rng([seed & 0xFFFFFFFF, frame & 0xFFFFFFFF, 0x48474931])


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """(3, 3) float32 uniformly distributed rotation (unit quaternion from 4 normal draws)."""
    q = rng.normal(size=4)
    w, x, y, z = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ],
        np.float32,
    )


def frame_directions(n: int, seed: int, frame: int) -> np.ndarray:
    """(n, 3) float32 probe directions of one frame, shared by every cell."""
    return spherical_fibonacci(n) @ random_rotation(frame_rng(seed, frame)).T


def octahedral_texel(dirs: np.ndarray, size: int) -> np.ndarray:
    """(n,) int32 index ty * size + tx of the octahedral-map texel holding each unit direction.

    The same nearest-texel mapping is used when writing depth moments and in the gathers (numpy
    and GLSL), so they agree exactly. Column by column in float32 (the fold is exact there),
    with the texel coordinate 0.5 + p / 2 in float64 as it always was.
    """
    d = np.asarray(dirs, np.float32).reshape(-1, 3)
    x, y, z = (np.ascontiguousarray(d[:, k]) for k in range(3))
    s = np.abs(x)
    s += np.abs(y)
    s += np.abs(z)
    np.maximum(s, np.float32(1e-20), out=s)
    px, py = x / s, y / s
    neg = np.flatnonzero(z < 0)
    if neg.size:
        qx, qy = px[neg], py[neg]
        px[neg] = (np.float32(1.0) - np.abs(qy)) * np.where(qx >= 0, np.float32(1.0), np.float32(-1.0))
        py[neg] = (np.float32(1.0) - np.abs(qx)) * np.where(qy >= 0, np.float32(1.0), np.float32(-1.0))
    tx, ty = (np.clip(np.floor((q * 0.5 + 0.5) * size), 0, size - 1).astype(np.int32)
              for q in (px.astype(np.float64), py.astype(np.float64)))
    ty *= size
    ty += tx
    return ty

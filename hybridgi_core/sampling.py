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
    and GLSL), so they agree exactly.
    """
    d = np.asarray(dirs, np.float32)
    s = np.abs(d).sum(axis=1, keepdims=True)
    p = d[:, :2] / np.maximum(s, 1e-20)
    neg = d[:, 2] < 0
    folded = (1.0 - np.abs(p[:, ::-1])) * np.where(p >= 0, 1.0, -1.0)
    p = np.where(neg[:, None], folded, p)
    uv = p * 0.5 + 0.5
    t = np.clip(np.floor(uv * size), 0, size - 1).astype(np.int32)
    return t[:, 1] * size + t[:, 0]

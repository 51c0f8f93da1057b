"""Real spherical harmonics up to L2 (Sloan's ordering and constants) for radiance and irradiance.

The cache stores *radiance* SH; irradiance E(n) is its convolution with the clamped cosine
(Ramamoorthi & Hanrahan 2001): band l is scaled by A_l = pi, 2pi/3, pi/4.
"""

from __future__ import annotations

import numpy as np

C0 = 0.28209479177387814  # 1 / (2 sqrt(pi))
C1 = 0.4886025119029199  # sqrt(3 / (4 pi))
C2 = 1.0925484305920792  # sqrt(15 / (4 pi))
C3 = 0.31539156525252005  # sqrt(5 / (16 pi))
C4 = 0.5462742152960396  # sqrt(15 / (16 pi))

#: OpenBLAS runs a GEMM on the calling thread alone up to this m*n*k (SMP_THRESHOLD_MIN * 4).
_GEMM_SINGLE_THREAD_MNK = 65536 * 4

#: Clamped-cosine convolution per band.
COSINE_BANDS = (np.pi, 2.0 * np.pi / 3.0, np.pi / 4.0)


def coeff_count(order: int) -> int:
    return (order + 1) ** 2


def basis(dirs: np.ndarray, order: int) -> np.ndarray:
    """SH basis at unit directions.

    dirs : (n, 3) float; returns (n, K) float32 with K = 4 (order 1) or 9 (order 2).
    """
    # Computed as contiguous rows (K, n) and returned transposed: ufuncs over the strided (n, 3)
    # columns were 3x slower.
    x, y, z = np.ascontiguousarray(np.asarray(dirs, np.float32).T)
    out = np.empty((coeff_count(order), x.shape[0]), np.float32)
    out[0] = C0
    np.multiply(y, np.float32(C1), out=out[1])
    np.multiply(z, np.float32(C1), out=out[2])
    np.multiply(x, np.float32(C1), out=out[3])
    if order >= 2:
        np.multiply(C2 * x, y, out=out[4])
        np.multiply(C2 * y, z, out=out[5])
        out[6] = C3 * (3.0 * z * z - 1.0)
        np.multiply(C2 * x, z, out=out[7])
        out[8] = C4 * (x * x - y * y)
    return out.T


def cosine_scale(order: int) -> np.ndarray:
    """(K,) float32 per-coefficient factor turning radiance SH into irradiance SH."""
    bands = [0] + [1] * 3 + [2] * 5
    return np.array([COSINE_BANDS[b] for b in bands[: coeff_count(order)]], np.float32)


def project_uniform(values: np.ndarray, dirs: np.ndarray, order: int) -> np.ndarray:
    """Monte-Carlo projection of values sampled at directions uniform over the sphere.

    values : (m, r, c) one row of r samples per cell; dirs : (r, 3) shared by all cells.
    Returns (m, K, c) float32 = 4 pi / r * sum_i f(w_i) Y(w_i).
    """
    return project_channels(np.swapaxes(values, 1, 2), dirs, order)


def project_channels(values: np.ndarray, dirs: np.ndarray, order: int) -> np.ndarray:
    """`project_uniform` for channel-major values (m, c, r); returns (m, K, c) float32.

    (m*c, r) @ (r, K) GEMMs (`matmul_on_this_thread`): far faster than a batch of tiny matmuls,
    einsum or add.at.
    """
    y = basis(dirs, order) * np.float32(4.0 * np.pi / dirs.shape[0])  # (r, K)
    m, c, r = values.shape
    out = matmul_on_this_thread(np.ascontiguousarray(values, dtype=np.float32).reshape(m * c, r), y)
    return np.swapaxes(out.reshape(m, c, -1), 1, 2)


def matmul_on_this_thread(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a (M, r) @ b (r, K) float32, in row blocks small enough that OpenBLAS runs each on the
    calling thread: its own threads, woken from the update's worker threads on a busy 2-core
    machine, made such products ~15x slower."""
    m, r = a.shape
    out = np.empty((m, b.shape[1]), np.float32)
    step = max(1, _GEMM_SINGLE_THREAD_MNK // max(1, r * b.shape[1]))
    for start in range(0, m, step):
        np.matmul(a[start : start + step], b, out=out[start : start + step])
    return out


def irradiance(coeffs: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Irradiance from radiance SH at unit normals.

    coeffs : (n, K, c) radiance SH per point; normals : (n, 3). Returns (n, c) float32 (unclamped).
    """
    k = coeffs.shape[1]
    order = 1 if k == 4 else 2
    yk = basis(normals, order) * cosine_scale(order)  # (n, K)
    return np.einsum("nk,nkc->nc", yk, coeffs).astype(np.float32, copy=False)

"""Neighbouring pixels' ray sets stratify together (`tiled_nets`): nets per pixel, per quad and per
tile, unbiased points, and a tile's average that beats independent sets on a smooth integrand."""

import numpy as np

from hybridgi_core import lights, tiled_nets


def _is_net(points: np.ndarray) -> bool:
    """Whether n = 2^m points in [0, 1)^2 hold one point in each elementary interval of area 1/n."""
    n = points.shape[0]
    m = int(round(np.log2(n)))
    assert 2**m == n
    for a in range(m + 1):
        cx = np.floor(points[:, 0] * 2**a).astype(np.int64)
        cy = np.floor(points[:, 1] * 2 ** (m - a)).astype(np.int64)
        if not (np.bincount(cx * 2 ** (m - a) + cy, minlength=n) == 1).all():
            return False
    return True


def _tile_pixels(width: int, x0: int = 0, y0: int = 0) -> np.ndarray:
    t = tiled_nets.TILE
    y, x = np.mgrid[y0:y0 + t, x0:x0 + t]
    return (y * width + x).ravel()


def test_aligned_blocks_of_the_sequence_are_nets():
    points = tiled_nets.sobol2(1024).astype(np.float64) / 2.0**32
    assert _is_net(points[64:96]) and _is_net(points[512:1024]) and _is_net(points[:16])
    # Not aligned: no net (the property is the blocks', not any run's).
    assert not _is_net(points[96:224])


def test_a_pixel_its_quad_and_its_tile_are_nets_after_the_shift():
    width, samples = 37, 32
    pix = _tile_pixels(width, 8, 4)
    u, v = tiled_nets.tiled_uv(pix, width, samples, key=11)
    pts = np.stack([u, v], axis=-1).astype(np.float64)  # (16, samples, 2)
    assert all(_is_net(pts[k]) for k in range(pix.size))
    block = tiled_nets.morton_block(pix % width % tiled_nets.TILE, pix // width % tiled_nets.TILE)
    quad = pts[np.argsort(block)].reshape(4, 4 * samples, 2)
    assert all(_is_net(q) for q in quad)
    assert _is_net(pts.reshape(-1, 2))
    # Another tile draws another shift: its points differ.
    u2, _ = tiled_nets.tiled_uv(_tile_pixels(width, 12, 4), width, samples, key=11)
    assert not np.allclose(np.sort(u.ravel()), np.sort(u2.ravel()))


def test_points_do_not_depend_on_how_pixels_are_split():
    width = 50
    pix = np.arange(3 * width, 9 * width)
    u, v = tiled_nets.tiled_uv(pix, width, 16, key=5)
    u1, v1 = tiled_nets.tiled_uv(pix[77:201], width, 16, key=5)
    assert np.array_equal(u[77:201], u1) and np.array_equal(v[77:201], v1)
    assert np.all((u >= 0) & (u < 1) & (v >= 0) & (v < 1))


def test_points_are_uniform_over_shifts():
    """Each point is uniform on [0, 1)^2 over the tiles' shifts: a pixel's estimate is unbiased."""
    width = 64
    tiles = 5 * width + 3 + tiled_nets.TILE * np.arange(16)  # one pixel of each of 16 tiles
    draws = [tiled_nets.tiled_uv(tiles, width, 8, key=k) for k in range(300)]
    first_u = np.asarray([u[:, 0] for u, _ in draws])
    assert abs(first_u.mean() - 0.5) < 0.01
    hist = np.histogram(np.concatenate([v.ravel() for _, v in draws]), bins=8, range=(0, 1))[0]
    assert hist.min() > 0.9 * hist.mean()


def test_a_tiles_average_beats_independent_sets():
    """The filter's average over a tile of pixels that see the same light: with the tile's sets
    one net its error is several times below that of independently shifted Hammersley sets."""
    def f(u, v):
        return np.exp(-3.0 * (u - 0.3) ** 2 - 5.0 * (v - 0.6) ** 2) + u * v

    exact_u = np.linspace(0, 1, 2001)
    grid = f(exact_u[:, None], exact_u[None, :])
    exact = np.trapz(np.trapz(grid, exact_u, axis=1), exact_u)
    width, samples = 64, 16
    pix = _tile_pixels(width)
    tiled, independent = [], []
    rng = np.random.default_rng(3)
    for key in range(300):
        u, v = tiled_nets.tiled_uv(pix, width, samples, key)
        tiled.append(f(u, v).mean() - exact)
        u, v = lights.stratified_uv(rng, pix.size, samples)
        independent.append(f(u, v).mean() - exact)
    tiled, independent = np.asarray(tiled), np.asarray(independent)
    assert abs(tiled.mean()) < 3 * tiled.std() / np.sqrt(tiled.size) + 1e-4  # unbiased
    assert np.sqrt(np.mean(tiled**2)) < 0.5 * np.sqrt(np.mean(independent**2))

"""Ray sets of neighbouring pixels that stratify together: blocks of one (0, 2)-sequence.

Why: a pixel's GI rays are a stratified set of its own (a shifted Hammersley set), and the image's
noise is then what the residual filter averages over neighbouring pixels. With a random shift per
pixel, the union of the neighbours' sets is no better stratified than random sets of that size:
each pixel's error is independent, and the filter's average keeps 1/sqrt(taps) of it. Here the
pixels of a TILE x TILE tile take consecutive blocks of one low-discrepancy sequence whose aligned
blocks are nets (the first two dimensions of Sobol's sequence, a (0, 2)-sequence in base 2): each
pixel's set is a (0, m, 2)-net (32 rays: as well stratified as a Hammersley set), each 2 x 2 quad's
four blocks form a net four times as fine, and the whole tile's sixteen a net sixteen times as fine
(the blocks go to the pixels in Morton order). Where neighbours see nearly the same incoming light
(one surface, one normal), their errors cancel in the filter's average instead of adding up in
quadrature: the noise moves to high spatial frequencies, which the filter removes.

Each tile's sets carry one random digital shift (XOR of both coordinates' bits) drawn from a hash
of the tile and the frame's key: every point is uniform on [0, 1)^2, so each pixel's estimate
stays unbiased, and the shift does not depend on how the pixels are split into work items.

numpy only.
"""

from __future__ import annotations

import functools

import numpy as np

from .lights import _radical_inverse_base2

#: Pixels per tile side; the tile's TILE^2 pixels take TILE^2 consecutive blocks of the sequence.
TILE = 4
_BITS = 32


@functools.lru_cache(maxsize=16)
def sobol2(n: int) -> np.ndarray:
    """(n, 2) uint32 the first n points of the 2-D Sobol sequence as 32-bit fractions: the van der
    Corput sequence and Sobol's second dimension (primitive polynomial x + 1, direction numbers
    v_1 = 1/2, v_j = v_(j-1) xor v_(j-1) / 2). Together a (0, 2)-sequence in base 2: every block
    of 2^m points starting at a multiple of 2^m has one point in each elementary interval of
    area 2^-m."""
    i = np.arange(n, dtype=np.uint64)
    out = np.zeros((n, 2), np.uint64)
    # van der Corput: i's bits reversed (exact in float64 as a fraction of 2^32).
    out[:, 0] = (_radical_inverse_base2(i) * 2.0**_BITS).astype(np.uint64)
    v = np.uint64(1 << (_BITS - 1))
    for j in range(_BITS):
        bit = ((i >> np.uint64(j)) & np.uint64(1)).astype(bool)
        out[bit, 1] ^= v
        v = v ^ (v >> np.uint64(1))
    result = out.astype(np.uint32)
    result.flags.writeable = False
    return result


def morton_block(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """(n,) int64 the block of pixels (x, y) within their TILE x TILE tile, in Morton order: the
    four pixels of each 2 x 2 quad hold four consecutive (aligned) blocks."""
    block = np.zeros(np.shape(x), np.int64)
    for bit in range(TILE.bit_length() - 1):
        block |= ((x >> bit) & 1) << (2 * bit)
        block |= ((y >> bit) & 1) << (2 * bit + 1)
    return block


def _mix32(h: np.ndarray) -> np.ndarray:
    """A 32-bit integer hash (Wellons' lowbias32) of uint32 h."""
    h = h.astype(np.uint32)
    h ^= h >> np.uint32(16)
    h *= np.uint32(0x7FEB352D)
    h ^= h >> np.uint32(15)
    h *= np.uint32(0x846CA68B)
    h ^= h >> np.uint32(16)
    return h


def tiled_uv(pix: np.ndarray, width: int, samples: int, key: int) -> tuple[np.ndarray, np.ndarray]:
    """(u, v) (m, samples) float32 in [0, 1): the sample sets of the pixels `pix` (flat indices
    into an image `width` pixels wide), each its tile's block of the shifted (0, 2)-sequence.
    key : the frame's stream (any int); other keys give other shifts."""
    pix = np.asarray(pix, np.int64)
    x, y = pix % width, pix // width
    blocks = TILE * TILE
    pattern = sobol2(blocks * int(samples)).reshape(blocks, int(samples), 2)
    own = pattern[morton_block(x % TILE, y % TILE)]  # (m, samples, 2)
    tiles_x = -(-int(width) // TILE)
    tile = ((y // TILE) * tiles_x + x // TILE).astype(np.uint64)
    salt = np.uint64(_mix32(np.asarray([key & 0xFFFFFFFF], np.uint32))[0])
    seed = (tile * np.uint64(2) + salt * np.uint64(0x9E3779B1)) & np.uint64(0xFFFFFFFF)
    shift_u = _mix32(seed.astype(np.uint32))
    shift_v = _mix32(shift_u ^ np.uint32(0x68E31DA4))
    scale = np.float32(2.0**-24)
    u = ((own[..., 0] ^ shift_u[:, None]) >> np.uint32(8)).astype(np.float32) * scale
    v = ((own[..., 1] ^ shift_v[:, None]) >> np.uint32(8)).astype(np.float32) * scale
    return u, v

"""Image comparison for renders against Cycles: error metrics, noise-robust blurring, error heatmaps
and a dependency-free PNG writer. numpy only (no bpy, no PIL), so tests and tools can use it anywhere.

Images are numpy arrays of shape (h, w) or (h, w, c), row 0 at the top; masks are (h, w) bool.
"""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np

#: Depth values at or beyond this are background: Cycles writes 1e10 where a camera ray escapes.
BACKGROUND_DEPTH = 1e9

#: Viridis (matplotlib's default colormap, CC0, by N. J. Smith, S. van der Walt and E. Firing)
#: sampled at every 16th of its 256 entries. Perceptually uniform and readable in greyscale and
#: by colour-blind readers, so the heatmaps' brightness order is the error order.
_VIRIDIS_INDEX = (0, 16, 32, 48, 64, 80, 96, 112, 128, 144, 160, 176, 192, 208, 224, 240, 255)
_VIRIDIS_RGB = (
    (0.267004, 0.004874, 0.329415),
    (0.282327, 0.094955, 0.417331),
    (0.278826, 0.175490, 0.483397),
    (0.258965, 0.251537, 0.524736),
    (0.229739, 0.322361, 0.545706),
    (0.199430, 0.387607, 0.554642),
    (0.172719, 0.448791, 0.557885),
    (0.149039, 0.508051, 0.557250),
    (0.127568, 0.566949, 0.550556),
    (0.120638, 0.625828, 0.533488),
    (0.157851, 0.683765, 0.501686),
    (0.246070, 0.738910, 0.452024),
    (0.369214, 0.788888, 0.382914),
    (0.515992, 0.831158, 0.294279),
    (0.678489, 0.863742, 0.189503),
    (0.845561, 0.887322, 0.099702),
    (0.993248, 0.906157, 0.143936),
)

#: Colour of pixels outside the mask in heatmaps: dark grey, distinct from viridis' darkest purple.
_MASKED_OUT_RGB = (40, 40, 40)

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_COLOR_TYPES = {1: 0, 2: 4, 3: 2, 4: 6}  # channels -> grey, grey+alpha, RGB, RGBA


# --- metrics -----------------------------------------------------------------------------------


def relative_l1(test: np.ndarray, ref: np.ndarray, mask: np.ndarray | None = None) -> float:
    """sum |test - ref| / sum |ref| over the masked pixels, all channels.

    test, ref : (h, w) or (h, w, c) float
    mask : (h, w) bool or None (all pixels)

    Returns 0.0 when both sums are 0 and inf when only the reference is all zero.
    """
    t, r = _masked(test, ref, mask)
    num = float(np.abs(t - r).sum())
    den = float(np.abs(r).sum())
    if den == 0.0:
        return 0.0 if num == 0.0 else float("inf")
    return num / den


def relative_bias(test: np.ndarray, ref: np.ndarray, mask: np.ndarray | None = None) -> float:
    """sum(test) / sum(ref) - 1 over the masked pixels: the energy gained (+) or lost (-).

    Unlike relative_l1 it is blind to noise and to light in the wrong place, which is why the two
    together say whether an error is missing light or misplaced light.
    """
    t, r = _masked(test, ref, mask)
    den = float(r.sum())
    if den == 0.0:
        return 0.0 if float(t.sum()) == 0.0 else float("inf")
    return float(t.sum()) / den - 1.0


def _masked(test: np.ndarray, ref: np.ndarray, mask: np.ndarray | None):
    t = np.asarray(test, np.float64)
    r = np.asarray(ref, np.float64)
    if t.shape != r.shape:
        raise ValueError(f"test {t.shape} and reference {r.shape} differ in shape")
    if mask is None:
        return t, r
    m = np.asarray(mask, bool)
    if m.shape != t.shape[:2]:
        raise ValueError(f"mask {m.shape} does not match the images' {t.shape[:2]}")
    return t[m], r[m]


def masked_geometry(depth_or_alpha: np.ndarray, kind: str = "auto") -> np.ndarray:
    """(h, w) bool: the pixels that show geometry.

    depth_or_alpha : (h, w) float, a Depth pass (background >= BACKGROUND_DEPTH, inf, nan or <= 0)
        or an alpha channel (background < 0.5; only meaningful with a transparent film).
    kind : "depth", "alpha" or "auto" (alpha when every value lies in [0, 1], else depth).
        Pass the kind explicitly where a scene may be smaller than one unit.
    """
    a = np.asarray(depth_or_alpha, np.float64)
    if a.ndim != 2:
        raise ValueError(f"expected an (h, w) pass, got shape {a.shape}")
    if kind == "auto":
        finite = a[np.isfinite(a)]
        kind = "alpha" if finite.size and finite.min() >= 0.0 and finite.max() <= 1.0 else "depth"
    if kind == "alpha":
        return np.isfinite(a) & (a >= 0.5)
    if kind == "depth":
        return np.isfinite(a) & (a > 0.0) & (a < BACKGROUND_DEPTH)
    raise ValueError(f"kind must be 'auto', 'depth' or 'alpha', got {kind!r}")


def box_blur(img: np.ndarray, radius: int, mask: np.ndarray | None = None) -> np.ndarray:
    """Mean over a (2r+1)^2 window, the window cut at the image border and at the mask.

    Renders at a few hundred spp are noisy; comparing blurred images measures bias (light missing
    or misplaced) rather than noise. Normalising by the number of pixels actually averaged (the
    window clipped to the image and the mask) keeps edges unbiased and keeps background from
    bleeding into geometry. Masked-out pixels come back as 0.

    img : (h, w) or (h, w, c) float;  mask : (h, w) bool or None.  Returns float32, img's shape.
    """
    a = np.asarray(img, np.float64)
    if radius <= 0:
        return a.astype(np.float32)
    flat = a.ndim == 2
    if flat:
        a = a[..., None]
    w = np.ones(a.shape[:2]) if mask is None else np.asarray(mask, np.float64)
    a = np.where(w[..., None] > 0, a, 0.0)  # NaN * 0 is NaN: masked-out NaNs must not spread
    num = _box_sum(_box_sum(a * w[..., None], radius, 0), radius, 1)
    den = _box_sum(_box_sum(w[..., None], radius, 0), radius, 1)
    out = np.divide(num, den, out=np.zeros_like(num), where=den > 0)
    if mask is not None:
        out[~np.asarray(mask, bool)] = 0.0
    return (out[..., 0] if flat else out).astype(np.float32)


def _box_sum(a: np.ndarray, radius: int, axis: int) -> np.ndarray:
    """Sum over [i - r, i + r] along axis, clipped to the array: a prefix sum, O(n) for any r."""
    n = a.shape[axis]
    c = np.cumsum(a, axis=axis)
    c = np.concatenate([np.zeros_like(np.take(c, [0], axis=axis)), c], axis=axis)
    i = np.arange(n)
    hi = np.minimum(i + radius + 1, n)
    lo = np.maximum(i - radius, 0)
    return np.take(c, hi, axis=axis) - np.take(c, lo, axis=axis)


def error_map(test: np.ndarray, ref: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """(h, w) float32: per-pixel |test - ref| (mean over channels) / the mean |ref| of the mask.

    Normalised by the image mean rather than per pixel, so its mean over the mask is exactly
    relative_l1 (per-pixel ratios blow up in dark corners that hardly count).
    """
    t = np.asarray(test, np.float64)
    r = np.asarray(ref, np.float64)
    diff = np.abs(t - r)
    mag = np.abs(r)
    if diff.ndim == 3:
        diff = diff.mean(axis=2)
        mag = mag.mean(axis=2)
    scale = float(mag[mask].mean()) if mask is not None and np.any(mask) else float(mag.mean())
    out = diff / scale if scale > 0 else np.where(diff > 0, np.inf, 0.0)
    return out.astype(np.float32)


# --- pictures ----------------------------------------------------------------------------------


def heatmap(err: np.ndarray, vmax: float, mask: np.ndarray | None = None) -> np.ndarray:
    """(h, w, 3) uint8 viridis picture of err in [0, vmax] (values beyond are clamped).

    err : (h, w) float, or (h, w, c) (the channels are averaged).  Non-finite values show as the
    top of the scale; pixels outside mask as dark grey.
    """
    e = np.asarray(err, np.float64)
    if e.ndim == 3:
        e = e.mean(axis=2)
    if vmax <= 0:
        raise ValueError(f"vmax must be positive, got {vmax}")
    t = np.clip(np.nan_to_num(e / vmax, nan=1.0, posinf=1.0, neginf=0.0), 0.0, 1.0)
    xs = np.asarray(_VIRIDIS_INDEX, np.float64) / 255.0
    lut = np.asarray(_VIRIDIS_RGB, np.float64)
    rgb = np.stack([np.interp(t, xs, lut[:, k]) for k in range(3)], axis=-1)
    out = np.round(rgb * 255.0).astype(np.uint8)
    if mask is not None:
        out[~np.asarray(mask, bool)] = _MASKED_OUT_RGB
    return out


def to_display(img: np.ndarray, white: float) -> np.ndarray:
    """(h, w, 3) uint8 sRGB of linear img, with `white` mapping to 1.0 (then clamped).

    A caller shows a test and its reference with the same `white` so that brightness compares.
    """
    a = np.asarray(img, np.float64)
    if a.ndim == 2:
        a = np.repeat(a[..., None], 3, axis=2)
    a = a[..., :3]
    if a.shape[2] == 1:
        a = np.repeat(a, 3, axis=2)
    x = np.clip(np.nan_to_num(a / white if white > 0 else a, nan=0.0, posinf=1.0), 0.0, 1.0)
    srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return np.round(srgb * 255.0).astype(np.uint8)


def comparison_strip(
    test: np.ndarray,
    ref: np.ndarray,
    mask: np.ndarray | None = None,
    vmax: float = 1.0,
    gap: int = 2,
) -> np.ndarray:
    """(h, 3w + 2 gap, 3) uint8: test | reference | heatmap of error_map(test, ref, mask).

    Both images share one exposure, the reference's 99th percentile over the mask, so the strip
    reads as 'how bright should it be'; the heatmap's scale is vmax in error_map units (1 = an
    error as large as the mean reference value).
    """
    r = np.asarray(ref, np.float64)
    sel = r[mask] if mask is not None and np.any(mask) else r.reshape(-1, *r.shape[2:])
    white = float(np.percentile(sel, 99)) if sel.size else 1.0
    white = white if white > 0 else 1.0
    panels = [
        to_display(test, white),
        to_display(ref, white),
        heatmap(error_map(test, ref, mask), vmax, mask),
    ]
    h = panels[0].shape[0]
    spacer = np.full((h, gap, 3), 255, np.uint8)
    return np.concatenate([panels[0], spacer, panels[1], spacer, panels[2]], axis=1)


def write_png(path: str | Path, image: np.ndarray) -> Path:
    """Write an 8-bit PNG: (h, w) grey, (h, w, 2) grey+alpha, (h, w, 3) RGB or (h, w, 4) RGBA uint8.

    Filter type 0 on every row and zlib level 6: small pictures, so simplicity beats the few
    percent a per-row filter choice would save.
    """
    a = np.asarray(image)
    if a.dtype != np.uint8:
        raise ValueError(f"write_png needs uint8 pixels, got {a.dtype}")
    if a.ndim == 2:
        a = a[..., None]
    if a.ndim != 3 or a.shape[2] not in _PNG_COLOR_TYPES or a.shape[0] < 1 or a.shape[1] < 1:
        raise ValueError(f"cannot write an image of shape {np.asarray(image).shape} as PNG")
    h, w, c = a.shape
    raw = np.concatenate([np.zeros((h, 1), np.uint8), a.reshape(h, w * c)], axis=1).tobytes()
    ihdr = struct.pack(">IIBBBBB", w, h, 8, _PNG_COLOR_TYPES[c], 0, 0, 0)
    data = b"".join(
        [_PNG_SIGNATURE, _chunk(b"IHDR", ihdr), _chunk(b"IDAT", zlib.compress(raw, 6)), _chunk(b"IEND", b"")]
    )
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data)
    return path


def _chunk(kind: bytes, payload: bytes) -> bytes:
    return struct.pack(">I", len(payload)) + kind + payload + struct.pack(">I", zlib.crc32(kind + payload))

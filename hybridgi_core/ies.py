"""IES light profiles (a lamp's IES Texture node), read and evaluated as Cycles does.

Cycles (`util/ies.cpp`) reads an LM-63 file's candela table (photometric types B and C),
scales it by the file's candela multiplier, ballast and ballast-lamp factors and 4 pi / 177.83
(candela to W/sr of a D65 spectrum, times 4 pi for a lamp's strength), mirrors partial
symmetries out to a full sphere (vertical 0..180 degrees from straight down, horizontal
0..360), and the IES Texture node (`svm_node_ies`) returns Strength x the table at the
direction it is given: for a lamp, from the lamp to the shaded point in the lamp's own frame
(vertical angle = acos(-z), horizontal = atan2(x, y) + pi). Here that factor multiplies the
lamp's radiance per direction wherever a spot's cone does (`lights.spot_attenuation`).
Cycles interpolates the table bicubically; this reads it bilinearly.

Pure numpy; the add-on hands the file's text in (`addon/sync.py`).
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

#: Candela to Cycles' lamp strength: 4 pi / 177.83 (the luminous efficacy of D65).
CANDELA_TO_STRENGTH = 0.0706650768394


@dataclass(frozen=True, eq=False)
class IESProfile:
    """A lamp's intensity over directions: `table` (H, V) float32 at horizontal angles `h`
    (H,, radians, 0..2 pi) and vertical angles `v` (V,, radians from straight down, ascending)."""

    h: np.ndarray
    v: np.ndarray
    table: np.ndarray

    def key(self) -> tuple:
        return self.table.shape, float(self.table.sum(dtype=np.float64)), float(self.v[-1])

    def __call__(self, local: np.ndarray) -> np.ndarray:
        """(n,) float32 the profile at directions (n, 3) lamp -> point in the lamp's frame."""
        d = np.asarray(local, np.float64).reshape(-1, 3)
        norm = np.maximum(np.linalg.norm(d, axis=1), 1e-30)
        v_angle = np.arccos(np.clip(-d[:, 2] / norm, -1.0, 1.0))
        h_angle = np.arctan2(d[:, 0], d[:, 1]) + np.pi
        return _bilinear(self.h, self.v, self.table, h_angle, v_angle).astype(np.float32)


def _bilinear(h: np.ndarray, v: np.ndarray, table: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """The table (H, V) at (x, y), linear between its grid's angles; 0 beyond the last vertical angle."""
    i = np.clip(np.searchsorted(h, x, side="right") - 1, 0, h.size - 2) if h.size > 1 else np.zeros(x.shape, int)
    j = np.clip(np.searchsorted(v, y, side="right") - 1, 0, v.size - 2) if v.size > 1 else np.zeros(y.shape, int)
    if h.size > 1:
        fx = np.clip((x - h[i]) / np.maximum(h[i + 1] - h[i], 1e-12), 0.0, 1.0)
        i1 = i + 1
    else:
        fx, i1 = np.zeros(x.shape), i
    if v.size > 1:
        fy = np.clip((y - v[j]) / np.maximum(v[j + 1] - v[j], 1e-12), 0.0, 1.0)
        j1 = j + 1
    else:
        fy, j1 = np.zeros(y.shape), j
    top = table[i, j] * (1 - fy) + table[i, j1] * fy
    bottom = table[i1, j] * (1 - fy) + table[i1, j1] * fy
    out = top * (1 - fx) + bottom * fx
    return np.where(y <= v[-1] + 1e-6, out, 0.0)


def parse(text: str) -> IESProfile | None:
    """The profile of an LM-63 file's text, or None where Cycles would not read it either (no
    TILT line, photometric type A, too few numbers, a horizontal range it does not recognise)."""
    text = text.replace(",", " ")
    at = text.find("\nTILT=")
    if at < 0:
        return None
    rest = text[at + 1:]
    line_end = rest.find("\n")
    tilt = rest[:line_end if line_end >= 0 else len(rest)].strip()
    numbers = [float(x) for x in re.findall(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?",
                                            rest[line_end + 1:] if line_end >= 0 else "")]
    if tilt.upper().startswith("TILT=INCLUDE"):
        if len(numbers) < 2:
            return None
        count = int(numbers[1])
        numbers = numbers[2 + 2 * count:]
    if len(numbers) < 13:
        return None
    factor = numbers[2]
    n_v, n_h, kind = int(numbers[3]), int(numbers[4]), int(numbers[5])
    factor *= numbers[10] * numbers[11] * CANDELA_TO_STRENGTH
    data = numbers[13:]
    if kind not in (2, 1) or n_v < 1 or n_h < 1 or len(data) < n_v + n_h + n_v * n_h:
        return None
    v = list(data[:n_v])
    h = list(data[n_v:n_v + n_h])
    values = np.asarray(data[n_v + n_h:n_v + n_h + n_v * n_h], np.float64).reshape(n_h, n_v) * factor
    intensity = [list(row) for row in values]
    processed = _type_c(h, v, intensity) if kind == 1 else _type_b(h, v, intensity)
    if processed is None:
        return None
    h, v, intensity = processed
    order = np.argsort(v)
    table = np.asarray(intensity, np.float32)[:, order]
    return IESProfile(np.radians(np.asarray(h, np.float64)), np.radians(np.asarray(v, np.float64)[order]), table)


def _type_c(h, v, intensity):
    """Cycles' `process_type_c`: horizontal angles to 0..360 (rotated, mirrored from one or two
    quadrants), vertical angles starting at 0."""
    if h[0] == 90.0:
        h = [a - 90.0 for a in h]
    if h[0] != 0.0:
        return None
    if len(h) == 1:
        h, intensity = h + [360.0], intensity + [intensity[0]]
    if h[-1] == 90.0:
        n = len(h)
        for i in range(n - 2, -1, -1):
            h.append(180.0 - h[i])
            intensity.append(intensity[i])
    if h[-1] == 180.0:
        n = len(h)
        for i in range(n - 2, -1, -1):
            h.append(360.0 - h[i])
            intensity.append(intensity[i])
    if h[-1] != 360.0:
        last, first, gap = h[-1] - h[-2], h[1] - h[0], 360.0 - h[-1]
        if last == gap or first == gap:
            h, intensity = h + [360.0], intensity + [intensity[0]]
        else:
            return None
    if v[0] == 90.0:
        if v[-1] != 180.0:
            return None
        v = [180.0 - a for a in v]
    elif v[0] != 0.0:
        return None
    return h, v, intensity


def _type_b(h, v, intensity):
    """Cycles' `process_type_b`: the table transposed (its vertical angles become the horizontal
    ones), each range mirrored or shifted to cover the sphere."""
    table = [[intensity[j][i] for j in range(len(h))] for i in range(len(v))]
    h, v = v, h
    if h[-1] != 90.0:
        return None
    if h[0] == 0.0:
        n = len(h)
        h = [90.0 - h[i] for i in range(n - 1, 0, -1)] + [90.0 + a for a in h]
        table = [table[i] for i in range(n - 1, 0, -1)] + table
    elif h[0] == -90.0:
        h = [a + 90.0 for a in h]
    h, table = h + [360.0], table + [table[0]]
    if v[-1] != 90.0:
        return None
    if v[0] == 0.0:
        n = len(v)
        v = [90.0 - v[i] for i in range(n - 1, 0, -1)] + [90.0 + a for a in v]
        table = [[row[j] for j in range(n - 2, -1, -1)] + row for row in table]
    elif v[0] == -90.0:
        v = [a + 90.0 for a in v]
    return h, v, table

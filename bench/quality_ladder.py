"""Pure helpers of the time-to-quality benchmark (`bench/time_to_quality.py`): the seconds a
renderer needs to reach an error along its quality ladder, the content key of a cached Cycles
reference, and the tone map FLIP sees. numpy only (no bpy), so tests run them in plain Python.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

#: Bumped when the way references are rendered changes in a way the settings dict does not show.
REFERENCE_FORMAT = 1


# --- time to an error along a ladder ------------------------------------------------------------


@dataclass(frozen=True)
class TimeToError:
    """seconds : float, math.inf when the ladder never reaches the target
    how : "interpolated" (log-log between the two rungs around the first crossing), "at_most"
        (the cheapest rung is already at or below the target: its seconds bound the time from above)
        or "never" (no rung reaches it; `reason` says what the best rung got)
    """

    seconds: float
    how: str
    reason: str = ""

    def as_json(self) -> dict:
        return {
            "seconds": round(self.seconds, 4) if math.isfinite(self.seconds) else None,
            "how": self.how,
            **({"reason": self.reason} if self.reason else {}),
        }


def time_to_error(points, target: float) -> TimeToError:
    """First time a ladder reaches `target`, interpolated in log-log.

    points : iterable of (seconds, error), seconds > 0 and error > 0 (others are skipped); the
        ladder is walked in order of seconds, and the first rung at or below `target` ends it. The
        crossing between that rung (t1, e1) and the one before (t0, e0) is where the straight line
        through (log t0, log e0) and (log t1, log e1) meets log(target): Monte Carlo error falls as a
        power of time, a straight line in log-log.
    """
    pts = sorted((float(t), float(e)) for t, e in points if _positive(t) and _positive(e))
    if not pts:
        return TimeToError(math.inf, "never", "no rung has a finite positive time and error")
    if not _positive(target):
        return TimeToError(math.inf, "never", f"target error {target!r} is not positive")
    if pts[0][1] <= target:
        return TimeToError(pts[0][0], "at_most", f"the cheapest rung is already at {pts[0][1]:.4g}")
    for (t0, e0), (t1, e1) in zip(pts, pts[1:], strict=False):
        if e1 <= target:
            if e1 == e0:
                return TimeToError(t1, "interpolated")
            f = (math.log(target) - math.log(e0)) / (math.log(e1) - math.log(e0))
            return TimeToError(math.exp(math.log(t0) + f * (math.log(t1) - math.log(t0))), "interpolated")
    best = min(e for _t, e in pts)
    return TimeToError(math.inf, "never", f"best rung's error {best:.4g} > target {target:.4g}")


def crossing_rungs(points, target: float) -> tuple[int, ...]:
    """Indices (into `points`) of the rungs whose seconds `time_to_error` reads: the two around
    the first crossing (the second alone when its error is the target itself), the cheapest one
    alone when it is already at the target, none when the ladder never gets there (or nothing
    is valid). What a benchmark re-times to steady a ratio: the other rungs do not enter it."""
    pts = sorted((float(t), float(e), i) for i, (t, e) in enumerate(points) if _positive(t) and _positive(e))
    if not pts or not _positive(target):
        return ()
    if pts[0][1] <= target:
        return (pts[0][2],)
    for (_t0, _e0, i0), (_t1, e1, i1) in zip(pts, pts[1:], strict=False):
        if e1 == target:  # the target is this rung's own error (Cycles 16 spp): its time alone
            return (i1,)
        if e1 < target:
            return (i0, i1)
    return ()


def speed_ratio(test: TimeToError, peer: TimeToError) -> float | None:
    """test.seconds / peer.seconds; inf when only the test never gets there, None when neither does."""
    if not math.isfinite(peer.seconds):
        return None
    if not math.isfinite(test.seconds):
        return math.inf
    return test.seconds / peer.seconds


def _positive(x) -> bool:
    try:
        return math.isfinite(float(x)) and float(x) > 0.0
    except (TypeError, ValueError):
        return False


# --- the reference cache key --------------------------------------------------------------------


def scene_digest(blend: Path, procedural_sources=()) -> str:
    """sha256 of what a scene is made of.

    Bundled scenes are rebuilt by `make scenes` into .blend files whose bytes differ from build to
    build (timestamps), so for them pass their procedural sources (procedural.py, build.py): the key
    then follows the scene's content, not its build. Other scenes hash their .blend bytes.
    """
    h = hashlib.sha256()
    if procedural_sources:
        h.update(b"procedural:" + blend.stem.encode() + b"\0")
        for src in procedural_sources:
            h.update(Path(src).read_bytes())
            h.update(b"\0")
    else:
        h.update(b"blend:")
        h.update(Path(blend).read_bytes())
    return h.hexdigest()


def reference_key(scene_digest_hex: str, blender_version: str, res, spp: int, settings: dict) -> str:
    """24 hex digits naming a reference render: the scene's content, the Blender version, the
    resolution, the samples and every render setting (a change to any renders it again)."""
    payload = {
        "format": REFERENCE_FORMAT,
        "scene": scene_digest_hex,
        "blender": str(blender_version),
        "res": [int(res[0]), int(res[1])],
        "spp": int(spp),
        "settings": {str(k): settings[k] for k in sorted(settings)},
    }
    return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()[:24]


# --- the tone map FLIP compares -----------------------------------------------------------------


def exposure_white(reference: np.ndarray, mask: np.ndarray | None = None, percentile: float = 99.0) -> float:
    """The reference's luminance percentile over `mask`: the value tone_map shows as white."""
    lum = np.asarray(reference, np.float64)[..., :3] @ np.array([0.2126, 0.7152, 0.0722])
    sel = lum[mask] if mask is not None and np.any(mask) else lum.ravel()
    sel = sel[np.isfinite(sel)]
    white = float(np.percentile(sel, percentile)) if sel.size else 1.0
    return white if white > 0 else 1.0


def tone_map(img: np.ndarray, white: float) -> np.ndarray:
    """(h, w, 3) float32 display sRGB in [0, 1]: linear RGB / white, Reinhard on luminance-scaled
    values (x / (1 + x), rescaled so `white` maps to 1), then the sRGB curve. Test and reference
    must share `white` (the reference's) so a brightness error stays an error."""
    a = np.nan_to_num(np.asarray(img, np.float64)[..., :3], nan=0.0, posinf=1e6, neginf=0.0)
    x = np.maximum(a / white, 0.0)
    y = np.clip(x / (1.0 + x) * 2.0, 0.0, 1.0)  # white (x = 1) -> 1
    srgb = np.where(y <= 0.0031308, 12.92 * y, 1.055 * np.power(y, 1 / 2.4) - 0.055)
    return srgb.astype(np.float32)

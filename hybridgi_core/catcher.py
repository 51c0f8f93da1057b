"""Shadow catchers (Object > Visibility > Shadow Catcher), as Cycles composes them.

Cycles traces a catcher's pixel twice: with the scene as it is, and as if only the catcher, the
lamps and the world were there. Their ratio (the Shadow Catcher pass) is what the other objects
do to the catcher's light: below 1 in their shadows and occlusion, above 1 where they bounce
light onto it. The camera sees through the catcher: on an opaque film its Combined is what lies
behind it (the world) times that ratio; on a transparent film it is black with the shadow as its
alpha (1 - ratio). Its light passes (Diffuse / Glossy Direct and Indirect) are zero; Diffuse
Color, AO, Normal and Depth are the catcher's own. Measured against Cycles 5.0 (a grey world, the
catcher a floor under a sun): Combined on the open floor = the world's radiance exactly, Diffuse
Direct / Indirect 0.

Here the catcher's light with the scene is the frame's own (Diffuse Direct + Indirect, filtered
over the subframes), and without it the lamps' unshadowed light (`GISystem.direct`'s
`unshadowed`, the same lamps the frame samples) plus the world's irradiance over the whole
hemisphere (`open_irradiance`). The ratio is taken at the centre raster's catcher pixels.

Pure numpy; the add-on writes the passes (`addon/pipeline._write_result`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import sh
from .sky_ratio import sky_irradiance

_LUMA = np.array([0.2126, 0.7152, 0.0722], np.float32)
#: Shadow-ray samples per catcher pixel and lamp of the unshadowed light (its samples' light
#: without shadows: area lamps' is exact where the lamp is wholly seen, `lights.direct_irradiance`).
SAMPLES = 16


@dataclass
class CatcherPixels:
    """The centre raster's pixels that see a shadow catcher: flat indices into the (h, w) image
    (rows bottom-up, as the G-buffer's), their points and unit normals (n, 3)."""

    pix: np.ndarray
    points: np.ndarray
    normals: np.ndarray


def open_irradiance(world, normals: np.ndarray) -> np.ndarray:
    """(n, 3) float32 the world's irradiance at unit normals (n, 3) with nothing in the way: its
    sky map's (`sky_ratio.SkyIrradiance`), its SH sky's, or pi x its uniform colour."""
    n = np.asarray(normals, np.float32).reshape(-1, 3)
    table = sky_irradiance(world)
    if table is not None:
        return np.asarray(table.irradiance(n), np.float32)
    if getattr(world, "sky_sh", None) is not None:
        coeffs = np.broadcast_to(np.asarray(world.sky_sh, np.float32)[None], (n.shape[0], *world.sky_sh.shape))
        return np.maximum(sh.irradiance(coeffs, n), 0.0).astype(np.float32)
    return np.broadcast_to((np.asarray(world.color, np.float32) * np.float32(np.pi)), (n.shape[0], 3)).copy()


def light_ratio(system, pixels: CatcherPixels, irradiance: np.ndarray, frame: int,
                samples: int = SAMPLES) -> np.ndarray:
    """(n, 3) float32 the catcher pixels' light with the scene (`irradiance` (n, 3), W/m^2) over
    their light without it (the lamps unshadowed plus the open world). Per channel where that
    channel has light; a channel without takes the luminance ratio; no light at all: 1."""
    n = pixels.pix.shape[0]
    unshadowed = np.zeros((n, 3), np.float32)
    if n and system.scene.lights:
        system.direct(pixels.points, pixels.normals, frame, samples=samples, unshadowed=unshadowed)
    free = unshadowed + open_irradiance(system.scene.world, pixels.normals)
    light = np.asarray(irradiance, np.float32).reshape(n, 3)
    lum_free, lum = free @ _LUMA, light @ _LUMA
    grey = np.where(lum_free > 1e-8, lum / np.maximum(lum_free, np.float32(1e-8)), np.float32(1.0))
    ratio = np.where(free > 1e-8, light / np.maximum(free, np.float32(1e-8)), grey[:, None])
    return np.maximum(ratio, 0.0).astype(np.float32)


def compose(combined: np.ndarray, pix: np.ndarray, ratio: np.ndarray, background: np.ndarray,
            transparent: bool) -> None:
    """Write the catcher pixels `pix` (flat) of `combined` (h, w, 4), in place: an opaque film's
    world `background` (n, 3) behind them times `ratio` (n, 3), alpha 1; a transparent film's
    black with the shadow's alpha, 1 - the ratio's luminance (clipped to 0..1)."""
    flat = combined.reshape(-1, 4)
    if transparent:
        flat[pix, :3] = 0.0
        flat[pix, 3] = np.clip(1.0 - ratio @ _LUMA, 0.0, 1.0)
    else:
        flat[pix, :3] = np.asarray(background, np.float32).reshape(-1, 3) * ratio
        flat[pix, 3] = 1.0

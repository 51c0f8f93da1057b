"""An environment map (an HDRI world) split into what the renderer can light with: a shadowed sun
plus a uniform sky.

HybridGI's sky is uniform radiance (`World.color`). Spreading an HDRI's mean over the whole sky
puts its sun's energy on surfaces the sun never reaches (an atrium lit by `sunrise.exr` came out
2.3x too bright against Cycles). `split_environment` finds the map's brightest compact region
(the sun disc and its glow), turns it into a SUN lamp (direction, irradiance, angular diameter,
shadowed by the lamp code like any other), and keeps the rest as the sky's radiance: the mean a
surface facing up receives from the upper hemisphere, where the open sky of most scenes is.

Equirectangular maps follow Blender's convention (`equirect_directions`): row 0 at the bottom
(the nadir), the middle column facing +X, u growing clockwise seen from above; `to_world` maps
texture directions to world directions (the inverse of a Mapping node's transform). Pure numpy.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .sh import basis

#: Half-angle (radians) around the brightest pixel within which the sun region is looked for.
SUN_SEARCH = np.radians(12.0)
#: A pixel belongs to the sun region when brighter than this share of the brightest pixel.
SUN_THRESHOLD = 0.02
#: The region counts as a sun only if it carries this share of the light a surface facing it gets.
SUN_MIN_SHARE = 0.2
#: Rec.709 luminance weights.
LUMA = np.array([0.2126, 0.7152, 0.0722], np.float64)


@dataclass(frozen=True)
class EnvironmentSplit:
    """sun_direction : (3,) unit world direction towards the sun, None when the map has none
    sun_irradiance : (3,) W/m^2 on a surface facing the sun (a SUN lamp's colour x strength)
    sun_angle : radians, angular diameter of the region (the SUN lamp's angle)
    sky : (3,) radiance of the uniform sky that stands for the rest of the map (the mean a
        surface facing up receives)
    sky_sh : (9, 3) L2 radiance SH of the rest of the map (what probe rays that escape read)
    """

    sun_direction: np.ndarray | None
    sun_irradiance: np.ndarray
    sun_angle: float
    sky: np.ndarray
    sky_sh: np.ndarray


def equirect_directions(height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """((h, w, 3) unit texture-space directions of the pixel centres, (h,) solid angle of a pixel
    in each row). Blender/Cycles: u = (pi - atan2(y, x)) / 2pi, v = 0.5 + asin(z) / pi."""
    v = (np.arange(height) + 0.5) / height
    u = (np.arange(width) + 0.5) / width
    latitude = (v - 0.5) * np.pi
    longitude = np.pi - 2.0 * np.pi * u
    cl = np.cos(latitude)[:, None]
    dirs = np.stack(np.broadcast_arrays(cl * np.cos(longitude)[None, :], cl * np.sin(longitude)[None, :],
                                        np.sin(latitude)[:, None]), axis=-1)
    solid = (2.0 * np.pi / width) * (np.pi / height) * np.cos(latitude)
    return dirs, solid


def split_environment(pixels: np.ndarray, to_world: np.ndarray | None = None) -> EnvironmentSplit:
    """Split an (h, w, 3) linear equirectangular radiance map (see the module docstring)."""
    pixels = np.nan_to_num(np.asarray(pixels, np.float64), nan=0.0, posinf=0.0, neginf=0.0).clip(min=0.0)
    h, w = pixels.shape[:2]
    dirs, solid = equirect_directions(h, w)
    if to_world is not None:
        dirs = dirs @ np.asarray(to_world, np.float64).T
        dirs /= np.maximum(np.linalg.norm(dirs, axis=-1, keepdims=True), 1e-12)
    luma = pixels @ LUMA
    weight = np.broadcast_to(solid[:, None], luma.shape)
    peak = np.unravel_index(int(np.argmax(luma)), luma.shape)
    to_peak = dirs @ dirs[peak]  # cosine of each pixel's angle to the brightest one
    region = (to_peak > np.cos(SUN_SEARCH)) & (luma > SUN_THRESHOLD * luma[peak])
    # Light from the region on a surface facing the peak, against the whole upper hemisphere of it.
    facing_light = luma * weight * np.clip(to_peak, 0.0, None)
    region_light = float(facing_light[region].sum())
    total_light = float(facing_light.sum())
    sun = None
    irradiance = np.zeros(3)
    angle = 0.0
    filled = pixels
    if luma[peak] > 0 and region_light > SUN_MIN_SHARE * total_light:
        power = (luma * weight)[region]
        sun = (dirs[region] * power[:, None]).sum(axis=0)
        sun /= np.linalg.norm(sun)
        # Irradiance on a surface facing the sun: the region's radiance times its solid angle.
        irradiance = (pixels[region] * weight[region][:, None] * np.clip(dirs[region] @ sun, 0, None)[:, None]).sum(axis=0)
        omega = float(weight[region].sum())
        angle = float(2.0 * np.sqrt(omega / np.pi))
        # The sky behind the sun: the ring around the region, not its glow.
        ring = (to_peak > np.cos(2.0 * SUN_SEARCH)) & ~region
        fill = (pixels[ring] * weight[ring][:, None]).sum(axis=0) / max(float(weight[ring].sum()), 1e-12)
        filled = pixels.copy()
        filled[region] = fill
    # The uniform sky: the cosine-weighted mean over the upper hemisphere (irradiance / pi of an
    # unoccluded surface facing up).
    up = np.clip(dirs[..., 2], 0.0, None) * weight
    sky = (filled * up[..., None]).sum(axis=(0, 1)) / max(float(up.sum()), 1e-12)
    flat = dirs.reshape(-1, 3)
    sky_sh = basis(flat, 2).astype(np.float64).T @ (filled.reshape(-1, 3) * weight.reshape(-1, 1))
    return EnvironmentSplit(sun, irradiance.astype(np.float32), angle, sky.astype(np.float32), sky_sh.astype(np.float32))

"""The world behind the scene as the camera sees it (`environment.BackgroundMap`), on the GPU.

Why: the lighting reads an environment map as a sun, an SH sky and a coarse map
(`environment.split_environment`); the camera must see the map itself, as in Cycles (a uniform
colour there turned an HDRI's skyline into a flat grey). The deferred pass draws it on the pixels
without geometry: each pixel's view direction (through the projection the G-buffer was drawn
with, so jittered subframes anti-alias the map's detail too) is looked up in the equirectangular
map, bilinearly, exactly as `BackgroundMap.radiance` does on the CPU.

The texture holds the map with one wrap column on each side (its last column before the first,
its first after the last), so that bilinear filtering across u = 0 / 1 needs no sampler setting
that differs between Blender versions.
"""

from __future__ import annotations

import numpy as np

from .readback import upload_texture_2d

#: std140 block the deferred pass reads: inverse view-projection, world -> texture rotation,
#: (strength, texture width, 0, 0).
WORLD_TYPEDEF = """
struct WorldBlock {
  mat4 inv_view_proj;
  mat4 texture_from_world;
  vec4 params;
};
"""


def wrapped(pixels: np.ndarray) -> np.ndarray:
    """(h, w + 2, 4) float32 of an (h, w, 3) map with its wrap columns and alpha 1."""
    p = np.asarray(pixels, np.float32)
    out = np.empty((p.shape[0], p.shape[1] + 2, 4), np.float32)
    out[:, 1:-1, :3] = p
    out[:, 0, :3] = p[:, -1]
    out[:, -1, :3] = p[:, 0]
    out[..., 3] = 1.0
    return out


def world_block(background, view: np.ndarray, proj: np.ndarray, width: int) -> np.ndarray:
    """(36,) float32 std140 data of `WorldBlock` for `background` (a BackgroundMap) drawn with
    camera `view` / `proj` (4, 4, row-major as Blender gives them) into a texture `width` texels
    wide (the map's width + 2)."""
    view = np.asarray(view, np.float64).reshape(4, 4)
    proj = np.asarray(proj, np.float64).reshape(4, 4)
    inv = np.linalg.inv(proj @ view)
    rot = np.eye(4)
    rot[:3, :3] = background.texture_from_world()
    params = np.array([background.strength, float(width), 0.0, 0.0])
    return np.concatenate([inv.T.ravel(), rot.T.ravel(), params]).astype(np.float32)


def camera_rays(view: np.ndarray, proj: np.ndarray, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(points (n, 3), unit directions (n, 3)) float64 of the camera rays through NDC (x, y) (n,):
    from the near plane's point towards the far plane's, as the deferred pass finds them
    (perspective and orthographic cameras alike)."""
    inv = np.linalg.inv(np.asarray(proj, np.float64).reshape(4, 4) @ np.asarray(view, np.float64).reshape(4, 4))
    ndc = np.stack(np.broadcast_arrays(np.asarray(x, np.float64), np.asarray(y, np.float64), 0.0, 1.0),
                   axis=-1).reshape(-1, 4)

    def at(z):
        ndc[:, 2] = z
        q = ndc @ inv.T
        return q[:, :3] / q[:, 3:4]

    near = at(-1.0)
    d = at(1.0) - near
    return near, d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-30)


def pixel_directions(view: np.ndarray, proj: np.ndarray, width: int, height: int) -> np.ndarray:
    """(h * w, 3) float32 unit world directions of the rays through the pixel centres (rows
    bottom-up, as the G-buffer's), as the deferred pass finds them (`camera_rays`)."""
    x = (np.arange(width) + 0.5) / width * 2.0 - 1.0
    y = (np.arange(height) + 0.5) / height * 2.0 - 1.0
    return camera_rays(view, proj, x[None, :], y[:, None])[1].astype(np.float32)


class WorldTexture:
    """The GPU copy of the world's `BackgroundMap`: uploaded when the map changes (a new map
    object: the snapshot's world is replaced on every world edit), kept otherwise."""

    def __init__(self) -> None:
        self.background = None
        self.texture = None
        self._ubo = None

    def update(self, background) -> None:
        """Show `background` (a BackgroundMap, or None: the uniform colour). The texture is uploaded
        again only for other pixels: a world edit that changes the strength alone (its slider
        dragged in the viewport: the same split, `sync._cached_split`) keeps it, a uniform."""
        same_pixels = (background is not None and self.background is not None
                       and background.pixels is self.background.pixels)
        self.background = background
        if not same_pixels:
            self.texture = None if background is None else upload_texture_2d(wrapped(background.pixels), "RGBA16F")

    def ubo(self, view: np.ndarray, proj: np.ndarray):
        """The `WorldBlock` buffer for a draw with `view` / `proj` (a map must be set)."""
        import gpu  # noqa: PLC0415

        data = world_block(self.background, view, proj, int(self.background.pixels.shape[1]) + 2)
        if self._ubo is None:
            self._ubo = gpu.types.GPUUniformBuf(data)
        else:
            self._ubo.update(data)
        return self._ubo

    def free(self) -> None:
        self.background = self.texture = self._ubo = None

"""Lifecycle shared by every raster pass: create / resize / execute / free.

As in RTXGI's host passes, each pass owns its shaders (built in `create`) and its render targets
(allocated in `resize`, only when the size changes); `execute` draws and returns the pass's output
textures; `free` drops every GPU object (Blender frees them when the Python wrappers die). All
targets are scene-linear float (RGBA16F / RGBA32F / R32F). Image rows are bottom-up everywhere.
"""

from __future__ import annotations

import logging
from contextlib import contextmanager

import numpy as np

from ..errors import HybridGIError
from .glsl import ShaderSpec, build_shader, load_glsl

log = logging.getLogger(__name__)

#: View depth written where no geometry was hit (Cycles' Depth pass uses 1e10 for the background).
BACKGROUND_DEPTH = 1.0e10


class RasterError(HybridGIError):
    """A raster pass was used out of its lifecycle or with inputs of the wrong size."""


def low_res_size(width: int, height: int, factor: int) -> tuple[int, int]:
    """Size of the downsampled images: each low-res pixel covers a factor x factor block
    (the last block of a row/column may be cut by the image border)."""
    return -(-int(width) // int(factor)), -(-int(height) // int(factor))


def camera_block(view: np.ndarray, proj: np.ndarray) -> np.ndarray:
    """std140 data of the `CameraBlock` struct (CAMERA_TYPEDEF below).

    view, proj : (4, 4) row-major world->camera and camera->clip matrices as Blender gives them
    (`matrix_world.inverted()` and `calc_matrix_camera`), perspective or orthographic.
    Returns (20,) float32: view_proj column-major (GLSL mat4 layout), then the view matrix's third
    row, whose dot product with (p, 1) is minus the view-axis depth of p.
    """
    view = np.asarray(view, np.float64).reshape(4, 4)
    proj = np.asarray(proj, np.float64).reshape(4, 4)
    view_proj = proj @ view
    return np.concatenate([view_proj.T.ravel(), view[2]]).astype(np.float32)


CAMERA_TYPEDEF = """
struct CameraBlock {
  mat4 view_proj;
  vec4 view_z;
};
"""


def fullscreen_spec(name: str, fragment: str, **kwargs) -> ShaderSpec:
    """ShaderSpec of a full-screen pass: one big triangle, the fragment shader uses gl_FragCoord."""
    return ShaderSpec(
        name=name,
        vertex=load_glsl("fullscreen_vert.glsl"),
        fragment=fragment,
        vertex_in=((0, "VEC2", "pos"),),
        **kwargs,
    )


def fullscreen_batch():
    """A GPUBatch of one triangle covering clip space [-1, 1]^2 (no diagonal seam, one draw)."""
    import gpu  # noqa: PLC0415

    fmt = gpu.types.GPUVertFormat()
    fmt.attr_add(id="pos", comp_type="F32", len=2, fetch_mode="FLOAT")
    vbo = gpu.types.GPUVertBuf(fmt, 3)
    vbo.attr_fill("pos", ((-1.0, -1.0), (3.0, -1.0), (-1.0, 3.0)))
    return gpu.types.GPUBatch(type="TRIS", buf=vbo)


@contextmanager
def draw_state(depth_test: str = "NONE", depth_mask: bool = False):
    """Sets depth test/write and no blending for a pass, then restores what was set before
    (the add-on draws inside Blender's own viewport state)."""
    import gpu  # noqa: PLC0415

    old = (gpu.state.depth_test_get(), gpu.state.depth_mask_get(), gpu.state.blend_get())
    gpu.state.depth_test_set(depth_test)
    gpu.state.depth_mask_set(depth_mask)
    gpu.state.blend_set("NONE")
    try:
        yield
    finally:
        gpu.state.depth_test_set(old[0])
        gpu.state.depth_mask_set(old[1])
        gpu.state.blend_set(old[2])


def make_target(width: int, height: int, fmt: str):
    import gpu  # noqa: PLC0415

    return gpu.types.GPUTexture((int(width), int(height)), format=fmt)


def check_size(texture, width: int, height: int, what: str) -> None:
    if (texture.width, texture.height) != (width, height):
        raise RasterError(f"{what} is {texture.width}x{texture.height}, expected {width}x{height}")


class RasterPass:
    """Base of the raster passes.

    Subclasses implement `_build_shaders() -> dict`, `_allocate(width, height)` (targets and
    framebuffers for that size) and `_release_targets()`; `execute(...)` is pass-specific and
    starts with `self._require()`.
    """

    name = "raster pass"

    def __init__(self) -> None:
        self._shaders: dict | None = None
        self._fullscreen = None
        self.width = 0
        self.height = 0

    # -- lifecycle ---------------------------------------------------------------------------
    def create(self) -> None:
        """Compile the shaders (idempotent). Needs Blender's GPU context."""
        if self._shaders is None:
            self._fullscreen = fullscreen_batch()
            self._shaders = self._build_shaders()

    def resize(self, width: int, height: int) -> None:
        """(Re)allocate render targets for `width` x `height` pixels when the size changed."""
        width, height = int(width), int(height)
        if width < 1 or height < 1:
            raise RasterError(f"{self.name}: invalid size {width}x{height}")
        if (width, height) != (self.width, self.height):
            self._release_targets()
            self._allocate(width, height)
            self.width, self.height = width, height

    def free(self) -> None:
        """Drop every GPU object; `create` + `resize` make the pass usable again."""
        self._release_targets()
        self._shaders = None
        self._fullscreen = None
        self.width = self.height = 0

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.free()

    # -- for subclasses ----------------------------------------------------------------------
    def _require(self) -> None:
        if self._shaders is None:
            self.create()
        if self.width == 0:
            raise RasterError(f"{self.name}: call resize() before execute()")

    def _build_shaders(self) -> dict:
        raise NotImplementedError

    def _allocate(self, width: int, height: int) -> None:
        raise NotImplementedError

    def _release_targets(self) -> None:
        raise NotImplementedError

    def _shader(self, key: str = "main"):
        return self._shaders[key]

    def _draw_fullscreen(self, fb, shader, size: tuple[int, int]) -> None:
        """Run `shader` over every pixel of `fb`, whose targets are `size` = (w, h)."""
        import gpu  # noqa: PLC0415

        with fb.bind():
            gpu.state.viewport_set(0, 0, int(size[0]), int(size[1]))
            with draw_state():
                self._fullscreen.draw(shader)


def compile_spec(spec: ShaderSpec):
    """`build_shader`, with the pass name in the error when the driver rejects the GLSL."""
    try:
        return build_shader(spec)
    except Exception as exc:  # Blender raises a bare Exception with the compile log
        raise RasterError(f"shader {spec.name!r} failed to compile: {exc}") from exc

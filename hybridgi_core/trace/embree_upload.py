"""Triangle upload into an embreex scene through Embree's own C API, without embreex's copy loop.

embreex's `TriangleMesh` copies every vertex coordinate and every triangle index through Python
indexing of untyped numpy arrays (`tri_vertices[i, 0]`, `tri_indices[i][0]`): ~0.4 s of a
single thread for a 300k-triangle scene, three times Embree's own BVH build of it, and again for
every frame of a deforming mesh. The same library that embreex loaded (`libembree4` in its
wheel) takes the buffers written straight into its own: `rtcNewGeometry`, `rtcSetNewGeometryBuffer`
(Embree owns and pads them, so nothing has to outlive the call), `rtcCommitGeometry`,
`rtcAttachGeometry` - what `TriangleMesh` does, in C, with the same layout (16-byte vertices,
uint32 triangles), so Embree builds the same BVH and every hit is bit for bit the same (tested).

The scene handle is a private field of embreex's Cython `EmbreeScene`. It is found, once per
process, from a layout check rather than assumed: toggling the public `is_committed` field shows
its offset, the field declared before it (`scene_i`, a pointer) sits 8 bytes earlier, and the
field after it must hold the `EmbreeDevice` object the scene was made with. Anything unexpected
(another embreex layout, no library found, an Embree error) makes `upload` return False and the
caller uses `TriangleMesh`.
"""

from __future__ import annotations

import ctypes
import logging
import sys
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

_GEOMETRY_TYPE_TRIANGLE = 0
_BUFFER_TYPE_INDEX = 0
_BUFFER_TYPE_VERTEX = 1
_FORMAT_UINT3 = 0x5003
_FORMAT_FLOAT3 = 0x9003
_PROBE = 0x5A5A1234

_state: dict = {}


def _library_paths() -> list[Path]:
    """Embree shared libraries shipped with embreex (linux: embreex.libs/, macOS: embreex/.dylibs/,
    Windows: embreex.libs/ or beside the package)."""
    import embreex  # noqa: PLC0415

    pkg = Path(embreex.__file__).resolve().parent
    found = []
    for folder in (pkg.parent / "embreex.libs", pkg / ".dylibs", pkg, pkg.parent):
        if folder.is_dir():
            found += sorted(p for p in folder.iterdir() if "embree4" in p.name and _is_library(p.name))
    return found


def _is_library(name: str) -> bool:
    return name.endswith((".so", ".dll", ".dylib")) or ".so." in name


def _bind(lib) -> None:
    vp, c_int, c_uint, size = ctypes.c_void_p, ctypes.c_int, ctypes.c_uint, ctypes.c_size_t
    for name, res, args in (
        ("rtcGetSceneDevice", vp, [vp]),
        ("rtcNewGeometry", vp, [vp, c_int]),
        ("rtcSetNewGeometryBuffer", vp, [vp, c_int, c_uint, c_int, size, size]),
        ("rtcCommitGeometry", None, [vp]),
        ("rtcAttachGeometry", c_uint, [vp, vp]),
        ("rtcReleaseGeometry", None, [vp]),
        ("rtcReleaseDevice", None, [vp]),
        ("rtcGetDeviceError", c_int, [vp]),
    ):
        fn = getattr(lib, name)
        fn.restype, fn.argtypes = res, args


def _scene_offset(scene_type, device) -> int | None:
    """Byte offset of `scene_i` in embreex's EmbreeScene, checked on a scratch scene; None when the
    layout is not the expected one."""
    probe = scene_type(device)
    size = type(probe).__basicsize__
    before = ctypes.string_at(id(probe), size)
    probe.is_committed = _PROBE
    after = ctypes.string_at(id(probe), size)
    probe.is_committed = 0
    changed = [i for i in range(size) if before[i] != after[i]]
    if not changed:
        return None
    at = changed[0] - changed[0] % 4
    if at < 8 + 16 or at + 16 > size or after[at : at + 4] != _PROBE.to_bytes(4, sys.byteorder):
        return None
    if int.from_bytes(after[at + 8 : at + 16], sys.byteorder) != id(device):
        return None  # the field after is_committed is not the scene's EmbreeDevice
    if ctypes.c_void_p.from_address(id(probe) + at - 8).value is None:
        return None
    return at - 8


def _setup(scene_type, device):
    """(library, scene-handle offset), or None: found once per process."""
    if "lib" in _state:
        return _state["lib"]
    result = None
    try:
        offset = _scene_offset(scene_type, device)
        for path in _library_paths() if offset is not None else []:
            try:
                lib = ctypes.CDLL(str(path))
                _bind(lib)
            except (OSError, AttributeError):
                continue
            result = (lib, offset)
            break
    except Exception as exc:  # noqa: BLE001 - any surprise means the slow, safe path
        log.info("embree upload: C API path unavailable (%s); using embreex's TriangleMesh", exc)
        result = None
    if result is None:
        log.info("embree upload: C API path unavailable; using embreex's TriangleMesh")
    _state["lib"] = result
    return result


def available(scene_type, device) -> bool:
    """Whether `upload` can attach meshes to scenes of `scene_type` made with `device` (the C
    API path was found), so vertex copies cost a memmove, not a Python call per vertex."""
    return _setup(scene_type, device) is not None


def upload(scene, device, vertices: np.ndarray, triangles: np.ndarray) -> bool:
    """Attach one triangle mesh (vertices (m, 3) float, triangles (k, 3) indices < m) to the
    uncommitted embreex `scene` made with `device`; False (scene untouched) when the C API path is
    unavailable, so the caller falls back to `TriangleMesh`."""
    setup = _setup(type(scene), device)
    if setup is None:
        return False
    lib, offset = setup
    handle = ctypes.c_void_p.from_address(id(scene) + offset).value
    if not handle:
        return False
    n_vert, n_tri = vertices.shape[0], triangles.shape[0]
    dev = lib.rtcGetSceneDevice(handle)
    if not dev:
        return False
    try:
        geom = lib.rtcNewGeometry(dev, _GEOMETRY_TYPE_TRIANGLE)
        if not geom:
            return False
        vb = lib.rtcSetNewGeometryBuffer(geom, _BUFFER_TYPE_VERTEX, 0, _FORMAT_FLOAT3, 16, n_vert)
        ib = lib.rtcSetNewGeometryBuffer(geom, _BUFFER_TYPE_INDEX, 0, _FORMAT_UINT3, 12, n_tri)
        if not vb or not ib:
            lib.rtcReleaseGeometry(geom)
            return False
        # Written in place through numpy views of Embree's buffers (one pass each: no padded copy
        # to memmove, ~30 MB of first touches fewer for the atrium's 960k corners); the pad
        # float 0, as the padded copy had it.
        try:
            v4 = _view(vb, (n_vert, 4), np.float32)
            v4[:, :3] = vertices
            v4[:, 3] = 0.0
            _view(ib, (n_tri, 3), np.uint32)[...] = triangles
        except BaseException:
            lib.rtcReleaseGeometry(geom)  # (arrays of another shape: nothing attached)
            raise
        lib.rtcCommitGeometry(geom)
        lib.rtcAttachGeometry(handle, geom)
        lib.rtcReleaseGeometry(geom)  # the scene holds its own reference
        error = lib.rtcGetDeviceError(dev)
    finally:
        lib.rtcReleaseDevice(dev)  # rtcGetSceneDevice's extra reference
    if error:
        raise RuntimeError(f"Embree error {error} while uploading {n_tri} triangles")
    return True


def _view(address: int, shape: tuple[int, int], dtype) -> np.ndarray:
    """A writable numpy array over `shape` elements of `dtype` at `address` (memory Embree owns)."""
    count = shape[0] * shape[1]
    buffer = (ctypes.c_byte * (count * np.dtype(dtype).itemsize)).from_address(address)
    return np.frombuffer(buffer, dtype, count).reshape(shape)

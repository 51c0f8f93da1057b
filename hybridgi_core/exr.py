"""Read the multilayer EXRs the CLI writes, without bpy or OpenImageIO (neither ships a reader the
tests can use: bpy only exposes a multilayer image's first pass).

Covers what Blender writes: single- or multi-part scanline files, compression NONE, ZIPS or ZIP,
HALF / FLOAT / UINT channels. Channel names are Blender's `<ViewLayer>.<Pass>.<channel>`, as
in the file (`hybridgi_cli.exr` reads them under Blender 5.0's pass names). bpy-free: the CLI, the
tests and the add-on's Compare with Cycles operator read renders with it.
"""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np

MAGIC = 20000630
_MULTIPART = 0x1000
_TILED = 0x200
_PIXEL_DTYPES = {0: np.dtype("<u4"), 1: np.dtype("<f2"), 2: np.dtype("<f4")}
_LINES_PER_CHUNK = {0: 1, 2: 1, 3: 16}  # NONE, ZIPS, ZIP
_COMPRESSION_NAMES = ("NONE", "RLE", "ZIPS", "ZIP", "PIZ", "PXR24", "B44", "B44A", "DWAA", "DWAB")


class ExrError(ValueError):
    """Not an EXR file, or one using a feature this reader does not cover."""


def channel_names(path: str | Path) -> list[str]:
    """Names of all channels of all parts, in file order."""
    data = Path(path).read_bytes()
    headers, _ = _headers(data)
    return [name for header in headers for name, _type in header["channels"]]


def read_channels(path: str | Path) -> dict[str, np.ndarray]:
    """Every channel as an (h, w) float32 array, row 0 at the top of the image (EXR order;
    Blender's `RenderPass.rect` and `Image.pixels` are bottom-up)."""
    data = Path(path).read_bytes()
    headers, pos = _headers(data)
    tables = []
    for header in headers:
        count = header["chunks"]
        tables.append(struct.unpack_from(f"<{count}Q", data, pos))
        pos += 8 * count
    multipart = len(headers) > 1 or headers[0]["multipart"]
    out = {}
    for header, table in zip(headers, tables, strict=True):
        out.update(_read_part(data, header, table, multipart))
    return out


def _headers(data: bytes):
    if len(data) < 8:
        raise ExrError("file too short for an EXR header")
    magic, version = struct.unpack_from("<ii", data, 0)
    if magic != MAGIC:
        raise ExrError("not an OpenEXR file")
    if version & _TILED:
        raise ExrError("tiled EXR files are not supported")
    multipart = bool(version & _MULTIPART)
    pos = 8
    headers = []
    while True:
        header, pos = _header(data, pos)
        header["multipart"] = multipart
        headers.append(header)
        if not multipart:
            break
        if data[pos] == 0:  # an empty header ends the list of parts
            pos += 1
            break
    return headers, pos


def _header(data: bytes, pos: int):
    attrs = {}
    while True:
        name, pos = _cstring(data, pos)
        if not name:
            break
        kind, pos = _cstring(data, pos)
        (size,) = struct.unpack_from("<i", data, pos)
        pos += 4
        attrs[name] = (kind, data[pos : pos + size])
        pos += size
    if attrs.get("type", ("", b"scanlineimage"))[1].rstrip(b"\0") not in (b"scanlineimage",):
        raise ExrError("only scanline parts are supported")
    xmin, ymin, xmax, ymax = struct.unpack("<4i", attrs["dataWindow"][1])
    compression = attrs["compression"][1][0]
    if compression not in _LINES_PER_CHUNK:
        raise ExrError(f"compression {_COMPRESSION_NAMES[compression]} is not supported")
    height = ymax - ymin + 1
    lines = _LINES_PER_CHUNK[compression]
    return {
        "channels": _channels(attrs["channels"][1]),
        "window": (xmin, ymin, xmax - xmin + 1, height),
        "compression": compression,
        "lines": lines,
        "chunks": -(-height // lines),
    }, pos


def _channels(raw: bytes):
    channels, pos = [], 0
    while raw[pos] != 0:
        name, pos = _cstring(raw, pos)
        (pixel_type,) = struct.unpack_from("<i", raw, pos)
        pos += 16  # type, pLinear + 3 reserved bytes, x and y sampling
        channels.append((name, pixel_type))
    return channels


def _cstring(data: bytes, pos: int):
    end = data.index(b"\0", pos)
    return data[pos:end].decode("utf-8"), end + 1


def _read_part(data: bytes, header, table, multipart: bool):
    xmin, ymin, width, height = header["window"]
    channels = header["channels"]
    dtypes = [_PIXEL_DTYPES[t] for _n, t in channels]
    planes = [np.empty((height, width), np.float32) for _ in channels]
    row_bytes = sum(width * d.itemsize for d in dtypes)
    for offset in table:
        pos = offset + (4 if multipart else 0)  # the part number precedes each chunk
        y, size = struct.unpack_from("<ii", data, pos)
        raw = data[pos + 8 : pos + 8 + size]
        first = y - ymin
        n_lines = min(header["lines"], height - first)
        expected = n_lines * row_bytes
        if header["compression"] != 0 and size < expected:
            raw = _unzip(raw, expected)
        rows = np.frombuffer(raw, np.uint8, expected).reshape(n_lines, row_bytes)
        start = 0
        for plane, dtype in zip(planes, dtypes, strict=True):
            stop = start + width * dtype.itemsize
            plane[first : first + n_lines] = rows[:, start:stop].copy().view(dtype).astype(np.float32)
            start = stop
    return {name: plane for (name, _t), plane in zip(channels, planes, strict=True)}


def _unzip(raw: bytes, expected: int) -> bytes:
    """Inverse of OpenEXR's ZIP filter: zlib, then undo the byte delta and the even/odd split."""
    t = np.frombuffer(zlib.decompress(raw), np.uint8)
    if t.size != expected:
        raise ExrError("corrupt ZIP chunk")
    t = np.cumsum(np.concatenate(([t[0]], t[1:].astype(np.int64) - 128))).astype(np.uint8)
    out = np.empty_like(t)
    half = (t.size + 1) // 2
    out[0::2] = t[:half]
    out[1::2] = t[half:]
    return out.tobytes()

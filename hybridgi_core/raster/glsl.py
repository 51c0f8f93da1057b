"""GLSL sources beside the passes, and one builder for `gpu.shader.create_from_info`.

Shader text lives in `.glsl` files next to the pass that uses it (named for what it does);
`load_glsl` joins several files so shared helpers (`common_lib.glsl`, `bilateral_lib.glsl`) are
plain text prepended to a stage, since `create_from_info` has no `#include`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path

log = logging.getLogger(__name__)

_HERE = Path(__file__).resolve().parent


@cache
def _read(name: str) -> str:
    path = _HERE / name
    if not path.is_file():
        raise FileNotFoundError(f"GLSL source {name!r} not found beside {__name__} ({path})")
    return path.read_text(encoding="utf-8")


def load_glsl(*names: str) -> str:
    """Concatenated text of the named `.glsl` files of this folder, in order."""
    return "\n".join(f"/* ---- {n} ---- */\n{_read(n)}" for n in names)


@dataclass
class ShaderSpec:
    """Declarative description of one graphics shader.

    vertex_in : (slot, type, name) tuples, e.g. (0, "VEC3", "pos")
    varyings : (qualifier, type, name) with qualifier "smooth" | "flat" | "no_perspective"
    samplers : (slot, type, name), e.g. (0, "FLOAT_2D", "albedo_tx")
    push : (type, name) push constants (keep under 128 bytes: larger blocks warn on OpenGL)
    ubos : (slot, struct_name, name) uniform blocks of structs in `typedefs`
    outputs : (slot, type, name) fragment outputs = framebuffer colour slots
    defines : name -> value (value may be "")
    """

    name: str
    vertex: str
    fragment: str
    vertex_in: tuple = ()
    varyings: tuple = ()
    samplers: tuple = ()
    push: tuple = ()
    ubos: tuple = ()
    outputs: tuple = ()
    typedefs: str = ""
    defines: dict = field(default_factory=dict)


def build_shader(spec: ShaderSpec):
    """Compile `spec` with `gpu.shader.create_from_info` (the only constructor in Blender 5)."""
    import gpu  # noqa: PLC0415  (raster modules import gpu lazily: only valid inside Blender)

    info = gpu.types.GPUShaderCreateInfo()
    for name, value in spec.defines.items():
        info.define(name, str(value))
    if spec.typedefs:
        info.typedef_source(spec.typedefs)
    for slot, struct_name, name in spec.ubos:
        info.uniform_buf(slot, struct_name, name)
    for slot, kind, name in spec.vertex_in:
        info.vertex_in(slot, kind, name)
    # Keep the interface object alive until compilation: create_info stores a reference to it.
    iface = None
    if spec.varyings:
        iface = gpu.types.GPUStageInterfaceInfo(f"{spec.name}_iface")
        for qualifier, kind, name in spec.varyings:
            getattr(iface, qualifier)(kind, name)
        info.vertex_out(iface)
    for slot, kind, name in spec.samplers:
        info.sampler(slot, kind, name)
    for kind, name in spec.push:
        info.push_constant(kind, name)
    for slot, kind, name in spec.outputs:
        info.fragment_out(slot, kind, name)
    info.vertex_source(spec.vertex)
    info.fragment_source(spec.fragment)
    shader = gpu.shader.create_from_info(info)
    del iface
    log.debug("compiled shader %s", spec.name)
    return shader

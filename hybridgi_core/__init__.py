"""HybridGI core: bpy-free numerics of the hybrid ray/raster irradiance cache.

Nothing here imports bpy, gpu or mathutils at module level; `hybridgi_core.raster` does so lazily
and only works inside Blender.
"""

__version__ = "0.1.0"

"""HybridGI: real-time global illumination from a ray-traced irradiance cache and raster passes.

Blender loads this package as an extension (metadata in blender_manifest.toml). The numerics live
in `hybridgi_core`, imported by its own name: the development checkout installs it in the Python
environment, the extension zip ships it as a wheel that Blender installs with the extension.
"""

from . import animation, compare, engine, overlay, properties, ui

# Registration order: properties first (panels and the engine read `scene.hybridgi`); animation
# last, so its handlers are removed first and any kept render cache is freed on unregister.
_modules = (properties, engine, overlay, ui, compare, animation)


def register():
    for module in _modules:
        module.register()


def unregister():
    for module in reversed(_modules):
        module.unregister()

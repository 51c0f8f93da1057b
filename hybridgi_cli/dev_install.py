"""Enable the add-on from this checkout in the running Blender (bpy module or Blender itself).

Blender only loads extensions from a repository folder that holds one folder per extension, named
by its id. The checkout's `addon/` is exposed that way without copying: a staging folder holds a
symlink `hybridgi -> <checkout>/addon`, and a user repository points at the staging folder, so
edits in the checkout are what Blender imports. `addon/blender_manifest.toml` is itself a symlink
to the checkout's `manifest.toml`.
"""

from __future__ import annotations

import importlib
from pathlib import Path

#: Repository module name: the add-on is imported as `bl_ext.hybridgi_dev.hybridgi`.
REPO_MODULE = "hybridgi_dev"
ADDON_ID = "hybridgi"
ENGINE_ID = "HYBRIDGI"

#: The add-on package of the checkout this module belongs to.
ADDON_DIR = Path(__file__).resolve().parents[1] / "addon"


class DevInstallError(RuntimeError):
    """The checkout's add-on could not be enabled."""


def addon_module_name() -> str:
    return f"bl_ext.{REPO_MODULE}.{ADDON_ID}"


def engine_registered() -> bool:
    """Whether a RenderEngine with bl_idname HYBRIDGI is registered right now."""
    import bpy  # noqa: PLC0415  (bpy must be imported after BLENDER_USER_RESOURCES is set)

    # `is_registered`: an unregistered class stays in __subclasses__() until garbage-collected.
    return any(
        getattr(cls, "bl_idname", None) == ENGINE_ID and cls.is_registered
        for cls in bpy.types.RenderEngine.__subclasses__()
    )


def enable(staging: Path | None = None, addon_dir: Path = ADDON_DIR):
    """Enable the checkout's add-on; idempotent. Returns the add-on's package module.

    staging : the repository folder that holds the symlink; default `<Blender user resources>/
        hybridgi_dev_repo`, which is a temporary folder when BLENDER_USER_RESOURCES points at one.

    Raises DevInstallError when the staging folder holds something else than our symlink, when
    Blender fails to import or register the add-on, or when no HYBRIDGI engine results.
    """
    import addon_utils  # noqa: PLC0415
    import bpy  # noqa: PLC0415

    addon_dir = Path(addon_dir).resolve()
    if not (addon_dir / "__init__.py").is_file() or not (addon_dir / "blender_manifest.toml").is_file():
        raise DevInstallError(f"{addon_dir} is not an extension folder (needs __init__.py and blender_manifest.toml)")
    staging = Path(staging) if staging is not None else Path(bpy.utils.resource_path("USER")) / "hybridgi_dev_repo"
    _link(staging, addon_dir)
    _ensure_repo(bpy.context.preferences.extensions.repos, staging)

    name = addon_module_name()
    failures: list[BaseException] = []
    module = addon_utils.enable(name, default_set=True, handle_error=failures.append)
    if failures:
        raise DevInstallError(f"enabling {name} failed: {failures[0]!r}") from failures[0]
    if module is None:
        # addon_utils returns None without calling handle_error when the module cannot be found.
        raise DevInstallError(f"Blender did not find {name} in {staging}")
    if not engine_registered():
        raise DevInstallError(f"{name} is enabled but no {ENGINE_ID} render engine is registered")
    return importlib.import_module(name)


def disable() -> None:
    """Disable the add-on again (unregisters the engine and `scene.hybridgi`)."""
    import addon_utils  # noqa: PLC0415

    addon_utils.disable(addon_module_name(), default_set=True)


def _link(staging: Path, addon_dir: Path) -> None:
    staging.mkdir(parents=True, exist_ok=True)
    link = staging / ADDON_ID
    if link.is_symlink():
        if link.resolve() == addon_dir:
            return
        link.unlink()  # a link to another checkout: ours replaces it
    elif link.exists():
        raise DevInstallError(f"{link} exists and is not a symlink; remove it or pass another staging folder")
    link.symlink_to(addon_dir, target_is_directory=True)


def _ensure_repo(repos, staging: Path) -> None:
    repo = next((r for r in repos if r.module == REPO_MODULE), None)
    if repo is None:
        repos.new(name="HybridGI checkout", module=REPO_MODULE, custom_directory=str(staging), source="USER")
        return
    if Path(repo.directory).resolve() != staging.resolve():
        repo.use_custom_directory = True
        repo.custom_directory = str(staging)
    repo.enabled = True

"""Build the installable HybridGI extension zips (`make extension`): one per platform, into dist/.

1. Wheels: every dependency pinned in pyproject.toml except the ones Blender ships (numpy), for each
   platform of manifest.toml and each Python of PYTHON_VERSIONS, from PyPI into a cache
   (build/wheels/<platform>/<python>/) that later builds reuse offline.
2. The core as a wheel of its own (`core_wheel`: pure Python, built here from `hybridgi_core/`,
   byte-for-byte reproducible), so the add-on imports it by its plain name `hybridgi_core` in
   both layouts: a checkout installs it in the Python environment, Blender installs the zip's
   wheel with the extension.
3. A clean staged source folder, build/extension/hybridgi/: the add-on's files, `wheels/`, and
   `blender_manifest.toml` = manifest.toml plus the `wheels = [...]` list.
4. Blender's own tool (it ships inside the bpy package): `blender_ext.py build --split-platforms`.
5. Each zip: `blender_ext.py validate`, then a check that it holds exactly its platform's wheels
   and the core's, the add-on, the core wheel with its .glsl files, and no __pycache__ or tests.

A build whose inputs (sources, manifest, pins, this script) are unchanged since the last one only
re-checks the zips in dist/.
"""

from __future__ import annotations

import argparse
import base64
import dataclasses
import hashlib
import importlib.util
import io
import json
import logging
import re
import shutil
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

log = logging.getLogger("build_extension")

REPO = Path(__file__).resolve().parents[1]
ADDON_DIR = REPO / "addon"
CORE_DIR = REPO / "hybridgi_core"
MANIFEST = REPO / "manifest.toml"
PYPROJECT = REPO / "pyproject.toml"
DIST = REPO / "dist"
WHEEL_CACHE = REPO / "build" / "wheels"
STAGE_ROOT = REPO / "build" / "extension"

#: Blender 4.2-5.0 bundle Python 3.11, Blender 5.1+ Python 3.13.
PYTHON_VERSIONS = ("3.11", "3.13")

#: Dependencies Blender already ships in its own Python: bundling a second numpy would shadow it.
SHIPPED_WITH_BLENDER = frozenset({"numpy"})

#: The pip platform tag each Blender platform downloads for; pip also accepts older tags of the
#: same kind (older manylinux, older macOS). Blender 4.2+ on Linux needs glibc 2.28. embreex's
#: macOS wheels need macOS 13 (Blender itself runs on 11.2+): the oldest tag that has every wheel.
PIP_PLATFORMS = {
    "linux-x64": "manylinux_2_28_x86_64",
    "windows-x64": "win_amd64",
    "macos-arm64": "macosx_13_0_arm64",
    "macos-x64": "macosx_13_0_x86_64",
}

#: Paths never copied into the staged folder.
STAGE_IGNORE = shutil.ignore_patterns("__pycache__", "*.pyc", "tests", ".*", "blender_manifest.toml")

#: Ends a pip download that cannot reach the index quickly (the default retries for minutes).
PIP_NETWORK_ARGS = ("--timeout", "20", "--retries", "1")


class BuildError(RuntimeError):
    """The extension could not be built or a built zip is not what it should be."""


class WheelsUnavailable(BuildError):
    """A wheel is neither in the cache nor downloadable (no network, or not published)."""


@dataclasses.dataclass(frozen=True)
class PlatformZip:
    """One built zip: its Blender platform and the wheel file names it must hold."""

    path: Path
    platform: str
    wheels: tuple[str, ...]


# ----------------------------------------------------------------------------------------------
# Inputs


def read_manifest() -> tuple[str, dict]:
    text = MANIFEST.read_text(encoding="utf-8")
    data = tomllib.loads(text)
    if "wheels" in data:
        raise BuildError(f"{MANIFEST.name} lists wheels itself; the build fills them in (see its comment)")
    platforms = data.get("platforms") or []
    unknown = sorted(set(platforms) - set(PIP_PLATFORMS))
    if not platforms or unknown:
        raise BuildError(f"{MANIFEST.name}: platforms must be a non-empty subset of {sorted(PIP_PLATFORMS)}")
    return text, data


def bundled_requirements() -> list[tuple[str, str]]:
    """(name, version) of the dependencies the extension bundles: pyproject's pins minus numpy
    (whose pins carry environment markers: each Blender's Python has its own numpy)."""
    dependencies = tomllib.loads(PYPROJECT.read_text(encoding="utf-8"))["project"]["dependencies"]
    pins = []
    for spec in dependencies:
        match = re.fullmatch(r"\s*([A-Za-z0-9][A-Za-z0-9._-]*)\s*==\s*([^\s;]+)\s*(;.*)?", spec)
        if match is None:
            raise BuildError(f"pyproject.toml: dependency {spec!r} is not pinned with == (wheels must be exact)")
        name, version, marker = match.groups()
        if normalized(name) in {normalized(n) for n in SHIPPED_WITH_BLENDER}:
            continue
        if marker:
            raise BuildError(f"pyproject.toml: bundled dependency {spec!r} must hold for every Python (no marker)")
        pins.append((name, version))
    return pins


def normalized(name: str) -> str:
    """A distribution name as wheel file names spell it (PEP 427/503): `fast-simplification` ->
    `fast_simplification`."""
    return re.sub(r"[-_.]+", "_", name).lower()


def blender_ext_tool() -> Path:
    """`blender_ext.py` from the bpy package of this Python (found without importing bpy)."""
    spec = importlib.util.find_spec("bpy")
    if spec is None or not spec.submodule_search_locations:
        raise BuildError("the bpy package is not installed in this Python (run `make setup`)")
    bpy_dir = Path(next(iter(spec.submodule_search_locations)))
    found = sorted(bpy_dir.glob("*/scripts/addons_core/bl_pkg/cli/blender_ext.py"))
    if not found:
        raise BuildError(f"Blender's extension tool is not inside {bpy_dir}")
    return found[-1]


def inputs_digest(tool: Path) -> str:
    """Hash of everything a build reads except the wheels (which the pins in pyproject fix)."""
    digest = hashlib.sha256()
    files = [MANIFEST, PYPROJECT, Path(__file__).resolve(), tool]
    for folder in (ADDON_DIR, CORE_DIR):
        files += [p for p in folder.rglob("*") if p.is_file() and "__pycache__" not in p.parts]
    for path in sorted(files):
        digest.update(str(path.relative_to(REPO) if path.is_relative_to(REPO) else path).encode())
        digest.update(hashlib.sha256(path.read_bytes()).digest())
    return digest.hexdigest()


# ----------------------------------------------------------------------------------------------
# Wheels


def fetch_wheels(platforms: list[str], cache: Path = WHEEL_CACHE) -> dict[str, list[Path]]:
    """{Blender platform: wheel files} for every bundled pin and Python; downloads what the cache
    lacks. Raises WheelsUnavailable when pip cannot get one."""
    pins = bundled_requirements()
    result: dict[str, list[Path]] = {}
    for platform in platforms:
        wheels: dict[str, Path] = {}  # by file name: a pure-Python wheel serves both Pythons
        for python in PYTHON_VERSIONS:
            folder = cache / platform / f"cp{python.replace('.', '')}"
            missing = [(n, v) for n, v in pins if not _cached(folder, n, v)]
            if missing:
                _pip_download(folder, platform, python, missing)
            for name, version in pins:
                wheel = _cached(folder, name, version)
                if wheel is None:
                    raise WheelsUnavailable(f"pip reported success but no {name}=={version} wheel is in {folder}")
                _check_dependencies(wheel, pins)
                wheels[wheel.name] = wheel
        result[platform] = sorted(wheels.values())
    return result


def _cached(folder: Path, name: str, version: str) -> Path | None:
    found = sorted(folder.glob(f"{normalized(name)}-{version}-*.whl")) if folder.is_dir() else []
    if len(found) > 1:
        raise BuildError(f"{folder} holds several {name}=={version} wheels: {[p.name for p in found]}")
    return found[0] if found else None


def _pip_download(folder: Path, platform: str, python: str, pins: list[tuple[str, str]]) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    abi = f"cp{python.replace('.', '')}"
    command = [
        sys.executable, "-m", "pip", "download", "--quiet", "--disable-pip-version-check",
        "--only-binary=:all:", "--no-deps", *PIP_NETWORK_ARGS,
        "--platform", PIP_PLATFORMS[platform], "--python-version", python,
        "--implementation", "cp", "--abi", abi,
        "--dest", str(folder),
        *(f"{name}=={version}" for name, version in pins),
    ]
    log.info("downloading %s for %s, Python %s", ", ".join(n for n, _v in pins), platform, python)
    run = subprocess.run(command, capture_output=True, text=True)
    if run.returncode != 0:
        raise WheelsUnavailable(
            f"pip could not download {pins} for {platform} / Python {python}:\n{run.stderr.strip()[-2000:]}"
        )


def _check_dependencies(wheel: Path, pins: list[tuple[str, str]]) -> None:
    """Blender installs no dependencies: each wheel's must be bundled too or ship with Blender."""
    with zipfile.ZipFile(wheel) as archive:
        metadata = next(n for n in archive.namelist() if n.endswith(".dist-info/METADATA"))
        lines = archive.read(metadata).decode("utf-8", "replace").splitlines()
    available = {normalized(n) for n, _v in pins} | {normalized(n) for n in SHIPPED_WITH_BLENDER}
    for line in lines:
        if not line.startswith("Requires-Dist:") or "extra ==" in line:
            continue
        requirement = re.match(r"Requires-Dist:\s*([A-Za-z0-9][A-Za-z0-9._-]*)", line)
        if requirement and normalized(requirement.group(1)) not in available:
            raise BuildError(f"{wheel.name} needs {requirement.group(1)}, which is neither bundled nor in Blender")


# ----------------------------------------------------------------------------------------------
# Staging


def generated_manifest(text: str, wheel_names: list[str]) -> str:
    """manifest.toml with `wheels = [...]` added among the top-level keys (before the first table)."""
    listing = "".join(f'    "./wheels/{name}",\n' for name in wheel_names)
    block = f"# Filled in by scripts/build_extension.py.\nwheels = [\n{listing}]\n\n"
    table = re.search(r"^\[", text, flags=re.MULTILINE)
    at = table.start() if table else len(text)
    head = text[:at] if at == 0 or text[:at].endswith("\n") else text[:at] + "\n"
    result = head + block + text[at:]
    expected = {**tomllib.loads(text), "wheels": [f"./wheels/{name}" for name in wheel_names]}
    if tomllib.loads(result) != expected:
        raise BuildError("internal error: adding the wheel list changed the manifest's other values")
    return result


#: Timestamp of every file in the core wheel (zip's earliest), so equal sources give equal bytes.
WHEEL_DATE = (1980, 1, 1, 0, 0, 0)


def core_version() -> str:
    text = (CORE_DIR / "__init__.py").read_text(encoding="utf-8")
    match = re.search(r'^__version__ = "([^"]+)"', text, flags=re.MULTILINE)
    if match is None:
        raise BuildError(f"{CORE_DIR.name}/__init__.py has no __version__")
    return match.group(1)


def core_files() -> list[Path]:
    """The files of `hybridgi_core/` that ship: sources, shaders, precomputed tables, READMEs (no caches)."""
    return sorted(
        p for p in CORE_DIR.rglob("*")
        if p.is_file() and "__pycache__" not in p.parts and p.suffix in {".py", ".glsl", ".md", ".npz"}
    )


def core_wheel(out_dir: Path) -> Path:
    """`hybridgi_core-<version>-py3-none-any.whl` of `hybridgi_core/` (PEP 427), reproducible.

    Its metadata names no dependencies: Blender installs none, and the extension bundles the
    core's (embreex, fast-simplification) as wheels of their own; numpy ships with Blender.
    """
    version = core_version()
    dist_info = f"{CORE_DIR.name}-{version}.dist-info"
    entries = [(p.relative_to(CORE_DIR.parent).as_posix(), p.read_bytes()) for p in core_files()]
    entries.append((f"{dist_info}/METADATA",
                    f"Metadata-Version: 2.1\nName: {CORE_DIR.name}\nVersion: {version}\n".encode()))
    entries.append((f"{dist_info}/WHEEL",
                    b"Wheel-Version: 1.0\nGenerator: hybridgi build_extension\nRoot-Is-Purelib: true\nTag: py3-none-any\n"))
    record = [
        f"{name},sha256={base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b'=').decode()},{len(data)}"
        for name, data in entries
    ]
    entries.append((f"{dist_info}/RECORD", ("\n".join(record + [f"{dist_info}/RECORD,,"]) + "\n").encode()))
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / f"{CORE_DIR.name}-{version}-py3-none-any.whl"
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as archive:
        for name, data in entries:
            info = zipfile.ZipInfo(name, WHEEL_DATE)
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            archive.writestr(info, data)
    return path


def stage(manifest_text: str, wheels: list[Path], stage_root: Path = STAGE_ROOT) -> Path:
    """A clean build/extension/hybridgi/: the add-on, wheels/ (the core's among them), the manifest."""
    source = stage_root / "hybridgi"
    if source.exists():
        shutil.rmtree(source)
    stage_root.mkdir(parents=True, exist_ok=True)
    shutil.copytree(ADDON_DIR, source, ignore=STAGE_IGNORE)
    (source / "wheels").mkdir()
    for wheel in wheels:
        shutil.copy2(wheel, source / "wheels" / wheel.name)
    text = generated_manifest(manifest_text, [w.name for w in wheels])
    (source / "blender_manifest.toml").write_text(text, encoding="utf-8")
    return source


# ----------------------------------------------------------------------------------------------
# Blender's tool and the checks of its output


def run_tool(tool: Path, *args: str) -> str:
    run = subprocess.run([sys.executable, str(tool), *args], capture_output=True, text=True)
    output = (run.stdout + run.stderr).strip()
    if run.returncode != 0:
        raise BuildError(f"blender_ext.py {args[0]} failed ({run.returncode}):\n{output}")
    return output


def zip_name(manifest: dict, platform: str) -> str:
    """The name Blender's tool gives a split-platform zip."""
    return f"{manifest['id']}-{manifest['version']}-{platform.replace('-', '_')}.zip"


def check_zip(item: PlatformZip, tool: Path) -> str:
    """`blender_ext.py validate`, then the contents; returns the tool's output. Raises BuildError."""
    output = run_tool(tool, "validate", str(item.path))
    with zipfile.ZipFile(item.path) as archive:
        names = set(archive.namelist())
        manifest = tomllib.loads(archive.read("blender_manifest.toml").decode("utf-8"))
    problems = []
    wheels = {n.removeprefix("wheels/") for n in names if n.startswith("wheels/") and n.endswith(".whl")}
    if wheels != set(item.wheels):
        problems.append(f"wheels {sorted(wheels)} instead of {sorted(item.wheels)}")
    generated = manifest.get("build", {}).get("generated", {})
    if generated.get("platforms") != [item.platform]:
        problems.append(f"[build.generated] platforms = {generated.get('platforms')}, not [{item.platform!r}]")
    if sorted(generated.get("wheels", [])) != sorted(f"./wheels/{w}" for w in item.wheels):
        problems.append(f"[build.generated] wheels = {generated.get('wheels')}")
    required = ["__init__.py", "engine.py", "pipeline.py"]
    problems += [f"{name} is missing" for name in required if name not in names]
    core = f"wheels/{CORE_DIR.name}-{core_version()}-py3-none-any.whl"
    if core not in names:
        problems.append(f"{core} is missing")
    else:
        with zipfile.ZipFile(io.BytesIO(zipfile.ZipFile(item.path).read(core))) as wheel:
            inside = set(wheel.namelist())
        expected = {p.relative_to(CORE_DIR.parent).as_posix() for p in core_files()}
        problems += [f"{name} is missing from {core}" for name in sorted(expected - inside)]
    if any(n.startswith(f"{CORE_DIR.name}/") for n in names):
        problems.append(f"a loose {CORE_DIR.name}/ folder is packaged besides its wheel")
    problems += [
        f"{name} should not be packaged"
        for name in sorted(names)
        if "__pycache__/" in name or name.endswith(".pyc") or name.startswith("tests/") or "/tests/" in name
    ]
    if problems:
        raise BuildError(f"{item.path.name}: " + "; ".join(problems))
    return output


# ----------------------------------------------------------------------------------------------
# The whole build


def build(force: bool = False, dist: Path = DIST, cache: Path = WHEEL_CACHE, stage_root: Path = STAGE_ROOT):
    """Build (or reuse, when up to date) and check one zip per platform. Returns [PlatformZip].

    Raises WheelsUnavailable when wheels are neither cached nor downloadable, BuildError otherwise.
    """
    tool = blender_ext_tool()
    manifest_text, manifest = read_manifest()
    digest = inputs_digest(tool)
    stamp = stage_root / "stamp.json"

    items = None if force else _reusable(stamp, digest, dist)
    if items is None:
        wheels = fetch_wheels(manifest["platforms"], cache)
        core = core_wheel(stage_root / "core-wheel")
        wheels = {platform: [*platform_wheels, core] for platform, platform_wheels in wheels.items()}
        every_wheel = sorted({w for platform_wheels in wheels.values() for w in platform_wheels})
        source = stage(manifest_text, every_wheel, stage_root)
        dist.mkdir(parents=True, exist_ok=True)
        for old in dist.glob(f"{manifest['id']}-*.zip"):
            old.unlink()
        log.info("building with %s", tool)
        run_tool(tool, "build", "--source-dir", str(source), "--output-dir", str(dist), "--split-platforms")
        items = [
            PlatformZip(dist / zip_name(manifest, p), p, tuple(w.name for w in wheels[p]))
            for p in manifest["platforms"]
        ]
        for item in items:
            if not item.path.is_file():
                raise BuildError(f"Blender's tool did not write {item.path}")
        stamp.write_text(json.dumps(_stamp(digest, items), indent=1), encoding="utf-8")
    else:
        log.info("dist/ is up to date with the sources; checking the zips again")

    for item in items:
        output = check_zip(item, tool)
        log.info("%s (%.1f MiB, %d wheels): %s", item.path.name, item.path.stat().st_size / 2**20,
                 len(item.wheels), output.splitlines()[-1] if output else "valid")
    return items


def _stamp(digest: str, items: list[PlatformZip]) -> dict:
    return {
        "digest": digest,
        "zips": [
            {"path": str(i.path), "platform": i.platform, "wheels": list(i.wheels),
             "size": i.path.stat().st_size, "mtime_ns": i.path.stat().st_mtime_ns}
            for i in items
        ],
    }


def _reusable(stamp: Path, digest: str, dist: Path) -> list[PlatformZip] | None:
    """The zips of the last build when nothing it read has changed and they are untouched."""
    try:
        record = json.loads(stamp.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if record.get("digest") != digest:
        return None
    items = []
    for entry in record.get("zips", []):
        path = Path(entry["path"])
        if path.parent != dist or not path.is_file():
            return None
        stat = path.stat()
        if (stat.st_size, stat.st_mtime_ns) != (entry["size"], entry["mtime_ns"]):
            return None
        items.append(PlatformZip(path, entry["platform"], tuple(entry["wheels"])))
    return items or None


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--force", action="store_true", help="rebuild even when dist/ is up to date")
    parser.add_argument("--dist", type=Path, default=DIST, help="output folder of the zips (default: dist/)")
    parser.add_argument("--wheel-cache", type=Path, default=WHEEL_CACHE, help="default: build/wheels/")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="extension: %(message)s")
    try:
        build(force=args.force, dist=args.dist.resolve(), cache=args.wheel_cache.resolve())
    except BuildError as err:
        log.error("%s", err)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())

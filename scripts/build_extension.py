"""Build the installable Blender extension zip with Blender's own extension tool.

Usage::

    .venv/bin/python scripts/build_extension.py [--output-dir dist] [--platforms all|linux-x64,...]
                                                [--no-bundle] [--blender-ext PATH]

Steps:

1. stage ``build/extension/`` (git-ignored): ``blender_manifest.toml`` from the repository root, the
   contents of ``nkf_blender/`` (Blender wants the manifest and ``__init__.py`` side by side), and a
   ``wheels/`` folder with the pure-Python ``nkf_model`` wheel built from this repository
   (``pip wheel --no-deps``), without its training code (:data:`NOT_BUNDLED`);
2. the compiled dependencies of the CPU path (:data:`BUNDLED`, exact versions, never NumPy) for each
   platform in ``--platforms`` (:data:`PLATFORMS`), downloaded from the package registry with
   ``pip download --only-binary=:all: --platform ... --python-version 3.11 --no-deps`` into the
   git-ignored ``.wheel-cache/<platform>/`` (once; later builds use the cache and need no network),
   copied to ``wheels/`` and listed, with ``platforms``, in the staged manifest;
3. check that every wheel listed in the manifest is there and nothing else is;
4. ``blender_ext.py validate`` on the staged folder;
5. ``blender_ext.py build --split-platforms`` into ``dist/``: one self-contained zip per platform,
   ``<id>-<version>-<platform>.zip`` (``linux_x64``, ...). With ``--no-bundle`` only the ``nkf_model``
   wheel is bundled and one zip ``<id>-<version>.zip`` is built, for an environment that already has
   SciPy, scikit-image and numba (the development tests in the project's venv).

``blender_ext.py`` ships inside the ``bpy`` wheel (``bpy/<version>/scripts/addons_core/bl_pkg/cli/``)
and in every Blender install; it is found without importing ``bpy``. Prints the zip's path on the
last lines of stdout, one per line; exit status 1 with the tool's messages when anything fails.
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import re
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
MANIFEST = "blender_manifest.toml"
ADDON_DIR = ROOT / "nkf_blender"
STAGE = ROOT / "build" / "extension"
WHEEL_CACHE = Path(os.environ.get("NKF_WHEEL_CACHE", ROOT / ".wheel-cache"))

# What the CPU path imports beyond Blender's own Python (NumPy, requests, ...), pinned. scikit-image
# is used only for marching cubes, which needs lazy_loader and none of its other dependencies
# (networkx, pillow, imageio, tifffile: 10 MB left out). tqdm and plyfile are tiny pure-Python
# wheels for nkf_model's files and progress bar. PyTorch is not bundled: NKF runs on the CPU with
# the feature network's NumPy twin; the preferences install PyTorch for the GPU.
BUNDLED = (
    "scipy==1.17.1",
    "scikit-image==0.26.0",
    "lazy_loader==0.6",
    "numba==0.68.1",
    "llvmlite==0.50.0",
    "threadpoolctl==3.8.0",
    "safetensors==0.8.0",
    "tqdm==4.70.1",
    "plyfile==1.1.3",
    # File > Import > Point Cloud: LAS/LAZ (laspy, its lazrs backend) and E57 (pye57, pyquaternion).
    "laspy==2.7.0",
    "lazrs==0.8.2",
    "pye57==0.4.19",
    "pyquaternion==0.9.9",
)

# Blender's platform names -> the wheel platform tags pip may take for it (Blender 4.2 needs glibc
# 2.28, macOS 11.2, Windows 10). On macOS arm64, SciPy 1.17 and llvmlite 0.50 have wheels for
# macOS 12 and later only, so that zip needs macOS 12. The registry has no numba/llvmlite wheels
# for macos-x64 and windows-arm64: no zip is built for them.
PLATFORMS = {
    "linux-x64": ("manylinux_2_28_x86_64", "manylinux_2_27_x86_64", "manylinux_2_24_x86_64",
                  "manylinux_2_17_x86_64", "manylinux2014_x86_64"),
    "macos-arm64": ("macosx_12_0_arm64", "macosx_11_0_arm64"),
    "macos-x64": ("macosx_10_15_x86_64",),
    "windows-x64": ("win_amd64",),
    "windows-arm64": ("win_arm64",),
}


class BuildError(Exception):
    """A step of the build failed; the message says which and why."""


def find_blender_ext() -> Path:
    """Path of ``blender_ext.py`` inside the installed ``bpy`` wheel (without importing ``bpy``)."""
    spec = importlib.util.find_spec("bpy")
    if spec is None or not spec.submodule_search_locations:
        raise BuildError(
            "bpy is not installed, so Blender's extension tool cannot be found; install it with "
            "`pip install -e '.[test]'` or pass --blender-ext PATH/TO/blender_ext.py"
        )
    for base in spec.submodule_search_locations:
        hits = sorted(Path(base).glob("*/scripts/addons_core/bl_pkg/cli/blender_ext.py"))
        if hits:
            return hits[-1]
    raise BuildError("bpy is installed but blender_ext.py was not found inside it; pass --blender-ext")


def build_wheel(dest: Path) -> Path:
    """Build the pure-Python ``nkf_model`` wheel of this repository into ``dest``."""
    dest.mkdir(parents=True, exist_ok=True)
    cmd = [sys.executable, "-m", "pip", "wheel", "--no-deps", "--quiet", "--wheel-dir", str(dest)]
    # The venv's own setuptools (>= 68) builds the wheel offline; without it pip fetches one.
    try:
        import setuptools

        if int(setuptools.__version__.split(".")[0]) >= 68:
            cmd.append("--no-build-isolation")
    except ImportError:
        pass
    cmd.append(str(ROOT))
    run = subprocess.run(cmd, capture_output=True, text=True)
    if run.returncode != 0:
        raise BuildError(f"pip wheel failed:\n{run.stdout}{run.stderr}")
    wheels = sorted(dest.glob("nkf_model-*.whl"))
    if len(wheels) != 1:
        raise BuildError(f"expected one nkf_model wheel in {dest}, found {[w.name for w in wheels]}")
    if not wheels[0].name.endswith("-py3-none-any.whl"):
        raise BuildError(f"the nkf_model wheel must be pure Python, got {wheels[0].name}")
    strip_wheel(wheels[0], NOT_BUNDLED)
    return wheels[0]


# What the extension's copy of nkf_model leaves out: training code (it needs the mesh corpus and
# PyTorch's autograd; reconstruction never imports it, tests/test_architecture.py enforces that).
NOT_BUNDLED = ("nkf_model/train/",)


def strip_wheel(wheel: Path, prefixes) -> list[str]:
    """Rewrite ``wheel`` without the files under ``prefixes`` (and their RECORD lines); returns them."""
    import zipfile

    tmp = wheel.with_suffix(".tmp")
    dropped = []
    with zipfile.ZipFile(wheel) as src, zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED) as dst:
        for info in src.infolist():
            if info.filename.startswith(tuple(prefixes)):
                dropped.append(info.filename)
                continue
            data = src.read(info)
            if info.filename.endswith(".dist-info/RECORD"):
                lines = data.decode().splitlines(keepends=True)
                data = "".join(ln for ln in lines if not ln.startswith(tuple(prefixes))).encode()
            dst.writestr(info, data)
    tmp.replace(wheel)
    return dropped


def _canon(name: str) -> str:
    return re.sub(r"[-_.]+", "_", name).lower()


def wheel_ok(path: Path) -> bool:
    """True when ``path`` is a whole wheel: a readable zip whose every member's CRC checks and that
    has a ``.dist-info/RECORD``. A partial download would otherwise go into the zip, and Blender
    would fail to unpack it at install time with a traceback (seen with bpy 5.0.1)."""
    import zipfile

    try:
        with zipfile.ZipFile(path) as z:
            return z.testzip() is None and any(n.endswith(".dist-info/RECORD") for n in z.namelist())
    except Exception:  # BadZipFile, EOFError, zlib.error, OSError: damaged either way
        return False


def _cached(folder: Path, pin: str) -> Path | None:
    """The wheel for ``name==version`` in ``folder``, if there and whole (a damaged one is deleted,
    so that it is downloaded again)."""
    name, version = pin.split("==")
    for w in sorted(folder.glob("*.whl")):
        parts = w.name.split("-")
        if _canon(parts[0]) == _canon(name) and parts[1] == version:
            if wheel_ok(w):
                return w
            w.unlink()
    return None


def download_wheels(platform: str, cache: Path = WHEEL_CACHE) -> list[Path]:
    """The :data:`BUNDLED` wheels for a Blender platform, from ``cache/<platform>/`` or downloaded
    there from the package registry (``pip download --no-deps --only-binary=:all:``)."""
    if platform not in PLATFORMS:
        raise BuildError(f"unknown platform {platform!r}; Blender's are {', '.join(PLATFORMS)}")
    folder = cache / platform
    folder.mkdir(parents=True, exist_ok=True)
    missing = [pin for pin in BUNDLED if _cached(folder, pin) is None]
    if missing:
        cmd = [sys.executable, "-m", "pip", "download", "--quiet", "--no-deps", "--only-binary=:all:",
               "--python-version", "3.11", "--implementation", "cp", "--abi", "cp311", "--abi", "abi3",
               "--abi", "none", "--dest", str(folder)]
        for tag in PLATFORMS[platform]:
            cmd += ["--platform", tag]
        run = subprocess.run(cmd + missing, capture_output=True, text=True)
        if run.returncode != 0:
            lines = [ln for ln in (run.stdout + run.stderr).splitlines() if ln.startswith("ERROR")]
            raise BuildError(f"no wheels for {platform} on the registry: " + " ".join(lines[:2]))
    wheels = []
    for pin in BUNDLED:
        w = _cached(folder, pin)
        if w is None:
            raise BuildError(f"pip download did not fetch {pin} for {platform}")
        wheels.append(w)
    if any(w.name.lower().startswith("numpy-") for w in wheels):
        raise BuildError("numpy must never be bundled: Blender ships its own")
    return wheels


def _set_manifest_list(text: str, key: str, items: list[str]) -> str:
    """``text`` (a manifest) with the top-level ``key = [...]`` replaced by ``items`` (or added)."""
    block = key + " = [\n" + "".join(f'  "{item}",\n' for item in items) + "]"
    pattern = re.compile(rf"^{key}\s*=\s*\[.*?\]", re.DOTALL | re.MULTILINE)
    if pattern.search(text):
        return pattern.sub(lambda m: block, text, count=1)
    first_table = re.search(r"^\[", text, re.MULTILINE)
    at = first_table.start() if first_table else len(text)
    return text[:at] + block + "\n\n" + text[at:]


def stage(stage_dir: Path = STAGE, platforms: tuple[str, ...] = ()) -> dict:
    """Fill ``stage_dir`` with the manifest, the add-on's files and its wheels (the ``nkf_model``
    wheel, and :data:`BUNDLED` for each of ``platforms``); return the staged manifest."""
    manifest_path = ROOT / MANIFEST
    if stage_dir.exists():
        shutil.rmtree(stage_dir)
    stage_dir.mkdir(parents=True)
    shutil.copytree(
        ADDON_DIR, stage_dir, dirs_exist_ok=True, ignore=shutil.ignore_patterns("__pycache__", "*.pyc")
    )
    built = build_wheel(stage_dir / "wheels")
    text = manifest_path.read_text()
    if platforms:
        listed = list(tomllib.loads(text).get("wheels", []))
        for platform in platforms:
            for w in download_wheels(platform):
                if f"./wheels/{w.name}" not in listed:  # pure-Python wheels serve every platform
                    shutil.copy2(w, stage_dir / "wheels" / w.name)
                    listed.append(f"./wheels/{w.name}")
        text = _set_manifest_list(text, "wheels", listed)
        text = _set_manifest_list(text, "platforms", list(platforms))
    (stage_dir / MANIFEST).write_text(text)
    manifest = tomllib.loads(text)
    listed = {Path(w).name for w in manifest.get("wheels", [])}
    present = {p.name for p in (stage_dir / "wheels").glob("*.whl")}
    if listed != present:
        raise BuildError(
            f"{MANIFEST} lists wheels {sorted(listed)} but the build made {sorted(present)}; "
            f"update `wheels` in {MANIFEST} (the nkf_model wheel is {built.name})"
        )
    if any(name.lower().startswith("numpy-") for name in present):
        raise BuildError("numpy must never be bundled: Blender ships its own")
    return manifest


def available_platforms(requested) -> tuple[tuple[str, ...], dict[str, str]]:
    """``(platforms whose wheels could be had, {platform: why not})`` for ``requested``."""
    ok, skipped = [], {}
    for platform in requested:
        try:
            download_wheels(platform)
            ok.append(platform)
        except BuildError as exc:
            skipped[platform] = str(exc)
    return tuple(ok), skipped


def blender_ext(tool: Path, *args: str) -> None:
    run = subprocess.run([sys.executable, str(tool), *args], capture_output=True, text=True)
    out = (run.stdout + run.stderr).strip()
    if run.returncode != 0:
        raise BuildError(f"blender_ext.py {args[0]} failed:\n{out}")
    if out:
        print(out)


def build(output_dir: Path, tool: Path | None = None, stage_dir: Path = STAGE,
          platforms: tuple[str, ...] = ()) -> list[Path]:
    """Stage, validate and build; return the zips (one per platform, or one without ``platforms``)."""
    tool = tool or find_blender_ext()
    manifest = stage(stage_dir, platforms)
    blender_ext(tool, "validate", str(stage_dir))
    output_dir.mkdir(parents=True, exist_ok=True)
    base = output_dir / f"{manifest['id']}-{manifest['version']}.zip"
    want = [base.with_name(f"{base.stem}-{p.replace('-', '_')}.zip") for p in platforms] or [base]
    for z in want:
        if z.exists():
            z.unlink()
    args = ["build", "--source-dir", str(stage_dir), "--output-filepath", str(base)]
    blender_ext(tool, *args, *(["--split-platforms"] if platforms else []))
    for z in want:
        if not z.is_file():
            raise BuildError(f"blender_ext.py build reported success but {z} does not exist")
    return want


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--output-dir", type=Path, default=ROOT / "dist",
                    help="where the zip goes (default dist/)")
    ap.add_argument("--stage-dir", type=Path, default=STAGE,
                    help="staging folder (default build/extension/)")
    ap.add_argument("--blender-ext", type=Path, default=None,
                    help="path of blender_ext.py (default: found inside the bpy wheel)")
    ap.add_argument("--platforms", default="all",
                    help="comma-separated Blender platforms to build a self-contained zip for "
                         f"({', '.join(PLATFORMS)}); 'all' (default): each one whose wheels the registry serves")
    ap.add_argument("--no-bundle", action="store_true",
                    help="bundle only the nkf_model wheel (one zip; SciPy, scikit-image and numba must "
                         "already be importable in Blender)")
    args = ap.parse_args(argv)
    try:
        platforms: tuple[str, ...] = ()
        if not args.no_bundle:
            if args.platforms == "all":
                platforms, skipped = available_platforms(PLATFORMS)
                for platform, why in skipped.items():
                    print(f"build_extension: skipped {platform}: {why}", file=sys.stderr)
                if not platforms:
                    raise BuildError("no platform's wheels could be downloaded")
            else:
                platforms = tuple(p.strip() for p in args.platforms.split(",") if p.strip())
        zips = build(args.output_dir.resolve(), args.blender_ext, args.stage_dir.resolve(), platforms)
    except BuildError as exc:
        print(f"build_extension: {exc}", file=sys.stderr)
        return 1
    for z in zips:
        print(f"built {z} ({os.path.getsize(z) / 1024:.0f} KiB)")
    for z in zips:
        print(z)
    return 0


if __name__ == "__main__":
    sys.exit(main())

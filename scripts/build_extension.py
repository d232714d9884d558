"""Build the installable Blender extension zip with Blender's own extension tool.

Usage::

    .venv/bin/python scripts/build_extension.py [--output-dir dist] [--blender-ext PATH]

Steps:

1. stage ``build/extension/`` (git-ignored): ``blender_manifest.toml`` from the repository root, the
   contents of ``nkf_blender/`` (Blender wants the manifest and ``__init__.py`` side by side), and a
   ``wheels/`` folder with the pure-Python ``nkf_model`` wheel built from this repository
   (``pip wheel --no-deps``), without its training code (:data:`NOT_BUNDLED`);
2. check that every wheel listed in the manifest is there and nothing else is;
3. ``blender_ext.py validate`` on the staged folder;
4. ``blender_ext.py build`` into ``dist/`` (``<id>-<version>.zip``).

``blender_ext.py`` ships inside the ``bpy`` wheel (``bpy/<version>/scripts/addons_core/bl_pkg/cli/``)
and in every Blender install; it is found without importing ``bpy``. Prints the zip's path on the
last line of stdout; exit status 1 with the tool's messages when anything fails.
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
MANIFEST = "blender_manifest.toml"
ADDON_DIR = ROOT / "nkf_blender"
STAGE = ROOT / "build" / "extension"


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


def stage(stage_dir: Path = STAGE) -> dict:
    """Fill ``stage_dir`` with the manifest, the add-on's files and its wheels; return the manifest."""
    manifest_path = ROOT / MANIFEST
    with open(manifest_path, "rb") as fh:
        manifest = tomllib.load(fh)
    if stage_dir.exists():
        shutil.rmtree(stage_dir)
    stage_dir.mkdir(parents=True)
    shutil.copy2(manifest_path, stage_dir / MANIFEST)
    shutil.copytree(
        ADDON_DIR, stage_dir, dirs_exist_ok=True, ignore=shutil.ignore_patterns("__pycache__", "*.pyc")
    )
    built = build_wheel(stage_dir / "wheels")
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


def blender_ext(tool: Path, *args: str) -> None:
    run = subprocess.run([sys.executable, str(tool), *args], capture_output=True, text=True)
    out = (run.stdout + run.stderr).strip()
    if run.returncode != 0:
        raise BuildError(f"blender_ext.py {args[0]} failed:\n{out}")
    if out:
        print(out)


def build(output_dir: Path, tool: Path | None = None, stage_dir: Path = STAGE) -> Path:
    """Stage, validate and build; return the path of the zip."""
    tool = tool or find_blender_ext()
    manifest = stage(stage_dir)
    blender_ext(tool, "validate", str(stage_dir))
    output_dir.mkdir(parents=True, exist_ok=True)
    zip_path = output_dir / f"{manifest['id']}-{manifest['version']}.zip"
    if zip_path.exists():
        zip_path.unlink()
    blender_ext(tool, "build", "--source-dir", str(stage_dir), "--output-filepath", str(zip_path))
    if not zip_path.is_file():
        raise BuildError(f"blender_ext.py build reported success but {zip_path} does not exist")
    return zip_path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--output-dir", type=Path, default=ROOT / "dist",
                    help="where the zip goes (default dist/)")
    ap.add_argument("--stage-dir", type=Path, default=STAGE,
                    help="staging folder (default build/extension/)")
    ap.add_argument("--blender-ext", type=Path, default=None,
                    help="path of blender_ext.py (default: found inside the bpy wheel)")
    args = ap.parse_args(argv)
    try:
        zip_path = build(args.output_dir.resolve(), args.blender_ext, args.stage_dir.resolve())
    except BuildError as exc:
        print(f"build_extension: {exc}", file=sys.stderr)
        return 1
    print(f"built {zip_path} ({os.path.getsize(zip_path) / 1024:.0f} KiB)")
    print(zip_path)
    return 0


if __name__ == "__main__":
    sys.exit(main())

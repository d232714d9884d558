"""The extension build never bundles a damaged wheel: a partial or corrupt file in the wheel cache
is deleted (and so downloaded again) instead of going into the zip, where Blender's installer would
fail with a traceback."""

import shutil
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def _build_extension():
    sys.path.insert(0, str(ROOT / "scripts"))
    try:
        import build_extension
    finally:
        sys.path.pop(0)
    return build_extension


def _a_wheel(tmp_path) -> Path:
    """A small pure-Python wheel (a zip with a package, METADATA and RECORD)."""
    import zipfile

    w = tmp_path / "tinypkg-1.0-py3-none-any.whl"
    with zipfile.ZipFile(w, "w", zipfile.ZIP_DEFLATED) as z:
        z.writestr("tinypkg/__init__.py", "x = 1\n" * 2000)
        z.writestr("tinypkg-1.0.dist-info/METADATA", "Metadata-Version: 2.1\nName: tinypkg\nVersion: 1.0\n")
        z.writestr("tinypkg-1.0.dist-info/RECORD", "tinypkg/__init__.py,,\n")
    return w


def test_whole_wheel_is_used_and_damaged_ones_are_dropped(tmp_path):
    be = _build_extension()
    cache = tmp_path / "cache"
    cache.mkdir()
    good = _a_wheel(tmp_path)
    shutil.copy(good, cache / good.name)
    assert be.wheel_ok(cache / good.name)
    assert be._cached(cache, "tinypkg==1.0") == cache / good.name
    # A partial download (cut in half), then one with a flipped byte in a member.
    for damage in ("cut", "flip"):
        data = bytearray(good.read_bytes())
        if damage == "cut":
            data = data[: len(data) // 2]
        else:
            data[60] ^= 0xFF  # inside the first member's compressed data
        (cache / good.name).write_bytes(bytes(data))
        assert not be.wheel_ok(cache / good.name), damage
        assert be._cached(cache, "tinypkg==1.0") is None, damage
        assert not (cache / good.name).exists()  # deleted: the next build downloads it again

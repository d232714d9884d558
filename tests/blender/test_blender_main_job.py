"""The README's main job (scripts/blender_main_job.py), run end to end in its own process on a small
input with a tiny render, so it stays quick: install the zip, import, reconstruct, save, render."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
from blender_helpers import ROOT, fibonacci_sphere, write_ply


def test_main_job_writes_blend_mesh_and_render(tmp_path, extension_zip, bpy_module):
    bpy = bpy_module
    pts, nrm = fibonacci_sphere(300, 1.0, (0.0, 0.0, 1.0))
    ply = write_ply(tmp_path / "ball.ply", pts, nrm)
    out = tmp_path / "out"
    run = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "blender_main_job.py"), "--out", str(out), "--input", str(ply),
         "--up", "Z", "--forward", "Y", "--zip", str(extension_zip), "--method", "SPLINES",
         "--resolution", "32", "--samples", "2", "--size", "96x72"],
        capture_output=True, text=True, timeout=300,
    )
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    assert "reconstructed 'ball_nkf' with SPLINES" in run.stdout
    for name in ("sample_nkf.blend", "sample_nkf_mesh.ply", "sample_render.png"):
        assert (out / name).stat().st_size > 0, name
    assert (out / "blender-user" / "extensions" / "user_default" / "nkf_blender" / "__init__.py").is_file()

    from nkf_model.io.files import read_mesh

    v, f = read_mesh(out / "sample_nkf_mesh.ply")
    r = np.linalg.norm(v - [0.0, 0.0, 1.0], axis=1)
    assert len(f) > 500 and np.abs(r - 1.0).max() < 0.05  # the exported mesh is the sphere, in place

    img = bpy.data.images.load(str(out / "sample_render.png"))
    try:
        assert tuple(img.size) == (96, 72)
        px = np.empty(96 * 72 * 4, dtype=np.float32)
        img.pixels.foreach_get(px)
        rgb = px.reshape(-1, 4)[:, :3]
        assert rgb.std() > 0.02  # an object on a background, not a blank frame
    finally:
        bpy.data.images.remove(img)

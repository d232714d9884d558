"""Disabling and re-enabling the extension: nothing left registered, no thread left running."""

from __future__ import annotations

import sys
import time

from blender_helpers import PKG, ext, fibonacci_sphere, import_ply, nkf_threads, write_ply

from nkf_model.options import Options

CLASS_NAMES = (
    "OBJECT_OT_nkf_reconstruct", "OBJECT_OT_nkf_cancel", "VIEW3D_PT_nkf",
    "NKF_OT_install_dependencies", "NKF_OT_cancel_install", "NKF_OT_check_dependencies",
)


def _registered(bpy) -> dict:
    state = {name: hasattr(bpy.types, name) for name in CLASS_NAMES}
    state["scene.nkf_settings"] = "nkf_settings" in bpy.types.Scene.bl_rna.properties
    state["preferences"] = PKG in bpy.context.preferences.addons
    return state


def test_disable_and_enable_twice_even_with_a_job_running(scene, bpy_module, tmp_path):
    import addon_utils

    bpy = bpy_module
    pts, nrm = fibonacci_sphere(800, 1.0)
    src = import_ply(bpy, write_ply(tmp_path / "ball.ply", pts, nrm))
    site = ext("prefs").user_site(create=True)
    assert site in sys.path
    for round_ in range(2):
        runner = ext("runner")
        runner.start(bpy.context, src, Options(method="splines", resolution=128, device="cpu"))
        assert nkf_threads()
        settings_classes = (ext("settings").NKF_PG_settings, ext("prefs").NKFPreferences)

        t0 = time.monotonic()
        addon_utils.disable(PKG, default_set=True)
        took = time.monotonic() - t0

        assert not any(_registered(bpy).values()), _registered(bpy)
        assert not any(cls.is_registered for cls in settings_classes)
        assert not nkf_threads(), f"round {round_}: a worker thread survived the disable"
        assert took < 3.0  # the running job was cancelled, not waited for
        assert site not in sys.path
        assert [o.name for o in bpy.data.objects] == ["ball"]

        addon_utils.enable(PKG, default_set=True)
        assert all(_registered(bpy).values()), _registered(bpy)
        assert site in sys.path
        assert ext("runner").running_count() == 0

    # Still fully working after the second enable.
    bpy.context.view_layer.objects.active = src
    assert bpy.ops.object.nkf_reconstruct(method="SPLINES", resolution=32) == {"FINISHED"}
    assert bpy.context.active_object.name == "ball_nkf"
    assert not nkf_threads()

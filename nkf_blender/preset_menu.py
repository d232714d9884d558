"""Presets of the panel's settings, in Blender's preset menu.

Four come with the extension (``presets/*.py`` beside this module: Closed Object, Room Scan,
Terrain, Sparse Sketch: method, normals, orientation, scan options, Lambda, Resolution). A person's
own are saved the usual Blender way (the + button: ``scripts/presets/nkf/`` in Blender's user
folder) and listed after them; the - button removes one of those.
"""

from __future__ import annotations

import os

import bpy
from bl_operators.presets import AddPresetBase

SUBDIR = "nkf"
BUNDLED = os.path.join(os.path.dirname(__file__), "presets")
# What a preset sets (scene settings, by property name).
VALUES = (
    "method", "normals_mode", "orientation", "use_scan", "trim", "min_piece", "use_close", "regularization",
    "resolution",
)


def preset_dirs() -> list[str]:
    """The bundled presets' folder, then Blender's ``presets/nkf`` folders (the user's own)."""
    return [BUNDLED, *bpy.utils.preset_paths(SUBDIR)]


class NKF_MT_presets(bpy.types.Menu):
    bl_label = "NKF Presets"
    preset_subdir = SUBDIR
    preset_operator = "script.execute_preset"

    def draw(self, context):
        self.path_menu(
            preset_dirs(), self.preset_operator, filter_ext=lambda ext: ext.lower() == ".py",
            display_name=lambda name: bpy.path.display_name(name, title_case=False),
        )


class NKF_OT_preset_add(AddPresetBase, bpy.types.Operator):
    """Save the panel's settings as a preset, or remove one of your presets"""

    bl_idname = "nkf.preset_add"
    bl_label = "Add NKF Preset"
    preset_menu = "NKF_MT_presets"
    preset_subdir = SUBDIR
    preset_defines = ["s = bpy.context.scene.nkf_settings"]
    preset_values = [f"s.{name}" for name in VALUES]


def draw_presets(layout) -> None:
    row = layout.row(align=True)
    row.menu(NKF_MT_presets.__name__, text=NKF_MT_presets.bl_label)
    row.operator(NKF_OT_preset_add.bl_idname, text="", icon="ADD")
    row.operator(NKF_OT_preset_add.bl_idname, text="", icon="REMOVE").remove_active = True


CLASSES = (NKF_MT_presets, NKF_OT_preset_add)

"""NKF for Blender: reconstruct a surface mesh from the active point cloud (oriented or not,
closed or an open scan, with or without colours).

Operator ``bpy.ops.object.nkf_reconstruct`` (modal with progress in the UI, synchronous in
headless Blender), panel View3D > Sidebar > NKF, add-on preferences that install PyTorch and the
other compiled dependencies, and a Python function, :func:`api.reconstruct_object`.

The reconstruction itself is the ``nkf_model`` package, bundled as a wheel. Module map:

* ``deps``, ``installer``, ``methods``, ``job``, ``estimates``, ``errors``: no ``bpy``; worker-thread
  logic, time and memory estimates, dependency checks and the pip installer;
* ``settings`` reads every default, range and tooltip from ``nkf_model.options`` and maps the
  properties to one ``nkf_model.options.Options``; enabling imports nothing heavier than that
  (no PyTorch, SciPy, scikit-image, numba, nor nkf_model's reconstruction code);
* ``importer``: File > Import > Point Cloud (LAS/LAZ, E57, XYZ, PCD, PLY through nkf_model's
  readers; drag and drop) and File > Export > Mesh in Map Coordinates;
* ``source`` (read points), ``result`` (build the mesh), ``runner`` (jobs on the main thread),
  ``settings``, ``ops``, ``panel``, ``prefs``, ``api``: the Blender side.
"""

from __future__ import annotations

import bpy

from . import batch, deps, importer, live, methods, ops, panel, prefs, prepare, preset_menu, runner, settings

_CLASSES = (
    settings.NKF_PG_settings, *prefs.CLASSES, *ops.CLASSES, *panel.CLASSES, *importer.CLASSES, *preset_menu.CLASSES,
    *batch.CLASSES, *live.CLASSES,
)


def register() -> None:
    # Find packages installed by "Install Dependencies" or in the user's PyTorch folder first:
    # the method's default (NKF when nkf_model can run it) depends on them. The default is decided
    # without importing PyTorch or nkf_model's reconstruction code (methods.quick_default), so that
    # enabling the add-on stays cheap; the real check runs when a reconstruction does.
    prefs_cls = prefs.NKFPreferences
    bpy.utils.register_class(prefs_cls)
    p = prefs.get_prefs()
    if p is not None and p.torch_path:
        prefs._applied_torch_path[0] = bpy.path.abspath(p.torch_path)
    prefs.apply_paths(p)
    default = methods.quick_default() if deps.status().ready else "SPLINES"
    settings.prepare_classes(default, settings.NKF_PG_settings, ops.OBJECT_OT_nkf_reconstruct)
    for cls in _CLASSES:
        if cls is not prefs_cls:
            bpy.utils.register_class(cls)
    bpy.types.Scene.nkf_settings = bpy.props.PointerProperty(type=settings.NKF_PG_settings)
    live.register()
    if not bpy.app.background:
        # Compile the solver once, in the background, a moment after enabling (not during it: enabling
        # stays cheap); timers never fire headless, where the first run compiles instead.
        bpy.app.timers.register(_start_prepare, first_interval=1.0)
    importer.register_menus()


def _start_prepare():
    """Timer: start the first-time preparation, then redraw its progress every 0.5 s until it ends."""
    if prepare.status().state == prepare.IDLE:
        if not deps.status().ready or not prepare.start(prefs.prepare_folder()):
            return None
    if prepare.running() and runner.running_count():
        prepare.cancel()  # a reconstruction compiles what it needs; never two threads in numba's pool
    ops._tag_redraw(bpy.context)
    return 0.5 if prepare.running() else None


def unregister() -> None:
    if bpy.app.timers.is_registered(_start_prepare):
        bpy.app.timers.unregister(_start_prepare)
    if not prepare.stop():
        print("NKF: the first-time preparation did not stop")
    live.unregister()
    stuck = runner.stop_all()
    if stuck:
        print(f"NKF: worker threads did not stop for {', '.join(stuck)}")
    prefs.stop_install()
    importer.unregister_menus()
    del bpy.types.Scene.nkf_settings
    for cls in reversed(_CLASSES):
        bpy.utils.unregister_class(cls)
    deps.remove_added_paths()
    prefs._applied_torch_path[0] = ""

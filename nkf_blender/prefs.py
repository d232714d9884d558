"""Add-on preferences: dependency status, "Install Dependencies", and an existing PyTorch folder.

PyTorch (CPU or CUDA build), SciPy, scikit-image, numba and safetensors are installed with pip
into the extension's user folder (``bpy.utils.extension_path_user(__package__,
path="site-packages")``), only when Blender's online access is on (or from a local folder of
wheels, which needs no network). pip runs in a subprocess; a timer polls it and the preferences
show its current step. The folder is appended to ``sys.path``, after Blender's own packages, so
Blender's NumPy stays first (and pip's NumPy is deleted from the folder).
"""

from __future__ import annotations

import os
import textwrap

import bpy
from bpy.props import EnumProperty, FloatProperty, IntProperty, StringProperty

from . import deps, import_failure, installer, methods

ADDON = __package__
POLL_INTERVAL = 0.5
GIB = 2**30


class InstallState:
    """The one pip run of this session, and the last outcome, for the preferences' draw()."""

    job: installer.PipJob | None = None
    message: str = ""
    ok: bool | None = None


def user_site(create: bool = False) -> str:
    """The extension's own ``site-packages`` folder (a user folder that survives updates)."""
    try:
        return bpy.utils.extension_path_user(ADDON, path="site-packages", create=create)
    except ValueError:  # loaded as a legacy add-on, not as an extension
        path = os.path.join(bpy.utils.user_resource("DATAFILES"), "nkf_blender", "site-packages")
        if create:
            os.makedirs(path, exist_ok=True)
        return path


def prepare_folder() -> str | None:
    """The extension's user ``cache`` folder, where the first-time preparation leaves its marker."""
    try:
        return bpy.utils.extension_path_user(ADDON, path="cache", create=True)
    except (ValueError, OSError):  # a legacy add-on, or a read-only user folder: no marker
        return None


def fit_cache_bytes(context=None) -> int:
    """The Fit Cache preference in bytes (1 GiB when the preferences are not there)."""
    p = get_prefs(context)
    return int(getattr(p, "fit_cache_mb", 1024)) * (1 << 20)


def _fit_cache_changed() -> None:
    from . import fitcache

    fitcache.CACHE.set_budget(fit_cache_bytes())


def get_prefs(context=None):
    context = context or bpy.context
    addon = context.preferences.addons.get(ADDON)
    return addon.preferences if addon is not None else None


def memory_budget(context=None) -> int | None:
    """The Memory Budget preference in bytes, or None for nkf_model's default (the setting is 0)."""
    p = get_prefs(context)
    gb = float(p.memory_budget) if p is not None else 0.0
    return int(gb * GIB) if gb > 0 else None


def apply_paths(prefs) -> None:
    """Put the extension's folder and the user's PyTorch folder on ``sys.path`` and re-check."""
    deps.add_path(user_site(create=True))
    if prefs is not None and prefs.torch_path:
        deps.add_path(bpy.path.abspath(prefs.torch_path))
    deps.refresh()
    methods.refresh()


_applied_torch_path = [""]


def _torch_path_changed(self, context) -> None:
    old = _applied_torch_path[0]
    if old:
        deps.remove_path(old)
    new = bpy.path.abspath(self.torch_path) if self.torch_path else ""
    _applied_torch_path[0] = new
    apply_paths(self)


def _redraw_preferences() -> None:
    wm = bpy.context.window_manager
    if wm is None:
        return
    for window in wm.windows:
        for area in window.screen.areas:
            if area.type in ("PREFERENCES", "VIEW_3D"):
                area.tag_redraw()


def _finish_install() -> None:
    job = InstallState.job
    res = job.finish()
    InstallState.job = None
    InstallState.ok = res.ok
    InstallState.message = res.message
    if res.removed_numpy:
        print(f"NKF: removed {', '.join(res.removed_numpy)} from {job.target} (Blender's NumPy is used)")
    apply_paths(get_prefs())
    print(f"NKF: {res.message}")


def _poll_install():
    """Timer callback: None ends the timer."""
    job = InstallState.job
    if job is None:
        return None
    if job.running:
        _redraw_preferences()
        return POLL_INTERVAL
    _finish_install()
    _redraw_preferences()
    return None


def stop_install() -> None:
    """Stop a running pip (the add-on is being disabled)."""
    if InstallState.job is not None:
        InstallState.job.cancel()
        _finish_install()
    if bpy.app.timers.is_registered(_poll_install):
        bpy.app.timers.unregister(_poll_install)


class NKF_OT_install_dependencies(bpy.types.Operator):
    """Install PyTorch, SciPy, scikit-image, numba and safetensors into the extension's folder with pip"""

    bl_idname = "nkf.install_dependencies"
    bl_label = "Install Dependencies"
    bl_options = {"REGISTER", "INTERNAL"}

    variant: EnumProperty(
        name="PyTorch Build",
        items=[
            ("CPU", "CPU", "PyTorch for the CPU (smaller download, runs everywhere)"),
            ("CUDA", "CUDA", "PyTorch with CUDA for NVIDIA GPUs (Windows and Linux; a large download)"),
        ],
        default="CPU",
    )
    requirements: StringProperty(
        name="Requirements",
        description="Override what is installed (space-separated pip requirement specifiers); for scripts",
        default="",
        options={"HIDDEN", "SKIP_SAVE"},
    )

    def execute(self, context):
        if InstallState.job is not None:
            self.report({"ERROR"}, "NKF: an install is already running")
            return {"CANCELLED"}
        prefs = get_prefs(context)
        wheel_dir = bpy.path.abspath(prefs.wheel_dir) if prefs is not None and prefs.wheel_dir else ""
        if wheel_dir and not os.path.isdir(wheel_dir):
            self.report({"ERROR"}, f"NKF: the offline wheels folder does not exist: {wheel_dir}")
            return {"CANCELLED"}
        if not wheel_dir and not bpy.app.online_access:
            self.report(
                {"ERROR"},
                "NKF: online access is off, so nothing was downloaded. Turn on Preferences > System > "
                "Network > Allow Online Access (and do not start Blender with --offline-mode), "
                "or set an offline wheels folder",
            )
            return {"CANCELLED"}
        try:
            reqs = self.requirements.split() or installer.requirements(self.variant)
            target = user_site(create=True)
            cmd = installer.pip_command(target, reqs, variant=self.variant, wheel_dir=wheel_dir or None)
            InstallState.job = installer.PipJob(cmd, target).start()
        except (installer.InstallError, OSError) as exc:
            InstallState.job = None
            self.report({"ERROR"}, f"NKF: {exc}")
            return {"CANCELLED"}
        InstallState.ok, InstallState.message = None, ""
        print("NKF: " + " ".join(cmd))
        if bpy.app.background:
            InstallState.job.wait()
            _finish_install()
            self.report({"INFO"} if InstallState.ok else {"ERROR"}, f"NKF: {InstallState.message}")
            return {"FINISHED"} if InstallState.ok else {"CANCELLED"}
        bpy.app.timers.register(_poll_install, first_interval=POLL_INTERVAL)
        self.report({"INFO"}, "NKF: installing dependencies; progress is shown in the add-on preferences")
        return {"FINISHED"}


class NKF_OT_cancel_install(bpy.types.Operator):
    """Stop the running install"""

    bl_idname = "nkf.cancel_install"
    bl_label = "Cancel Install"
    bl_options = {"INTERNAL"}

    @classmethod
    def poll(cls, context):
        return InstallState.job is not None

    def execute(self, context):
        stop_install()
        return {"FINISHED"}


def _from(name: str) -> str:
    """" from FOLDER" for the folder ``import name`` uses, or ""."""
    where = import_failure.origin(name)
    return f" from {where}" if where is not None else ""


class NKF_OT_check_dependencies(bpy.types.Operator):
    """Look for the Python packages again (after installing them yourself)"""

    bl_idname = "nkf.check_dependencies"
    bl_label = "Check Again"
    bl_options = {"INTERNAL"}

    def execute(self, context):
        apply_paths(get_prefs(context))
        st = deps.status()
        if st.ready:  # found: now import them for real, in a separate process (a broken one is named)
            broken = deps.verify([n for n in deps.IMPORTS if st.found.get(n)])
            if broken:
                self.report({"WARNING"}, "NKF: cannot import " + "; ".join(
                    f"{n}{_from(n)} ({w})" for n, w in broken.items()))
                return {"FINISHED"}
        msg = st.message() or "all Python packages found"
        self.report({"INFO"} if st.ready else {"WARNING"}, f"NKF: {msg}")
        return {"FINISHED"}


def wrapped(layout, text: str, icon: str = "NONE", width: int = 60) -> None:
    """Labels for a long message, one per wrapped line (labels do not wrap by themselves)."""
    for i, line in enumerate(textwrap.wrap(text, width) or [""]):
        layout.label(text=line, icon=icon if i == 0 else "BLANK1")


class NKFPreferences(bpy.types.AddonPreferences):
    bl_idname = ADDON

    torch_path: StringProperty(
        name="PyTorch Folder",
        subtype="DIR_PATH",
        description=(
            "A site-packages folder where PyTorch (and SciPy, scikit-image, numba) are already "
            "installed; it is added to Python's search path after Blender's own packages"
        ),
        update=_torch_path_changed,
    )
    install_variant: EnumProperty(
        name="PyTorch Build",
        items=[("CPU", "CPU", "PyTorch for the CPU"), ("CUDA", "CUDA", "PyTorch with CUDA (NVIDIA GPUs)")],
        default="CPU",
    )
    wheel_dir: StringProperty(
        name="Offline Wheels",
        subtype="DIR_PATH",
        description="Install only from the wheel files in this folder (nothing is downloaded)",
    )
    memory_budget: FloatProperty(
        name="Memory Budget (GB)",
        default=0.0,
        min=0.0,
        soft_max=64.0,
        precision=2,
        description=(
            "Refuse a reconstruction whose estimated memory exceeds this many GB (GiB), before it "
            "starts; 0 uses 60 % of this computer's memory, at most 16 GB"
        ),
    )
    fit_cache_mb: IntProperty(
        name="Fit Cache (MB)",
        default=1024,
        min=0,
        soft_max=16384,
        description=(
            "Memory for kept fits, so that a new Lambda or Resolution does not start over (least recently "
            "used dropped first); 0 keeps none"
        ),
        update=lambda self, context: _fit_cache_changed(),
    )

    def draw(self, context):
        draw_preferences(self, self.layout, context)


def draw_preferences(prefs, layout, context) -> None:
    """What the preferences show (``prefs``: this add-on's preferences)."""
    st = deps.status()
    box = layout.box()
    box.label(text="Python packages", icon="SCRIPT")
    grid = box.grid_flow(columns=3, even_columns=True)
    for mod in {**deps.REQUIRED, **deps.ENGINES, **deps.OPTIONAL}:
        found = st.found.get(mod, False)
        grid.label(text=mod, icon="CHECKMARK" if found else "X")
    if st.message():
        col = box.column()
        col.alert = not st.ready
        wrapped(col, st.message(), icon="ERROR" if not st.ready else "INFO")
    box.operator(NKF_OT_check_dependencies.bl_idname, icon="FILE_REFRESH")

    box = layout.box()
    box.label(text="Install GPU support (PyTorch)", icon="IMPORT")
    wrapped(box, "The extension brings what the CPU needs (NKF and Neural Splines). For the GPU, pip installs "
                 f"{installer.TORCH_SPEC} (with SciPy, scikit-image, numba, threadpoolctl and safetensors) into "
                 f"{user_site()} (several hundred MB for the CPU build, several GB for CUDA).")
    box.prop(prefs, "install_variant")
    box.prop(prefs, "wheel_dir")
    job = InstallState.job
    if job is not None:
        box.label(text=f"Installing… {job.elapsed:.0f} s", icon="SORTTIME")
        wrapped(box, job.step)
        box.operator(NKF_OT_cancel_install.bl_idname, icon="CANCEL")
    else:
        row = box.row()
        if not bpy.app.online_access and not prefs.wheel_dir:
            wrapped(box, "Online access is off: turn on Preferences > System > Network > Allow Online "
                         "Access to download, or set an offline wheels folder.", icon="INFO")
            row.enabled = False
        op = row.operator(NKF_OT_install_dependencies.bl_idname, icon="IMPORT")
        op.variant = prefs.install_variant
    if InstallState.message:
        col = box.column()
        col.alert = not InstallState.ok
        wrapped(col, InstallState.message, icon="CHECKMARK" if InstallState.ok else "ERROR")

    box = layout.box()
    box.label(text="Already have PyTorch?", icon="FILE_FOLDER")
    box.prop(prefs, "torch_path")

    box = layout.box()
    box.label(text="Limits", icon="MEMORY")
    box.prop(prefs, "memory_budget")
    box.prop(prefs, "fit_cache_mb")


CLASSES = (NKF_OT_install_dependencies, NKF_OT_cancel_install, NKF_OT_check_dependencies, NKFPreferences)

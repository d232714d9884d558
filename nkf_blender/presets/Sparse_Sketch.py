# NKF preset: a few hundred hand-placed or sparse points: the learned kernel, a smoother surface.
import bpy

s = bpy.context.scene.nkf_settings
s.method = "NKF"
s.normals_mode = "AUTO"
s.orientation = "OUTWARD"
s.use_scan = False
s.use_close = False
s.regularization = 1e-6
s.resolution = 96

# NKF preset: a closed object scanned or sampled from all around (a statue, a toy, a mesh's points).
import bpy

s = bpy.context.scene.nkf_settings
s.method = "NKF"
s.normals_mode = "AUTO"
s.orientation = "OUTWARD"
s.use_scan = False
s.use_close = False
s.regularization = 1e-10
s.resolution = 192

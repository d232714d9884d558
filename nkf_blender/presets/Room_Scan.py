# NKF preset: an interior scanned from inside (normals towards the scanner positions or the camera),
# an open surface trimmed where it runs far from the points.
import bpy

s = bpy.context.scene.nkf_settings
s.method = "SPLINES"
s.normals_mode = "AUTO"
s.orientation = "VIEWPOINT"
s.use_scan = True
s.trim = 4.0
s.min_piece = 0.002
s.use_close = False
s.regularization = 1e-10
s.resolution = 256

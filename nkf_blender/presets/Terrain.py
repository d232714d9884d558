# NKF preset: ground seen from above (aerial lidar, photogrammetry of a landscape): normals up, trimmed.
import bpy

s = bpy.context.scene.nkf_settings
s.method = "SPLINES"
s.normals_mode = "AUTO"
s.orientation = "UP"
s.use_scan = True
s.trim = 4.0
s.min_piece = 0.002
s.use_close = False
s.regularization = 1e-10
s.resolution = 256

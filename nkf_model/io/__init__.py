"""Files: reading point clouds, writing meshes."""

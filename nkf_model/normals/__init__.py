"""Stage 2: normals for clouds that have none: PCA, orientation (views, layers, winding number) and the
learned sign check."""

"""Stages 5-6: the fitted function on a sparse grid near its zero level, marching cubes, the open-scan
clean-up and vertex colours."""

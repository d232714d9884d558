"""The kernel: the Neural Spline kernel, its engines (numba on the CPU, PyTorch on a GPU), the learned
feature network phi and its weights files."""

"""Benchmarks and synthetic scenes (outside the installed package): ``python -m benchmarks.bench``,
``python -m benchmarks.bench_normals``, ``python -m benchmarks.bench_scenes``, ``python -m benchmarks.scenes``."""

"""The whole run: reconstruct() wires the stages; the time and memory budget, progress and cancel,
the stage list and the GPU-to-CPU fallback."""

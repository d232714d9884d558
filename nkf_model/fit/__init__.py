"""Stages 3-4: constraints from oriented points (augment) and the kernel weights (dense and Falkon
solves, the partition of unity of local solves)."""

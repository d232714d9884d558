"""Loading the reconstruction code without the cyclic garbage collector's futile work.

Importing the solver's modules (NumPy, SciPy, numba and llvmlite) makes about a million objects,
almost none of them garbage, and sets off some 250 collections that free nothing: 0.1 s of the
1 s it takes (docs/blender-user.md, "Command line at 1,000 points"). Standard library only.
"""

from __future__ import annotations

import contextlib
import gc


@contextlib.contextmanager
def collector_paused():
    """No cyclic garbage collection inside the block; the collector's previous state (on, or off
    because the host turned it off) comes back afterwards, also when the block raises."""
    was_enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was_enabled:
            gc.enable()

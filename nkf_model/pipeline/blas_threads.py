"""The BLAS thread limit of every solve, set without re-scanning the loaded libraries each time.

``threadpoolctl.threadpool_limits`` inspects every loaded shared library on each call (about 5 ms
on the 2-core reference CPU): a twelfth of a live preview step's time budget, paid twice per step
(the solve and the mesh). One :class:`threadpoolctl.ThreadpoolController` made at the first call
and reused makes entering the limit a few microseconds. A BLAS loaded after that first call (a
library imported later) is picked up by making the controller again when the set of loaded
libraries may have grown: cheaply checked by the number of entries in ``sys.modules``.
"""

from __future__ import annotations

import sys
import threading

from threadpoolctl import ThreadpoolController

_lock = threading.Lock()
_controller: ThreadpoolController | None = None
_modules_seen = -1


def _get_controller() -> ThreadpoolController:
    global _controller, _modules_seen
    with _lock:
        n = len(sys.modules)
        if _controller is None or n != _modules_seen:
            _controller = ThreadpoolController()
            _modules_seen = n
        return _controller


def blas_threads(limit: int):
    """Context manager: BLAS (OpenBLAS, MKL, BLIS) limited to ``limit`` threads inside it, as
    ``threadpool_limits(limits=limit, user_api="blas")``."""
    return _get_controller().limit(limits=limit, user_api="blas")

"""NKF: surface reconstruction from oriented points with Neural Kernel Fields.

NumPy in, NumPy out; no Blender needed. The main entry point is :func:`reconstruct`::

    import nkf_model
    mesh = nkf_model.reconstruct(points, normals, resolution=128)
    mesh.vertices  # (V, 3) float32, in the input's frame
    mesh.faces     # (F, 3) int32, facing out

``method="splines"`` is the data-free Neural Splines kernel (Williams et al., CVPR 2021). The
settings are one :class:`Options` object (``nkf_model.options``: defaults, ranges, messages).

``import nkf_model`` loads only the standard-library parts (settings, errors); the reconstruction
code and its compiled dependencies (SciPy, scikit-image, numba, PyTorch) load on first use of
:func:`reconstruct`, :func:`estimate`, :class:`Mesh` and the other names below. The stages live in
subpackages: ``points``, ``normals``, ``kernel``, ``fit``, ``surface``, ``pipeline``, ``io``
(``docs/architecture.md``); ``train`` holds the training of the learned kernel.
"""

import sys as _sys
from importlib import import_module
from types import ModuleType as _ModuleType

from .errors import (
    Cancelled,
    DegenerateInputError,
    DeviceWarning,
    InputWarning,
    InvalidParameterError,
    InvalidPointCloudError,
    MemoryBudgetError,
    MethodUnavailableError,
    MissingNormalsError,
    NKFInputError,
    NoSurfaceError,
    OutputPathError,
    PointCloudFileError,
    TooFewPointsError,
    WeightsError,
)
from .options import SETTING, SETTINGS, Options

__version__ = "0.1.0"

METHODS = SETTING["method"].values  # ("splines", "nkf")

# Public names whose modules load on first use: name -> module that defines it.
_LAZY = {
    "reconstruct": ".pipeline.reconstruct",
    "fit": ".pipeline.reconstruct",
    "Fit": ".pipeline.fitted",
    "estimate": ".pipeline.budget",
    "Estimate": ".pipeline.budget",
    "Mesh": ".surface.mesh",
    "estimate_normals": ".normals.estimate",
    "method_available": ".kernel.weights",
}


def __getattr__(name):
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'nkf_model' has no attribute {name!r}")
    value = getattr(import_module(module, __name__), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(_LAZY))


class _Package(_ModuleType):
    """``nkf_model.fit`` is a function and also the name of a subpackage. Importing the subpackage
    sets the package's attribute ``fit`` to it (``import nkf_model.fit.augment``, which the pipeline
    does), after which ``nkf_model.fit(...)`` raised "'module' object is not callable". A data
    descriptor on the module's class wins over that attribute: ``nkf_model.fit`` is always the
    function; ``from nkf_model.fit.solve import ...`` and ``import nkf_model.fit.augment`` still work
    (through ``sys.modules``)."""

    @property
    def fit(self):
        return import_module(".pipeline.reconstruct", __name__).fit

    @fit.setter
    def fit(self, value):  # the import system recording the subpackage: it stays in sys.modules
        pass


_sys.modules[__name__].__class__ = _Package


__all__ = [
    "reconstruct",
    "fit",
    "Fit",
    "Options",
    "SETTINGS",
    "Mesh",
    "METHODS",
    "InputWarning",
    "Cancelled",
    "NKFInputError",
    "InvalidParameterError",
    "InvalidPointCloudError",
    "TooFewPointsError",
    "DegenerateInputError",
    "MissingNormalsError",
    "PointCloudFileError",
    "OutputPathError",
    "NoSurfaceError",
    "MethodUnavailableError",
    "MemoryBudgetError",
    "DeviceWarning",
    "estimate",
    "Estimate",
    "estimate_normals",
    "WeightsError",
    "method_available",
    "__version__",
]

"""NKF: surface reconstruction from oriented points with Neural Kernel Fields.

NumPy in, NumPy out; no Blender needed. The main entry point is :func:`reconstruct`::

    import nkf_model
    mesh = nkf_model.reconstruct(points, normals, resolution=128)
    mesh.vertices  # (V, 3) float32, in the input's frame
    mesh.faces     # (F, 3) int32, facing out

``method="splines"`` is the data-free Neural Splines kernel (Williams et al., CVPR 2021).
"""

from .errors import (
    Cancelled,
    DegenerateInputError,
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
from .kernel.weights import method_available
from .normals.estimate import estimate_normals
from .pipeline.budget import Estimate, estimate
from .pipeline.device_fallback import DeviceWarning
from .pipeline.reconstruct import METHODS, InputWarning, reconstruct
from .surface.mesh import Mesh

__version__ = "0.1.0"

__all__ = [
    "reconstruct",
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

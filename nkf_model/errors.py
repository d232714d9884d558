"""Exceptions raised and warnings issued by :mod:`nkf_model` (standard library only).

Every failure a caller can cause is an :class:`NKFInputError` (a ``ValueError``) with a message
written for the person who gave the input. :class:`Cancelled` is raised when a ``cancel`` event
is set during :func:`nkf_model.reconstruct`; it is not an error of the input.
"""


class NKFInputError(ValueError):
    """Base class for every problem with the caller's input or settings."""


class InvalidParameterError(NKFInputError):
    """A setting (resolution, lambda, method, device, ...) is out of range or unknown."""


class InvalidPointCloudError(NKFInputError):
    """The point array or the normal array has the wrong shape, type or content."""


class TooFewPointsError(InvalidPointCloudError):
    """Fewer usable points remain than the method needs."""


class DegenerateInputError(InvalidPointCloudError):
    """The points do not span a volume: all identical, on a line, or on a plane."""


class MissingNormalsError(InvalidPointCloudError):
    """The input has no normals, and the method needs oriented points."""


class PointCloudFileError(NKFInputError):
    """A point-cloud file is missing, unreadable, corrupt, or lacks required properties."""


class OutputPathError(NKFInputError):
    """The output file cannot be written where it was asked for."""


class NoSurfaceError(NKFInputError):
    """The fitted function has no zero level set inside the grid."""


class MethodUnavailableError(NKFInputError):
    """The requested method or device is not available in this installation."""


class MemoryBudgetError(InvalidParameterError):
    """The estimated memory of a run exceeds the memory budget; the message says which setting to
    lower. Raised before any large allocation."""


class Cancelled(Exception):
    """The work was stopped because the caller's cancel event was set."""


class WeightsError(NKFInputError):
    """A weights file for the learned kernel is missing, corrupt, or made for another model."""


class DefaultWeightsMissingError(WeightsError, MethodUnavailableError):
    """``method="nkf"`` was asked for without a weights file, and the package ships none."""


class InputWarning(UserWarning):
    """Some input rows were dropped (NaN, infinite, zero-length normals, duplicates)."""


class DeviceWarning(UserWarning):
    """The GPU could not be used (out of memory); the work was done on the CPU instead."""

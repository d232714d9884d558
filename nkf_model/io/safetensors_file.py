"""Reading safetensors files (weights of the learned kernel and of the sign check) with one set of
messages for every problem a file can have."""

from __future__ import annotations

from pathlib import Path

from ..errors import WeightsError


def read_safetensors(path, framework: str = "numpy"):
    """Tensors (as ``framework`` arrays: ``"numpy"`` or ``"pt"``) and metadata of a safetensors
    file: ``(dict, dict)``. Every problem raises :class:`~nkf_model.errors.WeightsError` naming
    the file."""
    from safetensors import safe_open

    path = Path(path)
    if not path.exists():
        raise WeightsError(f"weights file {path} does not exist")
    if not path.is_file():
        raise WeightsError(f"weights path {path} is not a file")
    try:
        with safe_open(str(path), framework=framework) as fh:
            meta = fh.metadata() or {}
            tensors = {k: fh.get_tensor(k) for k in fh.keys()}
    except PermissionError:
        raise WeightsError(f"weights file {path} cannot be read (permission denied)") from None
    except Exception as exc:  # safetensors raises its own error types for every kind of damage
        raise WeightsError(
            f"weights file {path} is not a valid safetensors file (truncated or corrupt?): {exc}"
        ) from None
    return tensors, meta

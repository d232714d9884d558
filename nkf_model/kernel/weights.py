"""Weights of the learned kernel: saving, loading and checking safetensors files.

A weights file is a safetensors file (never a pickle) holding the feature network's tensors
(float32) and, in its metadata, everything needed to rebuild and check the network:

* ``format`` = ``"nkf-weights"`` and ``format_version``;
* ``config``: the :class:`~nkf_model.kernel.feature_net.FeatureConfig` as JSON;
* ``lam``: the regularisation per constraint the kernel was trained with (the default for
  ``method="nkf"``);
* ``training``: a JSON summary of the run that made it (free form, shown in the model card).

Every problem with a file raises :class:`~nkf_model.errors.WeightsError` (an ``NKFInputError``)
with one sentence that names the file.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

from ..errors import DefaultWeightsMissingError, WeightsError
from ..io.safetensors_file import read_safetensors

FORMAT = "nkf-weights"
FORMAT_VERSION = "1"
DEFAULT_WEIGHTS = Path(__file__).resolve().parents[1] / "weights" / "nkf_default.safetensors"

_CACHE: dict = {}


def default_weights_path() -> Path:
    """Where the package's default weights live (they may be absent in a development checkout)."""
    return DEFAULT_WEIGHTS


def has_default_weights() -> bool:
    """True when the package ships default weights for ``method="nkf"``."""
    return DEFAULT_WEIGHTS.is_file()


def save_weights(path, net, *, lam: float, training: dict | None = None) -> Path:
    """Write ``net`` (a :class:`~nkf_model.kernel.feature_net.FeatureNet`) to ``path`` as safetensors.

    The file is written to a temporary name and renamed, so a crash never leaves half a file.
    """
    from safetensors.torch import save_file

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tensors = {k: v.detach().to("cpu").contiguous().clone() for k, v in net.state_dict().items()}
    meta = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "config": json.dumps(net.config.to_dict(), sort_keys=True),
        "lam": repr(float(lam)),
        "training": json.dumps(training or {}, sort_keys=True),
    }
    tmp = path.with_name(path.name + ".tmp")
    save_file(tensors, str(tmp), metadata=meta)
    tmp.replace(path)
    return path


def read_weights(path, framework: str = "pt"):
    """Tensors (``framework`` "pt" or "numpy") and metadata of a weights file, checked; returns
    ``(tensors, meta, config)``."""
    from .feature_config import FeatureConfig

    path = Path(path)
    tensors, meta = read_safetensors(path, framework=framework)
    if meta.get("format") != FORMAT:
        raise WeightsError(f"weights file {path} is a safetensors file but not NKF weights (no '{FORMAT}' tag)")
    if meta.get("format_version") != FORMAT_VERSION:
        raise WeightsError(
            f"weights file {path} has format version {meta.get('format_version')!r}; "
            f"this version of nkf_model reads version {FORMAT_VERSION}"
        )
    try:
        config = FeatureConfig.from_dict(json.loads(meta["config"]))
        lam = float(meta["lam"])
    except (KeyError, ValueError, TypeError) as exc:
        raise WeightsError(f"weights file {path} has an unreadable model configuration: {exc}") from None
    if not (math.isfinite(lam) and lam >= 0):
        raise WeightsError(f"weights file {path} stores an invalid lambda {meta['lam']!r}")
    return tensors, meta, config


def resolve_backend(backend: str = "auto") -> str:
    """The feature network's backend: ``"torch"`` or ``"numpy"``. ``"auto"`` is ``"torch"`` when
    PyTorch is already imported, else ``"numpy"`` (:mod:`~nkf_model.kernel.feature_net_numpy`: the
    same features within 1e-6 of PyTorch's, about as fast for this small network, and no
    3-second PyTorch import), so NKF runs on the CPU without PyTorch."""
    import sys

    if backend not in ("auto", "torch", "numpy"):
        raise ValueError(f"backend must be 'auto', 'torch' or 'numpy', got {backend!r}")
    if backend == "auto":
        return "torch" if sys.modules.get("torch") is not None else "numpy"
    return backend


def load_weights(path=None, backend: str = "auto"):
    """Load a :class:`~nkf_model.kernel.learned_kernel.LearnedKernel` from ``path`` (default: the shipped file).

    ``backend`` (see :func:`resolve_backend`): ``"torch"`` runs the PyTorch network, ``"numpy"`` its
    NumPy twin, ``"auto"`` PyTorch when it is already imported. Raises :class:`~nkf_model.errors.WeightsError` if
    the file is missing, not safetensors, truncated, or does not match the network its metadata
    describes.
    """
    backend = resolve_backend(backend)
    path = Path(path) if path is not None else DEFAULT_WEIGHTS
    if path is DEFAULT_WEIGHTS and not path.is_file():
        raise DefaultWeightsMissingError(
            f"this installation has no default weights for method 'nkf' ({path}); train them with "
            "'nkf train' and pass weights=PATH (--weights PATH), or use method 'splines'"
        )
    key = None
    try:
        st = path.stat()
        key = (str(path.resolve()), st.st_mtime_ns, st.st_size)
    except OSError:
        pass
    if key is not None:
        key = (*key, backend)
    if key is not None and key in _CACHE:
        return _CACHE[key]
    if backend == "numpy":
        model = _load_numpy(path)
    else:
        model = _load_torch(path)
    if key is not None:
        _CACHE[key] = model
    return model


def _check_tensors(path, tensors: dict, expected: dict) -> None:
    """Names, shapes, dtypes (float32) and finiteness of ``tensors`` against ``expected``
    (name -> shape); raises :class:`WeightsError` naming the file and the first problem."""
    import numpy as np

    missing = sorted(set(expected) - set(tensors))
    extra = sorted(set(tensors) - set(expected))
    if missing or extra:
        raise WeightsError(
            f"weights file {path} does not match its stored configuration "
            f"({len(missing)} tensors missing, {len(extra)} unexpected"
            + (f", e.g. missing {missing[0]}" if missing else f", e.g. unexpected {extra[0]}")
            + ")"
        )
    for k, shape in expected.items():
        if tuple(tensors[k].shape) != tuple(shape):
            raise WeightsError(
                f"weights file {path} does not match its stored configuration: tensor {k} has shape "
                f"{tuple(tensors[k].shape)}, the network needs {tuple(shape)}"
            )
        dtype = str(tensors[k].dtype).removeprefix("torch.")
        if dtype != "float32":
            raise WeightsError(f"weights file {path}: tensor {k} is {dtype}, expected float32")
        if not bool(np.isfinite(np.asarray(tensors[k])).all()):
            raise WeightsError(f"weights file {path}: tensor {k} holds NaN or infinite values (corrupt)")


def _load_numpy(path):
    from .feature_net_numpy import NumpyFeatureNet, expected_shapes
    from .learned_kernel import LearnedKernel

    tensors, meta, config = read_weights(path, framework="numpy")
    try:
        expected = expected_shapes(config)
    except ValueError as exc:
        raise WeightsError(f"weights file {path} describes an invalid network: {exc}") from None
    _check_tensors(path, tensors, expected)
    return LearnedKernel(NumpyFeatureNet(config, tensors), _meta(meta, path))


def _meta(meta: dict, path) -> dict:
    meta = dict(meta)
    meta["lam_value"] = float(meta["lam"])
    meta["path"] = str(path)
    return meta


def _load_torch(path):
    from .feature_net import FeatureNet
    from .learned_kernel import LearnedKernel

    tensors, meta, config = read_weights(path)
    try:
        net = FeatureNet(config)
    except ValueError as exc:
        raise WeightsError(f"weights file {path} describes an invalid network: {exc}") from None
    _check_tensors(path, tensors, {k: tuple(t.shape) for k, t in net.state_dict().items()})
    net.load_state_dict(tensors, strict=True)
    return LearnedKernel(net, _meta(meta, path))


def method_available(method: str) -> tuple[bool, str]:
    """``(available, reason)`` for a method of :func:`nkf_model.reconstruct` in this installation.

    ``"splines"`` always is; ``"nkf"`` is when the shipped default weights load (``reason`` then
    says why not, in one sentence).
    """
    if method == "splines":
        return True, ""
    if method != "nkf":
        return False, f"unknown method {method!r}"
    try:
        load_weights()
    except WeightsError as exc:
        return False, str(exc)
    return True, ""

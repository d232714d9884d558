"""Architecture of the feature network (:class:`FeatureConfig`), without PyTorch.

The weights file stores it as JSON (:mod:`nkf_model.kernel.weights`); the PyTorch network
(:mod:`nkf_model.kernel.feature_net`, which re-exports it) and its NumPy twin
(:mod:`nkf_model.kernel.feature_net_numpy`) are both built from it.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields


@dataclass(frozen=True)
class FeatureConfig:
    """Architecture of the feature network; stored in the weights file's metadata.

    Attributes
    ----------
    grid : int
        Cells per side M of the feature grid.
    pointnet_width : int
        Channels of the per-cell PointNet.
    unet_width : int
        Channels of the U-Net's finest level (doubled at each coarser level).
    unet_levels : int
        Resolution levels of the U-Net (2 or 3; ``grid`` must be divisible by 2^(levels-1)).
    feature_dim : int
        d, the number of learned feature channels.
    point_weights : bool
        Predict per-constraint weights (one more output channel).
    gate_init : float
        Initial value of the per-channel gate on ``tanh(raw)``.
    const_channel : bool
        Make the first feature a learned constant ``c`` (the same for every point). With it,
        ``[x : c : phi' : 1]`` has the inner products of ``[x : phi' : sqrt(1 + c^2)]``: a learned
        global scale of the kernel (``x`` scaled by ``1 / sqrt(1 + c^2)``), which the per-point
        features then modulate.
    const_init : float
        Initial ``log(c^2)``.
    """

    grid: int = 16
    pointnet_width: int = 32
    unet_width: int = 16
    unet_levels: int = 3
    feature_dim: int = 8
    point_weights: bool = False
    gate_init: float = 0.1
    const_channel: bool = False
    const_init: float = -3.0

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> FeatureConfig:
        names = {f.name for f in fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise ValueError(f"unknown feature-network settings: {', '.join(sorted(unknown))}")
        return cls(**d)

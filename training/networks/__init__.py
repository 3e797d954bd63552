"""GeoNet networks (PyTorch): DepthNet, PoseNet, ResFlowNet and their variants.

Layer details: docs/networks.md and ../shared/reference/geonet_spec.md (1-3).
"""

from __future__ import annotations

import torch.nn as nn

from training.networks.blocks import BN_EPS, BN_MOMENTUM, BatchNormNoScale
from training.networks.depthnet import DEPTH_ARCHS, DepthNet
from training.networks.posenet import POSE_ARCHS, PoseNet
from training.networks.resflownet import FLOW_ARCHS, ResFlowNet

# kind -> archs accepted by that network's constructor.
NETWORK_ARCHS = {"depth": DEPTH_ARCHS, "pose": POSE_ARCHS, "flow": FLOW_ARCHS}


def build_network(kind: str, arch: str, **kwargs) -> nn.Module:
    """``build_network("depth"|"pose"|"flow", arch, **constructor kwargs)``.

    PoseNet needs ``num_source=``; ResFlowNet accepts ``in_channels=``.
    """
    if kind not in NETWORK_ARCHS:
        raise ValueError(f"kind must be one of {tuple(NETWORK_ARCHS)}, got {kind!r}")
    if arch not in NETWORK_ARCHS[kind]:
        raise ValueError(f"{kind} arch must be one of {NETWORK_ARCHS[kind]}, got {arch!r}")
    if kind == "depth":
        return DepthNet(arch, **kwargs)
    if kind == "pose":
        return PoseNet(arch=arch, **kwargs)
    return ResFlowNet(arch, **kwargs)


__all__ = [
    "BN_EPS",
    "BN_MOMENTUM",
    "BatchNormNoScale",
    "DEPTH_ARCHS",
    "POSE_ARCHS",
    "FLOW_ARCHS",
    "NETWORK_ARCHS",
    "DepthNet",
    "PoseNet",
    "ResFlowNet",
    "build_network",
]

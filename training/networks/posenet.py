"""GeoNet PoseNet: target + source frames -> one 6-DoF pose per source (spec section 2).

Archs:
* ``standard``: GeoNet ``pose_net``: 7 stride-2 convs (TF 'SAME', BN, ReLU), 1x1
  conv to 6 * num_source (bias), spatial mean, x ``POSE.output_scale``.
* ``small``: same 7-conv topology and kernels with narrower layers (see
  docs/networks.md).
"""

from __future__ import annotations

import torch
import torch.nn as nn

from geonet_infer.conventions import POSE
from training.networks.blocks import BN_MOMENTUM, ConvBlock, init_xavier

POSE_ARCHS = ("standard", "small")
POSE_KERNELS = (7, 5, 3, 3, 3, 3, 3)
POSE_WIDTHS = {
    "standard": (16, 32, 64, 128, 256, 256, 256),
    "small": (16, 32, 48, 64, 96, 96, 96),
}


class PoseNet(nn.Module):
    """Frame stack -> poses.

    Args:
        num_source: number of source frames N (seq_len - 1).
        arch: "standard" | "small".
        bn_momentum: PyTorch BN momentum (1e-3 == TF decay 0.999).

    forward(x): x (B, 3 * (1 + N), H, W) in [-1, 1], channels
    [target, sources in temporal order] -> (B, N, 6) = [tx, ty, tz, rx, ry, rz]
    (target -> source, Euler radians, see ``POSE``); the ``POSE.output_scale``
    (0.01) factor is applied inside the net so an export carries it.
    """

    def __init__(self, num_source: int, arch: str = "standard", bn_momentum: float = BN_MOMENTUM):
        super().__init__()
        if arch not in POSE_ARCHS:
            raise ValueError(f"PoseNet arch must be one of {POSE_ARCHS}, got {arch!r}")
        if num_source < 1:
            raise ValueError(f"num_source must be >= 1, got {num_source}")
        self.arch = arch
        self.num_source = num_source
        in_ch = 3 * (1 + num_source)
        layers = []
        for kernel, width in zip(POSE_KERNELS, POSE_WIDTHS[arch]):
            layers.append(ConvBlock(in_ch, width, kernel, 2, bn_momentum, padding="same"))
            in_ch = width
        self.convs = nn.Sequential(*layers)
        # slim 1x1 conv with bias, no BN / activation.
        self.pose_pred = nn.Conv2d(in_ch, 6 * num_source, 1, 1, bias=True)
        init_xavier(self)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        pose = self.pose_pred(self.convs(x))  # (B, 6N, h, w)
        pose = pose.mean(dim=(2, 3))  # (B, 6N)
        return POSE.output_scale * pose.reshape(-1, self.num_source, 6)

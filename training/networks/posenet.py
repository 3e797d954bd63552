"""GeoNet PoseNet: target + source frames -> one 6-DoF pose per source (spec section 2).

Archs:
* ``standard``: GeoNet ``pose_net``: 7 stride-2 convs (TF 'SAME', BN, ReLU), 1x1
  conv to 6 * num_source (bias), spatial mean, x ``POSE.output_scale``.
* ``small``: same 7-conv topology and kernels with narrower layers (see
  docs/networks.md).

Optional (not in GeoNet, issue 53): a :class:`MotionGate` that multiplies every pose by the
probability that the camera moves, so a stopped camera gets the identity whatever the trunk says.
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


GATE_WIDTH = 16  # a gate's first width; its five stride-2 3x3 convs are (w, 2w, 2w, 4w, 4w) wide: 128x416 -> 4x13
GATE_OPEN_LOGIT = 4.0  # a new gate starts open (sigmoid 0.98): the trunk's poses nearly unchanged


class MotionGate(nn.Module):
    """Frame stack -> (B, 1, 1) probability that the camera moves between the frames.

    Five stride-2 3x3 convs with ReLU (``width``: the first one's channels), no batch norm (its batch
    statistics differ between a training batch and one inference call, and a gate must give one answer
    for one snippet),
    spatial mean, one linear unit, sigmoid. Input as PoseNet's: (B, 3 * (1 + N), H, W) in [-1, 1].
    Trained alone on motion labels (``training.losses.gate_error``, on :meth:`logits`). ``hard``: outside
    training the gate is a step at probability 1/2 (1 moving, 0 still), so a confident gate never rescales
    a moving snippet's poses (round 19's soft gate gave one held-out snippet 0.76 and cost the held-out ATE).
    """

    def __init__(self, in_ch: int, hard: bool = False, width: int = GATE_WIDTH):
        super().__init__()
        self.hard = hard
        layers: list[nn.Module] = []
        for out_ch in (width, 2 * width, 2 * width, 4 * width, 4 * width):
            layers += [nn.Conv2d(in_ch, out_ch, 3, 2, 1), nn.ReLU()]
            in_ch = out_ch
        self.convs = nn.Sequential(*layers)
        self.logit = nn.Linear(in_ch, 1)
        init_xavier(self)
        nn.init.constant_(self.logit.bias, GATE_OPEN_LOGIT)

    def logits(self, x: torch.Tensor) -> torch.Tensor:
        """(B,) the logit of moving (what the loss reads: stable where the sigmoid saturates)."""
        return self.logit(self.convs(x).mean(dim=(2, 3)))[:, 0]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        logits = self.logits(x)[:, None, None]
        if self.hard and not self.training:  # a step: a moving snippet's poses pass exactly as the trunk gives them
            return (logits > 0).to(logits.dtype)
        return torch.sigmoid(logits)


class PoseNet(nn.Module):
    """Frame stack -> poses.

    Args:
        num_source: number of source frames N (seq_len - 1).
        arch: "standard" | "small".
        bn_momentum: PyTorch BN momentum (1e-3 == TF decay 0.999).
        gate: add a :class:`MotionGate` (``self.gate``) whose output multiplies every pose: "soft" (its
            probability) or "hard" (a step at 1/2 outside training); None: no gate. ``gate_width``: its width.

    forward(x): x (B, 3 * (1 + N), H, W) in [-1, 1], channels
    [target, sources in temporal order] -> (B, N, 6) = [tx, ty, tz, rx, ry, rz]
    (target -> source, Euler radians, see ``POSE``); the ``POSE.output_scale``
    (0.01) factor is applied inside the net so an export carries it.
    """

    def __init__(
        self,
        num_source: int,
        arch: str = "standard",
        bn_momentum: float = BN_MOMENTUM,
        gate: str | None = None,
        gate_width: int = GATE_WIDTH,
    ):
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
        if gate not in (None, "soft", "hard"):
            raise ValueError(f"PoseNet gate must be None, 'soft' or 'hard', got {gate!r}")
        in_ch = 3 * (1 + num_source)
        self.gate = None if gate is None else MotionGate(in_ch, hard=gate == "hard", width=gate_width)  # own init

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        pose = self.pose_pred(self.convs(x))  # (B, 6N, h, w)
        pose = pose.mean(dim=(2, 3))  # (B, 6N)
        pose = POSE.output_scale * pose.reshape(-1, self.num_source, 6)
        return pose if self.gate is None else pose * self.gate(x)

"""GeoNet ResFlowNet: image pair + rigid cues -> residual flow pyramid (spec section 3).

Same encoder/decoder as DepthNet (separate weights) with 2-channel heads
``FLOW_SCALING * conv3x3`` (no activation): the flow normalised by the image size
at that scale. That normalised prediction is what the decoder upsamples (nearest)
and feeds to the next level, as in GeoNet; ``forward`` converts the returned
flows to pixels (x by W_s, y by H_s).

Input channels (in_channels=12, "residual"): [I_t (3), I_s (3), I_s rigidly warped
to t (3), rigid flow t->s (2, pixels, scale 0), rigid photometric error (1)];
in_channels=6 is the "direct" ablation (first 6 channels only). Building that
input (and adding the rigid flow to get the full flow) is the trainer's job.
"""

from __future__ import annotations

import torch
import torch.nn as nn

from geonet_infer.conventions import FLOW_SCALING
from training.networks.blocks import (
    BN_MOMENTUM,
    ResNet50Encoder,
    SmallResNetEncoder,
    UpconvDecoder,
    conv3x3_head,
    init_xavier,
)
from training.networks.depthnet import RESNET_DECODER_WIDTHS, SMALL_DECODER_WIDTHS

FLOW_ARCHS = ("resnet50", "small")


class FlowPredHead(nn.Module):
    """3x3 conv (bias) x FLOW_SCALING: (B,C,h,w) -> flow normalised by (w, h), (B,2,h,w)."""

    def __init__(self, in_ch: int):
        super().__init__()
        self.conv = conv3x3_head(in_ch, 2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return FLOW_SCALING * self.conv(x)


class ResFlowNet(nn.Module):
    """Residual flow network.

    Args:
        arch: "resnet50" | "small".
        bn_momentum: PyTorch BN momentum (1e-3 == TF decay 0.999).
        in_channels: 12 (residual, default) or 6 (direct ablation).

    forward(x): x (B, in_channels, H, W), H and W multiples of 8 -> list of 4
    residual flows IN PIXELS, scale 0 first, (B,2,H_s,W_s) with H_s = H / 2**s;
    channel 0 is the x (column) displacement, channel 1 the y (row) one.
    """

    def __init__(self, arch: str = "resnet50", bn_momentum: float = BN_MOMENTUM, in_channels: int = 12):
        super().__init__()
        if arch not in FLOW_ARCHS:
            raise ValueError(f"ResFlowNet arch must be one of {FLOW_ARCHS}, got {arch!r}")
        self.arch = arch
        self.in_channels = in_channels
        if arch == "resnet50":
            self.encoder = ResNet50Encoder(in_channels, bn_momentum)
            widths = RESNET_DECODER_WIDTHS
        else:
            self.encoder = SmallResNetEncoder(in_channels, bn_momentum)
            widths = SMALL_DECODER_WIDTHS
        self.decoder = UpconvDecoder(
            self.encoder.out_channels,
            self.encoder.skip_channels,
            widths,
            FlowPredHead,
            pred_channels=2,
            pred_upsample="nearest",
            bn_momentum=bn_momentum,
        )
        init_xavier(self)

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        bottleneck, skips = self.encoder(x)
        flows_normalised = self.decoder(bottleneck, skips)  # [(B,2,H_s,W_s)] in image-size units
        flows_px = []
        for flow in flows_normalised:
            h_s, w_s = flow.shape[-2], flow.shape[-1]
            # (1,2,1,1) per-channel factor (W_s, H_s); a new tensor, no in-place writes.
            size = torch.tensor([w_s, h_s], dtype=flow.dtype, device=flow.device).view(1, 2, 1, 1)
            flows_px.append(flow * size)
        return flows_px

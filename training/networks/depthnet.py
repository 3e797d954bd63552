"""GeoNet DepthNet: image -> 4 disparity maps (spec section 1).

Archs:
* ``resnet50``: GeoNet ``build_resnet50`` (ResNet50-style encoder, upconv decoder,
  nearest pred upsampling), heads 5 * sigmoid + 0.01 (``DISP_HEADS``).
* ``vgg``: GeoNet ``build_vgg`` (DispNet encoder with TF 'SAME' padding, upconv
  decoder, TF legacy bilinear pred upsampling), heads 10 * sigmoid + 0.01.
* ``small``: our CPU-trainable variant (see docs/networks.md), heads as resnet50.
"""

from __future__ import annotations

import torch
import torch.nn as nn

from geonet_infer.conventions import DISP_HEADS
from training.networks.blocks import (
    BN_MOMENTUM,
    ConvBlock,
    ResNet50Encoder,
    SmallResNetEncoder,
    UpconvDecoder,
    conv3x3_head,
    init_xavier,
)

DEPTH_ARCHS = ("resnet50", "vgg", "small")

# Decoder widths, coarse to fine (upconv/iconv of each level).
RESNET_DECODER_WIDTHS = (512, 256, 128, 64, 32, 16)
VGG_DECODER_WIDTHS = (512, 512, 256, 128, 64, 32, 16)
SMALL_DECODER_WIDTHS = (128, 64, 32, 16, 16, 8)


class DispPredHead(nn.Module):
    """3x3 conv (bias) -> ``scale * sigmoid + offset``: (B,C,h,w) -> disparity (B,1,h,w)."""

    def __init__(self, in_ch: int, scale: float, offset: float):
        super().__init__()
        self.conv = conv3x3_head(in_ch, 1)
        self.scale = scale
        self.offset = offset

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.scale * torch.sigmoid(self.conv(x)) + self.offset


class VGGEncoder(nn.Module):
    """GeoNet ``build_vgg`` encoder (SfMLearner DispNet), TF 'SAME' padding.

    7 pairs (conv s2, convb s1) with (kernel, channels) (7,32) (5,64) (3,128)
    (3,256) (3,512) (3,512) (3,512). Stride-2 'SAME' pads put the extra pixel at
    the bottom/right, exactly as TF.

    forward: (B,3,H,W) -> (conv7b (B,512,H/128,W/128),
    skips fine-to-coarse [conv1b H/2 32ch, conv2b H/4 64ch, conv3b H/8 128ch,
    conv4b H/16 256ch, conv5b H/32 512ch, conv6b H/64 512ch]).
    """

    spec = ((7, 32), (5, 64), (3, 128), (3, 256), (3, 512), (3, 512), (3, 512))
    skip_channels = (32, 64, 128, 256, 512, 512)
    out_channels = 512

    def __init__(self, in_ch: int = 3, bn_momentum: float = BN_MOMENTUM):
        super().__init__()
        pairs = []
        for kernel, ch in self.spec:
            pairs.append(
                nn.Sequential(
                    ConvBlock(in_ch, ch, kernel, 2, bn_momentum, padding="same"),
                    ConvBlock(ch, ch, kernel, 1, bn_momentum, padding="same"),
                )
            )
            in_ch = ch
        self.pairs = nn.ModuleList(pairs)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, list[torch.Tensor]]:
        skips = []
        for pair in self.pairs:
            x = pair(x)
            skips.append(x)
        return skips[-1], skips[:-1]


class DepthNet(nn.Module):
    """Single image -> disparity pyramid.

    Args:
        arch: "resnet50" | "vgg" | "small".
        bn_momentum: PyTorch BN momentum (1e-3 == TF decay 0.999).

    forward(x): x (B,3,H,W) in [-1, 1] (``IMAGE_NORM`` applied by the caller), H and
    W multiples of 8 -> list of 4 disparities, scale 0 first:
    (B,1,H,W), (B,1,H/2,W/2), (B,1,H/4,W/4), (B,1,H/8,W/8), each in
    [offset, scale + offset] of ``DISP_HEADS[arch]``. depth = 1 / disparity.
    """

    def __init__(self, arch: str = "resnet50", bn_momentum: float = BN_MOMENTUM):
        super().__init__()
        if arch not in DEPTH_ARCHS:
            raise ValueError(f"DepthNet arch must be one of {DEPTH_ARCHS}, got {arch!r}")
        self.arch = arch
        head = DISP_HEADS[arch]

        def make_head(in_ch: int) -> nn.Module:
            return DispPredHead(in_ch, head.scale, head.offset)

        if arch == "resnet50":
            self.encoder = ResNet50Encoder(3, bn_momentum)
            widths, pred_upsample = RESNET_DECODER_WIDTHS, "nearest"
        elif arch == "small":
            self.encoder = SmallResNetEncoder(3, bn_momentum)
            widths, pred_upsample = SMALL_DECODER_WIDTHS, "nearest"
        else:
            self.encoder = VGGEncoder(3, bn_momentum)
            widths, pred_upsample = VGG_DECODER_WIDTHS, "bilinear_tf_legacy"
        self.decoder = UpconvDecoder(
            self.encoder.out_channels,
            self.encoder.skip_channels,
            widths,
            make_head,
            pred_channels=1,
            pred_upsample=pred_upsample,
            bn_momentum=bn_momentum,
        )
        init_xavier(self)

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        bottleneck, skips = self.encoder(x)
        return self.decoder(bottleneck, skips)

"""DepthNet's finest decoder level at half resolution (the "phase form"): the same function, graphs whose INT8
runs faster.

The finest level of a nearest-upsampling :class:`~training.networks.blocks.UpconvDecoder` (GeoNet's: no skip,
the scale-1 prediction fed back) works at full resolution with few channels: for the small DepthNet,
nearest x2 -> 3x3 conv 16->8 -> concat the upsampled scale-1 disparity -> 3x3 conv 9->8 -> 3x3 conv 8->1,
at 128x416, where the int8 kernels of onnxruntime run far below their speed (about 5.7 of DepthNet's
11 INT8 ms, one thread). Each full-resolution pixel (2i+a, 2j+b) is one of four "phases" of the
half-resolution pixel (i, j), so:

* a 3x3 conv (pad 1) of a nearest-x2-upsampled input is a 3x3 conv of the input itself to the four output
  phases (:func:`upsampled_conv_to_phases`);
* a 3x3 conv at full resolution is a 3x3 conv from the four input phases to the four output phases
  (:func:`full_res_conv_to_phases`; 9 of its 36 taps per channel pair are non-zero);
* the upsampled scale-1 prediction's four phases are the prediction itself: their taps add up;
* one ``pixel_shuffle`` (ONNX DepthToSpace) puts the phases back at the end.

Zero padding is the same pixels in both layouts, batch norm is folded into the convolutions, the head's
activation runs after the shuffle: the output equals the trained layout's up to float summation order
(7e-7 on the shipped DepthNet's disparity). Layers of 16->32, 33->32 and 32->4 channels at 64x208 replace
16->8, 9->8 and 8->1 at 128x416; the last two do up to 4x the multiply-adds (the zero taps), which the
int8 kernels repay: shipped DepthNet, one thread, AMD EPYC Zen 4, onnxruntime INT8 10.9 -> 7.5 ms, OpenVINO
INT8 4.9 -> 4.4, OpenVINO FP32 13.1 -> 12.7, onnxruntime FP32 14.4 -> 14.6 (docs/depthnet_phase_form.json,
``python -m experiments.depthnet_phase_form``). Training is untouched: this is how the export writes the
trained weights (:func:`export_depth_net`).
"""

from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F

from training.networks.blocks import ConvBlock, UpconvDecoder

# Where the phase form was measured (the shipped small DepthNet). resnet50's finest level is 16 channels wide
# and its graphs are also written by ``geonet-infer convert`` from templates of the trained layout: not
# measured, left as trained. VGG feeds its prediction back with bilinear upsampling: not this form.
PHASE_FORM_ARCHS = ("small",)

PHASES = ((0, 0), (0, 1), (1, 0), (1, 1))  # (row, column) offset in the 2x2 block; pixel_shuffle's channel order


def _tap(offset: int) -> tuple[int, int]:
    """A full-resolution row (or column) offset from a block's first pixel -> (half-resolution offset, phase)."""
    return offset // 2, offset % 2


def upsampled_conv_to_phases(weight: torch.Tensor) -> torch.Tensor:
    """A 3x3 conv (pad 1) of a nearest-x2-upsampled input, as a 3x3 conv (pad 1) of the input itself whose
    output channel ``o * 4 + phase`` is output channel o at that phase (``F.pixel_shuffle(y, 2)`` restores it).

    (Co, Ci, 3, 3) -> (4 Co, Ci, 3, 3): the upsampled input's four phases are the input itself
    (:func:`_read_at_every_phase`); the zero padding of both is the same pixels."""
    return _read_at_every_phase(full_res_conv_to_phases(weight))


def _read_at_every_phase(phase_weight: torch.Tensor) -> torch.Tensor:
    """Phase-form weights (4 Co, 4 Ci, 3, 3) of an input whose four phases are one tensor (a nearest-x2
    upsampled one) -> (4 Co, Ci, 3, 3) reading that tensor once: each channel's four phase taps add up."""
    return phase_weight.reshape(phase_weight.shape[0], -1, 4, 3, 3).sum(2)


def full_res_conv_to_phases(weight: torch.Tensor) -> torch.Tensor:
    """A 3x3 conv (pad 1) at full resolution, as a 3x3 conv (pad 1) from ``F.pixel_unshuffle(x, 2)`` to the
    output's phases (channel ``c * 4 + phase`` on both sides, ``F.pixel_shuffle``'s order).

    (Co, Ci, 3, 3) -> (4 Co, 4 Ci, 3, 3); 9 of each output phase's 36 taps per input channel are non-zero."""
    co, ci = weight.shape[:2]
    out = weight.new_zeros(co * 4, ci * 4, 3, 3)
    rows, cols = torch.arange(co) * 4, torch.arange(ci) * 4
    for phase, (a, b) in enumerate(PHASES):
        for ky in range(3):
            for kx in range(3):
                (p, pa), (q, pb) = _tap(a + ky - 1), _tap(b + kx - 1)
                out[(rows + phase)[:, None], (cols + pa * 2 + pb)[None, :], p + 1, q + 1] += weight[:, :, ky, kx]
    return out


def fold_batch_norm(block: ConvBlock) -> tuple[torch.Tensor, torch.Tensor]:
    """(weight, bias) of the conv + inference-mode BatchNormNoScale of ``block`` as one conv."""
    bn = block.bn
    inv_std = torch.rsqrt(bn.running_var + bn.eps)
    return block.conv.weight * inv_std[:, None, None, None], bn.bias - bn.running_mean * inv_std


class PhaseFinestLevel(nn.Module):
    """The finest level of a DepthNet's :class:`UpconvDecoder` (no skip, the scale-1 disparity fed back through
    nearest upsampling, the ``scale * sigmoid + offset`` head) computed at half resolution:
    (x (B,C,h,w) the level's input, pred (B,1,h,w) the scale-1 disparity) -> disparity (B,1,2h,2w),
    the same function as the decoder's."""

    def __init__(self, decoder: UpconvDecoder):
        super().__init__()
        if decoder.pred_upsample != "nearest":
            raise ValueError("the phase form assumes nearest upsampling of the fed-back prediction")
        level = decoder.num_levels - 1
        head = decoder.heads[0]  # DispPredHead: its activation runs on the shuffled phases
        self.scale, self.offset = head.scale, head.offset
        with torch.no_grad():
            up_w, up_b = fold_batch_norm(decoder.upconvs[level].conv)
            ic_w, ic_b = fold_batch_norm(decoder.iconvs[level])
            width = up_w.shape[0]
            phases = full_res_conv_to_phases(ic_w)
            fed = _read_at_every_phase(phases[:, width * 4 :])  # the scale-1 prediction, upsampled nearest
            self.upconv = self._conv(upsampled_conv_to_phases(up_w), up_b.repeat_interleave(4))
            self.iconv = self._conv(torch.cat([phases[:, : width * 4], fed], 1), ic_b.repeat_interleave(4))
            self.head = self._conv(full_res_conv_to_phases(head.conv.weight), head.conv.bias.repeat_interleave(4))

    @staticmethod
    def _conv(weight: torch.Tensor, bias: torch.Tensor) -> nn.Conv2d:
        conv = nn.Conv2d(weight.shape[1], weight.shape[0], 3, 1, padding=1)
        conv.weight.data.copy_(weight)
        conv.bias.data.copy_(bias)
        return conv

    def forward(self, x: torch.Tensor, pred: torch.Tensor) -> torch.Tensor:
        x = F.relu(self.upconv(x))
        x = F.relu(self.iconv(torch.cat([x, pred], 1)))
        logits = F.pixel_shuffle(self.head(x), 2)
        return self.scale * torch.sigmoid(logits) + self.offset


class PhaseDepthNet(nn.Module):
    """A trained DepthNet with its finest decoder level in phase form: image -> [disparity at scale 0]."""

    def __init__(self, depth_net: nn.Module):
        super().__init__()
        self.encoder = depth_net.encoder
        self.decoder = depth_net.decoder
        self.finest = PhaseFinestLevel(depth_net.decoder)

    def forward(self, image: torch.Tensor) -> list[torch.Tensor]:
        bottleneck, skips = self.encoder(image)
        x, preds = self.decoder.run_levels(bottleneck, skips, self.decoder.num_levels - 1)
        return [self.finest(x, preds[-1])]


def export_depth_net(depth_net: nn.Module) -> nn.Module:
    """The DepthNet module the export writes: the phase form for :data:`PHASE_FORM_ARCHS`, else ``depth_net``."""
    return PhaseDepthNet(depth_net) if getattr(depth_net, "arch", None) in PHASE_FORM_ARCHS else depth_net

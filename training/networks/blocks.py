"""Building blocks shared by DepthNet, PoseNet and ResFlowNet.

Layer conventions follow the official TF code (yzcjtr/GeoNet ``geonet_nets.py``,
slim defaults), see ``../shared/reference/geonet_spec.md`` sections 0-3:

* every non-head conv is conv (no bias) -> BatchNorm (eps 1e-3, beta only) -> ReLU;
* the ResNet path pads symmetrically with (k - 1) // 2 (GeoNet's ``conv`` helper);
* the VGG and PoseNet paths use TF 'SAME' padding, asymmetric for stride 2;
* "upconv" is nearest x2 upsampling then a 3x3 conv (not a transposed conv);
* Xavier-uniform weights, zero biases (slim's defaults).

Everything here exports to ONNX (Conv, BatchNormalization, Relu, Pad, MaxPool,
Resize(nearest), Gather, Concat): no in-place ops on views, no data-dependent
control flow (the only branches depend on static tensor sizes).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import torch
import torch.nn as nn
import torch.nn.functional as F

BN_EPS = 1e-3  # slim.batch_norm default epsilon
BN_MOMENTUM = 1e-3  # PyTorch convention: 1 - TF decay (0.999)


class BatchNormNoScale(nn.BatchNorm2d):
    """slim ``batch_norm`` defaults: center=True, **scale=False** (beta, no gamma).

    Built with ``affine=False`` (so ``self.weight`` is None) plus an own learnable
    ``bias`` (beta). ``F.batch_norm`` with ``weight=None`` exports to ONNX as a
    plain BatchNormalization (scale filled with ones), so no custom op is needed.
    """

    def __init__(self, num_features: int, momentum: float = BN_MOMENTUM, eps: float = BN_EPS):
        super().__init__(num_features, eps=eps, momentum=momentum, affine=False)
        self.bias = nn.Parameter(torch.zeros(num_features))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        # Same mode logic as nn.BatchNorm2d (momentum is always set, so the
        # num_batches_tracked counter is only kept for state_dict compatibility).
        if self.training and self.track_running_stats:
            self.num_batches_tracked.add_(1)
        use_batch_stats = self.training or not self.track_running_stats
        return F.batch_norm(
            x,
            self.running_mean,
            self.running_var,
            None,
            self.bias,
            use_batch_stats,
            self.momentum,
            self.eps,
        )


def tf_same_pads(in_h: int, in_w: int, kernel: int, stride: int) -> tuple[int, int, int, int]:
    """TF 'SAME' padding as (left, right, top, bottom) for F.pad.

    out = ceil(in / stride); total = max((out - 1) * stride + kernel - in, 0);
    TF puts total // 2 before and the rest after, so for stride 2 the extra
    pixel goes to the bottom / right (e.g. k3 s2 on an even size pads (0, 1)).
    """

    def one_dim(size: int) -> tuple[int, int]:
        out = -(-size // stride)
        total = max((out - 1) * stride + kernel - size, 0)
        return total // 2, total - total // 2

    top, bottom = one_dim(in_h)
    left, right = one_dim(in_w)
    return left, right, top, bottom


class Conv2dSame(nn.Conv2d):
    """nn.Conv2d with TF 'SAME' padding (square odd kernel, no dilation).

    When the TF pads are symmetric (always for stride 1) the conv pads itself;
    otherwise an explicit zero F.pad precedes a VALID conv. The pads depend only
    on the static input size, so the ONNX graph gets constant Pad values.
    """

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int, stride: int = 1, bias: bool = True):
        super().__init__(in_channels, out_channels, kernel_size, stride, padding=0, bias=bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        left, right, top, bottom = tf_same_pads(x.shape[-2], x.shape[-1], self.kernel_size[0], self.stride[0])
        if left == right and top == bottom:
            return F.conv2d(x, self.weight, self.bias, self.stride, (top, left))
        x = F.pad(x, (left, right, top, bottom))
        return F.conv2d(x, self.weight, self.bias, self.stride, 0)


class ConvBlock(nn.Module):
    """conv (no bias) -> BatchNormNoScale -> ReLU (ReLU optional).

    padding="symmetric": GeoNet's ``conv`` helper, pad (k - 1) // 2 on every side;
        a stride-2 output is ceil(in / 2).
    padding="same": TF 'SAME' (slim.conv2d default), see :class:`Conv2dSame`.
    """

    def __init__(
        self,
        in_ch: int,
        out_ch: int,
        kernel: int,
        stride: int = 1,
        bn_momentum: float = BN_MOMENTUM,
        relu: bool = True,
        padding: str = "symmetric",
    ):
        super().__init__()
        if padding == "symmetric":
            self.conv = nn.Conv2d(in_ch, out_ch, kernel, stride, padding=(kernel - 1) // 2, bias=False)
        elif padding == "same":
            self.conv = Conv2dSame(in_ch, out_ch, kernel, stride, bias=False)
        else:
            raise ValueError(f"padding must be 'symmetric' or 'same', got {padding!r}")
        self.bn = BatchNormNoScale(out_ch, momentum=bn_momentum)
        self.relu = relu

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.bn(self.conv(x))
        return F.relu(x) if self.relu else x


def conv3x3_head(in_ch: int, out_ch: int) -> nn.Conv2d:
    """Prediction head conv: 3x3, stride 1, pad 1, with bias, no BN/activation here."""
    return nn.Conv2d(in_ch, out_ch, 3, 1, padding=1, bias=True)


def upsample_nn(x: torch.Tensor, ratio: int = 2) -> torch.Tensor:
    """(B,C,h,w) -> (B,C,h*ratio,w*ratio), nearest (TF resize_nearest_neighbor)."""
    return F.interpolate(x, scale_factor=ratio, mode="nearest")


def resize_like(x: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """Nearest-resize x (B,C,h,w) to ref's (H,W) when they differ (GeoNet ``resize_like``).

    torch 'nearest' uses src = floor(dst * in / out), the same rule as TF1's
    legacy resize_nearest_neighbor, and exports as ONNX Resize(asymmetric, floor).
    """
    if x.shape[-2:] == ref.shape[-2:]:
        return x
    return F.interpolate(x, size=(int(ref.shape[-2]), int(ref.shape[-1])), mode="nearest")


def _legacy_linear_taps(in_size: int, out_size: int) -> tuple[list[int], list[int], list[float]]:
    """Taps of TF1 legacy resize_bilinear along one axis: src = dst * in / out (no half pixel)."""
    scale = in_size / out_size
    idx0, idx1, frac = [], [], []
    for dst in range(out_size):
        src = dst * scale
        i0 = min(int(math.floor(src)), in_size - 1)
        idx0.append(i0)
        idx1.append(min(i0 + 1, in_size - 1))
        frac.append(src - i0)
    return idx0, idx1, frac


def resize_bilinear_tf_legacy(x: torch.Tensor, size: Sequence[int]) -> torch.Tensor:
    """TF1 ``tf.image.resize_bilinear`` (align_corners=False, legacy, no half-pixel centres).

    (B,C,h,w) -> (B,C,H,W). TF legacy maps dst -> src = dst * in / out, which is
    ONNX Resize 'asymmetric'; torch's F.interpolate(bilinear) offers only
    half-pixel (align_corners=False) or corner-aligned (True), both of which differ
    (for x2: by a quarter input pixel / by a stretch). So we do the exact TF rule as
    two separable linear interpolations with constant index tensors: exports as
    Gather + Mul + Add, exact for any size. Used only for the 1-channel VGG
    disparity maps, so its cost is negligible.
    """
    out_h, out_w = int(size[0]), int(size[1])
    for dim, out_size in ((-2, out_h), (-1, out_w)):
        in_size = x.shape[dim]
        if in_size == out_size:
            continue
        idx0, idx1, frac = _legacy_linear_taps(in_size, out_size)
        i0 = torch.tensor(idx0, dtype=torch.long, device=x.device)
        i1 = torch.tensor(idx1, dtype=torch.long, device=x.device)
        w = torch.tensor(frac, dtype=x.dtype, device=x.device)
        w = w.view(-1, 1) if dim == -2 else w.view(1, -1)
        x0 = x.index_select(x.dim() + dim, i0)
        x1 = x.index_select(x.dim() + dim, i1)
        x = x0 + (x1 - x0) * w
    return x


class UpConv(nn.Module):
    """GeoNet ``upconv``: nearest x2 then 3x3 conv-BN-ReLU. (B,in,h,w) -> (B,out,2h,2w)."""

    def __init__(self, in_ch: int, out_ch: int, bn_momentum: float = BN_MOMENTUM):
        super().__init__()
        self.conv = ConvBlock(in_ch, out_ch, 3, 1, bn_momentum)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.conv(upsample_nn(x, 2))


class Bottleneck(nn.Module):
    """GeoNet ``resconv``: 1x1(w) -> 3x3(w, stride) -> 1x1(4w, BN, no ReLU) + shortcut, ReLU.

    The shortcut is ALWAYS a 1x1 projection conv + BN (stride as the block): the
    official ``tf.shape(x)[3] != num_layers`` test is always True (kept bug from
    monodepth), and it changes the parameter count, so we keep it.
    """

    def __init__(self, in_ch: int, width: int, stride: int, bn_momentum: float = BN_MOMENTUM):
        super().__init__()
        self.conv1 = ConvBlock(in_ch, width, 1, 1, bn_momentum)
        self.conv2 = ConvBlock(width, width, 3, stride, bn_momentum)
        self.conv3 = ConvBlock(width, 4 * width, 1, 1, bn_momentum, relu=False)
        self.shortcut = ConvBlock(in_ch, 4 * width, 1, stride, bn_momentum, relu=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.relu(self.conv3(self.conv2(self.conv1(x))) + self.shortcut(x))


class BasicBlock(nn.Module):
    """ResNet basic block for the ``small`` nets: 3x3(stride) -> 3x3(no ReLU) + shortcut, ReLU.

    Unlike :class:`Bottleneck` the shortcut is the identity when the shape is kept
    (standard ResNet): the small nets are our own design, not a port.
    """

    def __init__(self, in_ch: int, out_ch: int, stride: int, bn_momentum: float = BN_MOMENTUM):
        super().__init__()
        self.conv1 = ConvBlock(in_ch, out_ch, 3, stride, bn_momentum)
        self.conv2 = ConvBlock(out_ch, out_ch, 3, 1, bn_momentum, relu=False)
        if stride != 1 or in_ch != out_ch:
            self.shortcut = ConvBlock(in_ch, out_ch, 1, stride, bn_momentum, relu=False)
        else:
            self.shortcut = nn.Identity()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.relu(self.conv2(self.conv1(x)) + self.shortcut(x))


class _StemStagesEncoder(nn.Module):
    """conv1 -> pool1 -> 4 stages; subclasses build ``conv1``, ``pool1`` and ``stages``."""

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, list[torch.Tensor]]:
        conv1 = self.conv1(x)
        pool1 = self.pool1(conv1)
        s1 = self.stages[0](pool1)
        s2 = self.stages[1](s1)
        s3 = self.stages[2](s2)
        s4 = self.stages[3](s3)
        return s4, [conv1, pool1, s1, s2, s3]


class ResNet50Encoder(_StemStagesEncoder):
    """GeoNet ``build_resnet50`` encoder (not torchvision-compatible).

    conv1 7x7/2 (64) -> maxpool 3x3/2 -> 4 bottleneck stages (3, 4, 6, 3 blocks;
    widths 64, 128, 256, 512; outputs 256, 512, 1024, 2048). The stride-2 block is
    the LAST block of every stage, stage 1 included, so the bottleneck is at H/64.

    forward: (B,in_ch,H,W) -> (bottleneck (B,2048,H/64,W/64),
    skips fine-to-coarse [conv1 H/2 64ch, pool1 H/4 64ch, stage1 H/8 256ch,
    stage2 H/16 512ch, stage3 H/32 1024ch]).
    """

    skip_channels = (64, 64, 256, 512, 1024)
    out_channels = 2048

    def __init__(self, in_ch: int = 3, bn_momentum: float = BN_MOMENTUM):
        super().__init__()
        self.conv1 = ConvBlock(in_ch, 64, 7, 2, bn_momentum)
        # GeoNet zero-pads by 1 then max-pools VALID; the input is post-ReLU (>= 0),
        # so zero padding equals PyTorch's -inf padding.
        self.pool1 = nn.MaxPool2d(3, 2, padding=1)
        stages = []
        in_ch = 64
        for width, num_blocks in ((64, 3), (128, 4), (256, 6), (512, 3)):
            blocks = []
            for i in range(num_blocks):
                stride = 2 if i == num_blocks - 1 else 1
                blocks.append(Bottleneck(in_ch, width, stride, bn_momentum))
                in_ch = 4 * width
            stages.append(nn.Sequential(*blocks))
        self.stages = nn.ModuleList(stages)


class SmallResNetEncoder(_StemStagesEncoder):
    """Encoder of the ``small`` nets: same pyramid as :class:`ResNet50Encoder`, far cheaper.

    conv1 5x5/2 (16) -> maxpool 3x3/2 -> 4 stages of basic blocks (2, 2, 2, 1 blocks;
    widths 32, 64, 128, 256; stride 2 in the FIRST block, standard ResNet, so the
    extra blocks run at the lower resolution). Bottleneck at H/64 as in GeoNet.

    forward: (B,in_ch,H,W) -> (bottleneck (B,256,H/64,W/64),
    skips [conv1 H/2 16ch, pool1 H/4 16ch, H/8 32ch, H/16 64ch, H/32 128ch]).
    """

    conv1_channels = 16
    stage_widths = (32, 64, 128, 256)
    stage_blocks = (2, 2, 2, 1)
    skip_channels = (16, 16, 32, 64, 128)
    out_channels = 256

    def __init__(self, in_ch: int = 3, bn_momentum: float = BN_MOMENTUM):
        super().__init__()
        # 5x5 instead of 7x7: conv1 runs at H/2 and dominates the small encoder's
        # cost for the 12-channel ResFlowNet input.
        self.conv1 = ConvBlock(in_ch, self.conv1_channels, 5, 2, bn_momentum)
        self.pool1 = nn.MaxPool2d(3, 2, padding=1)
        stages = []
        in_ch = self.conv1_channels
        for width, num_blocks in zip(self.stage_widths, self.stage_blocks):
            blocks = []
            for i in range(num_blocks):
                blocks.append(BasicBlock(in_ch, width, 2 if i == 0 else 1, bn_momentum))
                in_ch = width
            stages.append(nn.Sequential(*blocks))
        self.stages = nn.ModuleList(stages)


class UpconvDecoder(nn.Module):
    """GeoNet decoder (ResNet and VGG flavours), coarse to fine.

    Level i (i = 0 is the coarsest): up_i = upconv(x) (nearest x2 + 3x3 conv),
    nearest ``resize_like`` to the skip when sizes differ, concat
    [up_i, skip_i, upsampled previous pred], iconv_i = 3x3 conv. The last 4 levels
    each produce a prediction with ``heads`` (H/8, H/4, H/2, H); a prediction is
    upsampled x2 (nearest, or TF legacy bilinear for VGG) and fed to the next level.
    The finest level has no skip (GeoNet: concat1 = [upconv1, upred2]).

    Official levels always match sizes below H/8 for inputs that are multiples of
    8; we apply ``resize_like`` wherever sizes differ (a no-op there) so other
    sizes run instead of failing at a concat.

    Args:
        in_ch: bottleneck channels.
        skip_channels: skip channels fine-to-coarse, one per level but the finest.
        widths: upconv/iconv widths per level, coarse to fine (len = len(skips) + 1).
        make_head: ``make_head(in_ch) -> nn.Module`` mapping iconv (B,C,h,w) to the
            prediction (B,P,h,w) that is both returned and fed to the next level.
        pred_channels: P.
        pred_upsample: "nearest" (ResNet) or "bilinear_tf_legacy" (VGG).
    """

    num_preds = 4

    def __init__(
        self,
        in_ch: int,
        skip_channels: Sequence[int],
        widths: Sequence[int],
        make_head: Callable[[int], nn.Module],
        pred_channels: int,
        pred_upsample: str = "nearest",
        bn_momentum: float = BN_MOMENTUM,
    ):
        super().__init__()
        skips_coarse_to_fine = list(skip_channels)[::-1] + [0]
        if len(widths) != len(skips_coarse_to_fine):
            raise ValueError(f"need {len(skips_coarse_to_fine)} widths, got {len(widths)}")
        if pred_upsample not in ("nearest", "bilinear_tf_legacy"):
            raise ValueError(f"unknown pred_upsample {pred_upsample!r}")
        self.pred_upsample = pred_upsample
        self.num_levels = len(widths)
        first_pred_level = self.num_levels - self.num_preds
        self.upconvs = nn.ModuleList()
        self.iconvs = nn.ModuleList()
        heads = []
        prev = in_ch
        for level, (width, skip_ch) in enumerate(zip(widths, skips_coarse_to_fine)):
            fed_pred = pred_channels if level > first_pred_level else 0
            self.upconvs.append(UpConv(prev, width, bn_momentum))
            self.iconvs.append(ConvBlock(width + skip_ch + fed_pred, width, 3, 1, bn_momentum))
            if level >= first_pred_level:
                heads.append(make_head(width))
            prev = width
        # heads[s] predicts scale s (0 = full resolution): fine-to-coarse like the outputs.
        self.heads = nn.ModuleList(heads[::-1])

    def _upsample_pred(self, pred: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
        if self.pred_upsample == "nearest":
            return resize_like(upsample_nn(pred, 2), ref)
        return resize_bilinear_tf_legacy(pred, ref.shape[-2:])

    def forward(self, bottleneck: torch.Tensor, skips: Sequence[torch.Tensor]) -> list[torch.Tensor]:
        """bottleneck (B,C,h,w) + skips fine-to-coarse -> [pred scale 0 (B,P,H,W), ..., scale 3]."""
        return self.run_levels(bottleneck, skips, self.num_levels)[1][::-1]

    def run_levels(
        self, bottleneck: torch.Tensor, skips: Sequence[torch.Tensor], levels: int
    ) -> tuple[torch.Tensor, list[torch.Tensor]]:
        """The first ``levels`` levels, coarse to fine -> (the last level's features, its predictions so far,
        coarse to fine). The export's phase form (``export.phase_form``) runs the finest level its own way."""
        skips_coarse_to_fine = list(skips)[::-1]
        first_pred_level = self.num_levels - self.num_preds
        x = bottleneck
        pred = None
        preds_coarse_to_fine = []
        for level in range(levels):
            x = self.upconvs[level](x)
            parts = [x]
            if level < len(skips_coarse_to_fine):
                skip = skips_coarse_to_fine[level]
                x = resize_like(x, skip)
                parts = [x, skip]
            if pred is not None:
                parts.append(self._upsample_pred(pred, x))
            x = self.iconvs[level](torch.cat(parts, dim=1))
            if level >= first_pred_level:
                scale = self.num_levels - 1 - level
                pred = self.heads[scale](x)
                preds_coarse_to_fine.append(pred)
        return x, preds_coarse_to_fine


def init_xavier(module: nn.Module) -> None:
    """slim defaults: Xavier-uniform conv weights, zero conv biases (BN beta starts at 0)."""
    for m in module.modules():
        if isinstance(m, nn.Conv2d):
            nn.init.xavier_uniform_(m.weight)
            if m.bias is not None:
                nn.init.zeros_(m.bias)

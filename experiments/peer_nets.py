"""The depth networks users pick instead of GeoNet, rebuilt in PyTorch for timing (issue 44).

Random weights only: these modules reproduce each peer's layers, shapes and operators, so that
their ONNX graphs cost what the released models cost; they predict nothing. Written from the
papers and the authors' code (facts taken over, code our own):

* :class:`Monodepth2`: ResNet18 encoder + depth decoder (Godard et al., ICCV 2019;
  github.com/nianticlabs/monodepth2 ``networks/resnet_encoder.py``, ``networks/depth_decoder.py``).
* :class:`LiteMono`: the base Lite-Mono (Zhang et al., CVPR 2023; github.com/noahzn/Lite-Mono
  ``networks/depth_encoder.py``, ``networks/depth_decoder.py``), dilations of its 640x192 setting.
* :class:`MidasSmall`: MiDaS v2.1 small, EfficientNet-Lite3 + RefineNet-style decoder
  (github.com/isl-org/MiDaS ``midas/midas_net_custom.py``, ``midas/blocks.py``; the encoder is
  gen-efficientnet's ``tf_efficientnet_lite3``: width 1.2, depth 1.4, ReLU6, TF "same" padding).
* :class:`DepthAnythingV2Small`: DINOv2 ViT-S/14 + DPT head (Yang et al., NeurIPS 2024;
  github.com/DepthAnything/Depth-Anything-V2 ``depth_anything_v2/dpt.py``, ``dinov2.py``).

Each module takes one image tensor (1, 3, H, W) normalised as its own pipeline does
(:data:`experiments.peer_models.PEERS` says how) and returns its finest depth/disparity map.
Heads a model keeps only for training (monodepth2's and Lite-Mono's coarser disparity scales)
are built, so parameters match the released checkpoints, but not run: inference reads scale 0.
torch only (no torchvision, no timm: neither is installable here without torchvision).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from training.networks.blocks import tf_same_pads

# ----------------------------------------------------------------------------- shared pieces


def dims(x: torch.Tensor) -> tuple[int, ...]:
    """The shape as Python ints: the (static-size) ONNX graphs then hold constant pads and reshapes,
    which ONNX shape inference (the MAC count) can follow, instead of Shape -> arithmetic chains."""
    return tuple(int(s) for s in x.shape)


class ReflectConv3x3(nn.Sequential):
    """monodepth2's ``Conv3x3``: reflection pad 1, then a 3x3 convolution with bias."""

    def __init__(self, cin: int, cout: int):
        super().__init__(nn.ReflectionPad2d(1), nn.Conv2d(cin, cout, 3))


class ConvElu(nn.Sequential):
    """monodepth2's ``ConvBlock``: ``ReflectConv3x3`` + ELU."""

    def __init__(self, cin: int, cout: int):
        super().__init__(ReflectConv3x3(cin, cout), nn.ELU(inplace=True))


class SkipDecoder(nn.Module):
    """The monodepth2-style decoder both monodepth2 and Lite-Mono use: per level an up-convolution,
    2x upsampling, concatenation with the encoder feature of that size, a second convolution; a
    sigmoid disparity head per scale in ``scales`` (only scale 0 runs, see the module docstring).

    ``dec_ch``: decoder channels per level (finest first); ``enc_ch``: encoder channels (finest first).
    ``head_upsample``: Lite-Mono upsamples its scale-0 disparity 2x (its finest level is at 1/2).
    """

    def __init__(
        self, enc_ch: list[int], dec_ch: list[int], scales: range, mode: str, align: bool | None, head_upsample: bool
    ):
        super().__init__()
        self.levels = len(dec_ch)
        self.mode, self.align, self.head_upsample = mode, align, head_upsample
        self.up0, self.up1 = nn.ModuleDict(), nn.ModuleDict()
        for i in range(self.levels - 1, -1, -1):
            cin = enc_ch[-1] if i == self.levels - 1 else dec_ch[i + 1]
            self.up0[str(i)] = ConvElu(cin, dec_ch[i])
            self.up1[str(i)] = ConvElu(dec_ch[i] + (enc_ch[i - 1] if i > 0 else 0), dec_ch[i])
        self.disp = nn.ModuleDict({str(s): ReflectConv3x3(dec_ch[s], 1) for s in scales})

    def _up(self, x: torch.Tensor) -> torch.Tensor:
        return F.interpolate(x, scale_factor=2, mode=self.mode, align_corners=self.align)

    def forward(self, features: list[torch.Tensor]) -> torch.Tensor:
        x = features[-1]
        for i in range(self.levels - 1, -1, -1):
            x = [self._up(self.up0[str(i)](x))]
            if i > 0:
                x.append(features[i - 1])
            x = self.up1[str(i)](torch.cat(x, 1))
        disp = self.disp["0"](x)
        if self.head_upsample:
            disp = self._up(disp)
        return torch.sigmoid(disp)


# ----------------------------------------------------------------------------- monodepth2


class BasicBlock(nn.Module):
    """ResNet's basic block (two 3x3 convolutions, BN, identity or 1x1 projection shortcut)."""

    def __init__(self, cin: int, cout: int, stride: int):
        super().__init__()
        self.conv1 = nn.Conv2d(cin, cout, 3, stride, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(cout)
        self.conv2 = nn.Conv2d(cout, cout, 3, 1, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(cout)
        self.down = (
            nn.Sequential(nn.Conv2d(cin, cout, 1, stride, bias=False), nn.BatchNorm2d(cout))
            if stride != 1 or cin != cout
            else nn.Identity()
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = F.relu(self.bn1(self.conv1(x)))
        return F.relu(self.bn2(self.conv2(out)) + self.down(x))


class ResNet18Encoder(nn.Module):
    """ResNet18 without its classifier; five features at 1/2 (after the stem), 1/4 .. 1/32."""

    channels = [64, 64, 128, 256, 512]

    def __init__(self):
        super().__init__()
        self.conv1 = nn.Conv2d(3, 64, 7, 2, 3, bias=False)
        self.bn1 = nn.BatchNorm2d(64)
        cin, layers = 64, []
        for cout, stride in zip((64, 128, 256, 512), (1, 2, 2, 2)):
            layers.append(nn.Sequential(BasicBlock(cin, cout, stride), BasicBlock(cout, cout, 1)))
            cin = cout
        self.layers = nn.ModuleList(layers)

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        feats = [F.relu(self.bn1(self.conv1(x)))]
        x = F.max_pool2d(feats[0], 3, 2, 1)
        for layer in self.layers:
            x = layer(x)
            feats.append(x)
        return feats


class Monodepth2(nn.Module):
    """monodepth2 (ResNet18, mono 640x192): input RGB in [0, 1]; output disparity (sigmoid), 1 x H x W."""

    def __init__(self):
        super().__init__()
        self.encoder = ResNet18Encoder()
        self.decoder = SkipDecoder(
            ResNet18Encoder.channels, [16, 32, 64, 128, 256], range(4), "nearest", None, head_upsample=False
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.decoder(self.encoder((x - 0.45) / 0.225))


# ----------------------------------------------------------------------------- Lite-Mono


class ConvBnGelu(nn.Module):
    """Lite-Mono's ``Conv`` (no bias) with optional BN + GELU."""

    def __init__(self, cin: int, cout: int, stride: int, act: bool):
        super().__init__()
        self.conv = nn.Conv2d(cin, cout, 3, stride, 1, bias=False)
        self.bn = nn.BatchNorm2d(cout) if act else None

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.conv(x)
        return F.gelu(self.bn(x)) if self.bn is not None else x


class DilatedConvBlock(nn.Module):
    """Lite-Mono's CDC unit: depthwise dilated 3x3 + BN, then a pointwise MLP (x6, GELU), layer scale."""

    def __init__(self, dim: int, dilation: int, expansion: int = 6):
        super().__init__()
        self.dw = nn.Conv2d(dim, dim, 3, padding=dilation, dilation=dilation, groups=dim, bias=False)
        self.bn = nn.BatchNorm2d(dim)
        self.norm = nn.LayerNorm(dim, eps=1e-6)  # built but unused in the authors' forward: parameters only
        self.pw1 = nn.Linear(dim, expansion * dim)
        self.pw2 = nn.Linear(expansion * dim, dim)
        self.gamma = nn.Parameter(1e-6 * torch.ones(dim))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.bn(self.dw(x)).permute(0, 2, 3, 1)
        y = self.gamma * self.pw2(F.gelu(self.pw1(y)))
        return x + y.permute(0, 3, 1, 2)


class FourierPositions(nn.Module):
    """DETR-style sine/cosine positions of an H x W grid (hidden 32 per axis), 1x1-projected to ``dim``."""

    def __init__(self, dim: int, hidden: int = 32, temperature: float = 10000.0):
        super().__init__()
        self.proj = nn.Conv2d(2 * hidden, dim, 1)
        self.hidden, self.temperature = hidden, temperature

    def forward(self, h: int, w: int) -> torch.Tensor:
        device = self.proj.weight.device
        y = torch.arange(1, h + 1, dtype=torch.float32, device=device)[:, None].expand(h, w)
        x = torch.arange(1, w + 1, dtype=torch.float32, device=device)[None, :].expand(h, w)
        y = y / (h + 1e-6) * 2 * math.pi
        x = x / (w + 1e-6) * 2 * math.pi
        t = torch.arange(self.hidden, dtype=torch.float32, device=device)
        t = self.temperature ** (2 * torch.div(t, 2, rounding_mode="floor") / self.hidden)
        px, py = x[..., None] / t, y[..., None] / t
        px = torch.stack((px[..., 0::2].sin(), px[..., 1::2].cos()), dim=3).flatten(2)
        py = torch.stack((py[..., 0::2].sin(), py[..., 1::2].cos()), dim=3).flatten(2)
        return self.proj(torch.cat((py, px), dim=2).permute(2, 0, 1)[None])


class XCA(nn.Module):
    """Cross-covariance attention: attention over channels (d_h x d_h), not tokens."""

    def __init__(self, dim: int, heads: int):
        super().__init__()
        self.heads = heads
        self.temperature = nn.Parameter(torch.ones(heads, 1, 1))
        self.qkv = nn.Linear(dim, 3 * dim)
        self.proj = nn.Linear(dim, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, n, c = dims(x)
        q, k, v = self.qkv(x).reshape(b, n, 3, self.heads, c // self.heads).permute(2, 0, 3, 4, 1)
        q, k = F.normalize(q, dim=-1), F.normalize(k, dim=-1)
        attn = ((q @ k.transpose(-2, -1)) * self.temperature).softmax(dim=-1)
        return self.proj((attn @ v).permute(0, 3, 1, 2).reshape(b, n, c))


class LGFI(nn.Module):
    """Lite-Mono's local-global features interaction: XCA (+ positions in stage 1), then an MLP."""

    def __init__(self, dim: int, heads: int, positions: bool, expansion: int = 6):
        super().__init__()
        self.pos = FourierPositions(dim) if positions else None
        self.norm_xca = nn.LayerNorm(dim, eps=1e-6)
        self.gamma_xca = nn.Parameter(1e-6 * torch.ones(dim))
        self.xca = XCA(dim, heads)
        self.norm = nn.LayerNorm(dim, eps=1e-6)
        self.pw1 = nn.Linear(dim, expansion * dim)
        self.pw2 = nn.Linear(expansion * dim, dim)
        self.gamma = nn.Parameter(1e-6 * torch.ones(dim))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, c, h, w = dims(x)
        t = x.reshape(b, c, h * w).permute(0, 2, 1)
        if self.pos is not None:
            t = t + self.pos(h, w).reshape(1, c, h * w).permute(0, 2, 1)
        t = t + self.gamma_xca * self.xca(self.norm_xca(t))
        t = self.gamma * self.pw2(F.gelu(self.pw1(self.norm(t.reshape(b, h, w, c)))))
        return x + t.permute(0, 3, 1, 2)


class LiteMonoEncoder(nn.Module):
    """The base Lite-Mono encoder: dims 48/80/128, depths 4/4/10, one LGFI at the end of each stage."""

    dims = [48, 80, 128]
    depths = [4, 4, 10]
    dilations = [[1, 2, 3], [1, 2, 3], [1, 2, 3, 1, 2, 3, 2, 4, 6]]  # the 640x192 setting
    heads = 8

    def __init__(self):
        super().__init__()
        d = self.dims
        self.stem1 = nn.Sequential(ConvBnGelu(3, d[0], 2, True), ConvBnGelu(d[0], d[0], 1, True))
        self.stem1.append(ConvBnGelu(d[0], d[0], 1, True))
        self.stem2 = ConvBnGelu(d[0] + 3, d[0], 2, False)
        self.down = nn.ModuleList(ConvBnGelu(d[i] * 2 + 3, d[i + 1], 2, False) for i in range(2))
        self.stages = nn.ModuleList()
        for i in range(3):
            blocks = [DilatedConvBlock(d[i], self.dilations[i][j]) for j in range(self.depths[i] - 1)]
            blocks.append(LGFI(d[i], self.heads, positions=i == 0))
            self.stages.append(nn.Sequential(*blocks))

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        x = (x - 0.45) / 0.225
        pooled = [x]
        for _ in range(3):  # the input at 1/2, 1/4, 1/8 (avg-pool 3x3, stride 2, pad 1, repeated)
            pooled.append(F.avg_pool2d(pooled[-1], 3, 2, 1))
        x = self.stem2(torch.cat((self.stem1(x), pooled[1]), 1))
        feats = [self.stages[0](x)]
        stage_in = x
        for i in range(1, 3):  # each stage reads the last one's input and output beside the pooled image
            stage_in = self.down[i - 1](torch.cat((stage_in, feats[-1], pooled[i + 1]), 1))
            feats.append(self.stages[i](stage_in))
        return feats


class LiteMono(nn.Module):
    """Lite-Mono (base, 640x192): input RGB in [0, 1]; output disparity (sigmoid), 1 x H x W."""

    def __init__(self):
        super().__init__()
        self.encoder = LiteMonoEncoder()
        enc = LiteMonoEncoder.dims
        self.decoder = SkipDecoder(enc, [c // 2 for c in enc], range(3), "bilinear", False, head_upsample=True)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.decoder(self.encoder(x))


# ----------------------------------------------------------------------------- MiDaS v2.1 small


def _round_channels(c: float, divisor: int = 8) -> int:
    """EfficientNet's channel rounding (nearest multiple of 8, never below 90 %)."""
    new = max(divisor, int(c + divisor / 2) // divisor * divisor)
    return new + divisor if new < 0.9 * c else new


class SameConv(nn.Conv2d):
    """A (grouped) convolution with TensorFlow "same" padding, as tf_* weights need
    (``training``'s :func:`tf_same_pads`; its ``Conv2dSame`` has no groups)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        pads = tf_same_pads(*dims(x)[-2:], self.kernel_size[0], self.stride[0])
        return super().forward(F.pad(x, pads) if any(pads) else x)


def _conv_bn(cin: int, cout: int, k: int, stride: int = 1, groups: int = 1, act: bool = True) -> nn.Sequential:
    layers = [SameConv(cin, cout, k, stride, groups=groups, bias=False), nn.BatchNorm2d(cout, eps=1e-3)]
    return nn.Sequential(*layers, nn.ReLU6()) if act else nn.Sequential(*layers)


class InvertedResidual(nn.Module):
    """MBConv without squeeze-excite (EfficientNet-Lite): 1x1 expand, kxk depthwise, 1x1 project."""

    def __init__(self, cin: int, cout: int, k: int, stride: int, expansion: int):
        super().__init__()
        mid = cin * expansion
        layers = [_conv_bn(cin, mid, 1)] if expansion != 1 else []
        layers += [_conv_bn(mid, mid, k, stride, groups=mid), _conv_bn(mid, cout, 1, act=False)]
        self.body = nn.Sequential(*layers)
        self.residual = stride == 1 and cin == cout

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.body(x) if self.residual else self.body(x)


class EfficientNetLite3(nn.Module):
    """gen-efficientnet's ``tf_efficientnet_lite3`` up to its last block (no head): width 1.2,
    depth 1.4 (first and last stage not deepened), stem fixed at 32 channels. MiDaS reads four
    features: after block stages 1, 2, 4 and 6 (1/4, 1/8, 1/16, 1/32)."""

    # (expansion, kernel, stride, channels, repeats) of EfficientNet-B0
    ARCH = [(1, 3, 1, 16, 1), (6, 3, 2, 24, 2), (6, 5, 2, 40, 2), (6, 3, 2, 80, 3), (6, 5, 1, 112, 3)]
    ARCH += [(6, 5, 2, 192, 4), (6, 3, 1, 320, 1)]
    WIDTH, DEPTH = 1.2, 1.4
    TAPS = (1, 2, 4, 6)  # stages whose output MiDaS takes

    def __init__(self):
        super().__init__()
        self.stem = _conv_bn(3, 32, 3, 2)
        cin, stages = 32, []
        for i, (e, k, s, c, r) in enumerate(self.ARCH):
            cout = _round_channels(c * self.WIDTH)
            reps = r if i in (0, len(self.ARCH) - 1) else math.ceil(r * self.DEPTH)
            blocks = []
            for j in range(reps):
                blocks.append(InvertedResidual(cin, cout, k, s if j == 0 else 1, e))
                cin = cout
            stages.append(nn.Sequential(*blocks))
        self.stages = nn.ModuleList(stages)
        self.channels = [_round_channels(self.ARCH[i][3] * self.WIDTH) for i in self.TAPS]

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        x, feats = self.stem(x), []
        for i, stage in enumerate(self.stages):
            x = stage(x)
            if i in self.TAPS:
                feats.append(x)
        return feats


class ResidualConvUnit(nn.Module):
    """RefineNet/DPT residual unit: ReLU, 3x3, ReLU, 3x3 (biases, no BN), plus the input."""

    def __init__(self, ch: int):
        super().__init__()
        self.conv1 = nn.Conv2d(ch, ch, 3, padding=1)
        self.conv2 = nn.Conv2d(ch, ch, 3, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.conv2(F.relu(self.conv1(F.relu(x))))


class FusionBlock(nn.Module):
    """MiDaS/DPT feature fusion: (+ residual unit of the skip), residual unit, bilinear 2x (or to
    ``size``, align_corners=True), 1x1 output convolution (halving channels when ``expand``).
    The deepest block has no skip but keeps its first unit (released checkpoints carry it)."""

    def __init__(self, ch: int, expand: bool):
        super().__init__()
        self.unit1, self.unit2 = ResidualConvUnit(ch), ResidualConvUnit(ch)
        self.out = nn.Conv2d(ch, ch // 2 if expand else ch, 1)

    def forward(self, x: torch.Tensor, skip: torch.Tensor | None = None, size=None) -> torch.Tensor:
        if skip is not None:
            x = x + self.unit1(skip)
        x = self.unit2(x)
        if size is None:
            x = F.interpolate(x, scale_factor=2, mode="bilinear", align_corners=True)
        else:
            x = F.interpolate(x, size=size, mode="bilinear", align_corners=True)
        return self.out(x)


class MidasSmall(nn.Module):
    """MiDaS v2.1 small (256x256): input ImageNet-normalised RGB; output inverse depth (ReLU), H x W."""

    def __init__(self, features: int = 64):
        super().__init__()
        self.encoder = EfficientNetLite3()
        widths = [features, features * 2, features * 4, features * 8]  # blocks={'expand': True}
        self.rn = nn.ModuleList(
            nn.Conv2d(c, w, 3, padding=1, bias=False) for c, w in zip(self.encoder.channels, widths)
        )
        self.fuse = nn.ModuleList(FusionBlock(w, expand=i > 0) for i, w in enumerate(widths))
        self.head = nn.Sequential(
            nn.Conv2d(features, features // 2, 3, padding=1),
            nn.Upsample(scale_factor=2, mode="bilinear", align_corners=False),
            nn.Conv2d(features // 2, 32, 3, padding=1),
            nn.ReLU(),
            nn.Conv2d(32, 1, 1),
            nn.ReLU(),
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        l1, l2, l3, l4 = (rn(f) for rn, f in zip(self.rn, self.encoder(x)))
        path = self.fuse[3](l4)
        path = self.fuse[2](path, l3)
        path = self.fuse[1](path, l2)
        path = self.fuse[0](path, l1)
        return self.head(path)[:, 0]


# ----------------------------------------------------------------------------- Depth-Anything-V2 Small


class ViTBlock(nn.Module):
    """A pre-norm transformer block with DINOv2's layer scale."""

    def __init__(self, dim: int, heads: int, mlp_ratio: int = 4):
        super().__init__()
        self.heads = heads
        self.norm1 = nn.LayerNorm(dim, eps=1e-6)
        self.qkv = nn.Linear(dim, 3 * dim)
        self.proj = nn.Linear(dim, dim)
        self.ls1 = nn.Parameter(torch.ones(dim))
        self.norm2 = nn.LayerNorm(dim, eps=1e-6)
        self.fc1 = nn.Linear(dim, mlp_ratio * dim)
        self.fc2 = nn.Linear(mlp_ratio * dim, dim)
        self.ls2 = nn.Parameter(torch.ones(dim))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, n, c = dims(x)
        q, k, v = self.qkv(self.norm1(x)).reshape(b, n, 3, self.heads, c // self.heads).permute(2, 0, 3, 1, 4)
        attn = ((q * (c // self.heads) ** -0.5) @ k.transpose(-2, -1)).softmax(dim=-1)
        x = x + self.ls1 * self.proj((attn @ v).transpose(1, 2).reshape(b, n, c))
        return x + self.ls2 * self.fc2(F.gelu(self.fc1(self.norm2(x))))


class DinoV2Small(nn.Module):
    """DINOv2 ViT-S/14 as Depth-Anything-V2 builds it: 518x518 position table (37x37 + class token),
    bicubically resized for other grids; returns the normed patch tokens of blocks 2, 5, 8, 11."""

    dim, depth, heads, patch, grid = 384, 12, 6, 14, 37
    taps = (2, 5, 8, 11)

    def __init__(self):
        super().__init__()
        self.patch_embed = nn.Conv2d(3, self.dim, self.patch, self.patch)
        self.cls_token = nn.Parameter(torch.zeros(1, 1, self.dim))
        self.pos_embed = nn.Parameter(0.02 * torch.randn(1, self.grid * self.grid + 1, self.dim))
        self.mask_token = nn.Parameter(torch.zeros(1, self.dim))  # training only; in the checkpoint
        self.blocks = nn.ModuleList(ViTBlock(self.dim, self.heads) for _ in range(self.depth))
        self.norm = nn.LayerNorm(self.dim, eps=1e-6)

    def positions(self, gh: int, gw: int) -> torch.Tensor:
        if (gh, gw) == (self.grid, self.grid):
            return self.pos_embed
        table = self.pos_embed[:, 1:].reshape(1, self.grid, self.grid, self.dim).permute(0, 3, 1, 2)
        table = F.interpolate(table, size=(gh, gw), mode="bicubic", align_corners=False)
        return torch.cat((self.pos_embed[:, :1], table.permute(0, 2, 3, 1).reshape(1, gh * gw, self.dim)), 1)

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        gh, gw = (s // self.patch for s in dims(x)[-2:])
        t = self.patch_embed(x).flatten(2).transpose(1, 2)
        t = torch.cat((self.cls_token.expand(t.shape[0], -1, -1), t), 1) + self.positions(gh, gw)
        out = []
        for i, block in enumerate(self.blocks):
            t = block(t)
            if i in self.taps:
                out.append(self.norm(t)[:, 1:])
        return out


class DepthAnythingV2Small(nn.Module):
    """Depth-Anything-V2 Small (518x518): input ImageNet-normalised RGB (sides multiples of 14);
    output relative inverse depth (ReLU), H x W. DPT head: features 64, projections 48/96/192/384."""

    def __init__(self, features: int = 64, widths: tuple[int, ...] = (48, 96, 192, 384)):
        super().__init__()
        self.backbone = DinoV2Small()
        dim = DinoV2Small.dim
        self.project = nn.ModuleList(nn.Conv2d(dim, w, 1) for w in widths)
        self.resize = nn.ModuleList(
            [
                nn.ConvTranspose2d(widths[0], widths[0], 4, 4),
                nn.ConvTranspose2d(widths[1], widths[1], 2, 2),
                nn.Identity(),
                nn.Conv2d(widths[3], widths[3], 3, 2, 1),
            ]
        )
        self.rn = nn.ModuleList(nn.Conv2d(w, features, 3, padding=1, bias=False) for w in widths)
        self.fuse = nn.ModuleList(FusionBlock(features, expand=False) for _ in widths)
        self.head1 = nn.Conv2d(features, features // 2, 3, padding=1)
        self.head2 = nn.Sequential(
            nn.Conv2d(features // 2, 32, 3, padding=1), nn.ReLU(), nn.Conv2d(32, 1, 1), nn.ReLU()
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        gh, gw = (s // DinoV2Small.patch for s in dims(x)[-2:])
        layers = []
        for tokens, project, resize, rn in zip(self.backbone(x), self.project, self.resize, self.rn):
            grid = tokens.permute(0, 2, 1).reshape(tokens.shape[0], tokens.shape[-1], gh, gw)
            layers.append(rn(resize(project(grid))))
        l1, l2, l3, l4 = layers
        path = self.fuse[3](l4, size=dims(l3)[2:])
        path = self.fuse[2](path, l3, size=dims(l2)[2:])
        path = self.fuse[1](path, l2, size=dims(l1)[2:])
        path = self.fuse[0](path, l1)
        out = F.interpolate(
            self.head1(path), (gh * DinoV2Small.patch, gw * DinoV2Small.patch), mode="bilinear", align_corners=True
        )
        return F.relu(self.head2(out))[:, 0]


# ----------------------------------------------------------------------------- weights


@torch.no_grad()
def randomize(module: nn.Module, seed: int = 0) -> nn.Module:
    """Random weights shaped like trained ones, in place: matrices keep PyTorch's initialisation,
    vectors (norm scales, layer scales, biases, BN statistics) get distinct values of order one.

    Constructor defaults would make many vectors identical (all-ones norm scales, 1e-6 layer scales):
    onnxruntime then shares them as one initializer, which its x64 INT8 precision option
    (the runtime's sessions) fails to load, and 1e-6 scales push activations towards denormals,
    which would time unlike a trained model.
    """
    gen = torch.Generator().manual_seed(seed)
    for name, tensor in [*module.named_parameters(), *module.named_buffers()]:
        if tensor.dim() > 1 or not tensor.is_floating_point():
            continue
        rand = torch.rand(tensor.shape, generator=gen)
        if name.endswith("bias") or name.endswith("running_mean"):
            tensor.copy_(0.2 * rand - 0.1)
        else:  # scales, gammas, temperatures, running_var: in [0.5, 1.5]
            tensor.copy_(rand + 0.5)
    for name, tensor in module.named_parameters():
        if tensor.dim() > 1 and not name.endswith("weight"):  # token and position tables
            tensor.copy_(0.02 * torch.randn(tensor.shape, generator=gen))
    return module

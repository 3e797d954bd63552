"""Parameter and conv-MAC table of every GeoNet network and variant.

    python -m training.summary [--height 128 --width 416]

MACs count nn.Conv2d layers only (forward hooks): out_elems * in_ch / groups * kh * kw
per conv, batch 1. Elementwise ops (BN, ReLU, sigmoid, adds), pooling, resizes,
concats and the spatial mean are NOT counted (same rule as
cpu_latency_anchors.md). BN contributes its beta to the parameter count, which
equals the conv bias of a BN-folded (deploy) model.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

import torch
import torch.nn as nn

from geonet_infer.conventions import REFERENCE_HEIGHT, REFERENCE_WIDTH
from training.networks import DepthNet, PoseNet, ResFlowNet


def count_params_and_macs(model: nn.Module, input_shape: Sequence[int]) -> tuple[int, int]:
    """(trainable parameters, conv MACs) of ``model`` for one forward of zeros(input_shape).

    MACs include the batch dimension of input_shape (use batch 1 for per-image MACs).
    Runs in eval mode under no_grad and restores the previous mode, so BN running
    statistics are left untouched.
    """
    params = sum(p.numel() for p in model.parameters() if p.requires_grad)
    macs = 0

    def hook(conv: nn.Conv2d, inputs, output):
        nonlocal macs
        kh, kw = conv.kernel_size
        macs += output.numel() * (conv.in_channels // conv.groups) * kh * kw

    handles = [m.register_forward_hook(hook) for m in model.modules() if isinstance(m, nn.Conv2d)]
    was_training = model.training
    try:
        model.eval()
        with torch.no_grad():
            model(torch.zeros(*input_shape))
    finally:
        model.train(was_training)
        for h in handles:
            h.remove()
    return params, macs


def network_table(height: int, width: int) -> list[tuple[str, str, tuple[int, ...], int, int]]:
    """Rows (network, variant, input shape, params, macs) at batch 1."""
    entries = [
        ("DepthNet", "resnet50", lambda: DepthNet("resnet50"), 3),
        ("DepthNet", "vgg", lambda: DepthNet("vgg"), 3),
        ("DepthNet", "small", lambda: DepthNet("small"), 3),
        ("PoseNet", "standard (seq 3)", lambda: PoseNet(2, "standard"), 9),
        ("PoseNet", "small (seq 3)", lambda: PoseNet(2, "small"), 9),
        ("PoseNet", "standard (seq 5)", lambda: PoseNet(4, "standard"), 15),
        ("PoseNet", "small (seq 5)", lambda: PoseNet(4, "small"), 15),
        ("ResFlowNet", "resnet50", lambda: ResFlowNet("resnet50"), 12),
        ("ResFlowNet", "small", lambda: ResFlowNet("small"), 12),
    ]
    rows = []
    for name, variant, build, channels in entries:
        shape = (1, channels, height, width)
        params, macs = count_params_and_macs(build(), shape)
        rows.append((name, variant, shape, params, macs))
    return rows


def main(argv: Sequence[str] | None = None) -> int:
    """Exit codes: 0 table printed, 2 bad size (one line naming it)."""
    parser = argparse.ArgumentParser(prog="python -m training.summary", description=__doc__.splitlines()[0])
    parser.add_argument("--height", type=int, default=REFERENCE_HEIGHT)
    parser.add_argument("--width", type=int, default=REFERENCE_WIDTH)
    args = parser.parse_args(argv)
    if min(args.height, args.width) < 1:
        print(f"error: --height/--width {args.height}x{args.width}: need positive sizes", file=sys.stderr)
        return 2
    rows = network_table(args.height, args.width)
    print("| network | variant | input (B,C,H,W) | params (M) | conv GMACs |")
    print("|---|---|---|---|---|")
    for name, variant, shape, params, macs in rows:
        print(f"| {name} | {variant} | {'x'.join(map(str, shape))} | {params / 1e6:.3f} | {macs / 1e9:.3f} |")
    print(
        "conv MACs only (out_elems * in_ch/groups * kh * kw); elementwise, pooling, "
        "resize and mean ops are not counted."
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())

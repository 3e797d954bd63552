"""experiments/resflow_scale1.py: the scale-1 flow at full resolution is the net's own scale-1 flow in pixels
(ResFlowNet.forward's second output) upsampled x2 and doubled: checked against that output, not the new code."""

from __future__ import annotations

import torch
import torch.nn.functional as F

from experiments.resflow_scale1 import ScaleOneFlow
from training.networks.resflownet import ResFlowNet


def test_the_scale_one_flow_is_the_nets_own_scale_one_flow_upsampled():
    torch.manual_seed(5)
    net = ResFlowNet("small", in_channels=12).eval()
    x = torch.rand(1, 12, 64, 96) * 2 - 1
    with torch.no_grad():
        half = net(x)[1]  # (1, 2, 32, 48) px of the half-resolution grid
        expected = 2 * F.interpolate(half, size=(64, 96), mode="bilinear", align_corners=False)
        (got,) = ScaleOneFlow(net)(x)
    assert got.shape == (1, 2, 64, 96)
    torch.testing.assert_close(got, expected, rtol=1e-5, atol=1e-5)

"""export.wrappers.fold_direct_input: a direct ResFlowNet's exported graph reads 7 input channels, the same
function as the trained net on its 12. The golden value is the trained net on training's own 12-channel
input (training.model.direct_flownet_input), never the folded code."""

from __future__ import annotations

import torch

from export.wrappers import FLOW_INPUT_CHANNELS, ResFlowExport, fold_direct_input
from training.model import direct_flownet_input
from training.networks.resflownet import ResFlowNet


def test_the_folded_direct_net_gives_the_trained_flow():
    torch.manual_seed(4)
    net = ResFlowNet("small").eval()
    for module in net.modules():
        if isinstance(module, torch.nn.BatchNorm2d):
            module.running_mean.uniform_(-0.5, 0.5)
            module.running_var.uniform_(0.5, 2.0)
    flow_input = torch.rand(2, FLOW_INPUT_CHANNELS, 64, 96) * 2 - 1
    target, source = flow_input[:, 0:3], flow_input[:, 3:6]
    with torch.no_grad():
        expected = net(direct_flownet_input(target, source, 0.85))[0]
        residual, flow = ResFlowExport(net, direct_alpha=0.85).eval()(flow_input)
    torch.testing.assert_close(flow, expected, rtol=1e-5, atol=1e-4)
    torch.testing.assert_close(residual, flow - flow_input[:, 9:11])
    assert fold_direct_input(net).encoder.conv1.conv.weight.shape[1] == 7
    assert net.encoder.conv1.conv.weight.shape[1] == 12  # the trained net is left as it was

"""export/phase_form.py: the half-resolution form of DepthNet's finest level is the same function.
Each golden value is the full-resolution computation itself (torch's own conv, nearest upsampling and pixel
(un)shuffle), never the phase form's code."""

from __future__ import annotations

import torch
import torch.nn.functional as F

from export import phase_form as phase
from training.networks.blocks import upsample_nn
from training.networks.depthnet import DepthNet


def test_a_conv_of_the_upsampled_input_is_a_conv_of_the_input_to_four_phases():
    g = torch.Generator().manual_seed(0)
    weight, x = torch.randn(3, 2, 3, 3, generator=g), torch.randn(1, 2, 5, 7, generator=g)
    full = F.conv2d(upsample_nn(x, 2), weight, padding=1)  # (1, 3, 10, 14)
    phased = F.pixel_shuffle(F.conv2d(x, phase.upsampled_conv_to_phases(weight), padding=1), 2)
    torch.testing.assert_close(phased, full, rtol=1e-5, atol=1e-5)


def test_a_full_resolution_conv_is_a_conv_between_phases():
    g = torch.Generator().manual_seed(1)
    weight, z = torch.randn(2, 3, 3, 3, generator=g), torch.randn(1, 3, 10, 14, generator=g)
    full = F.conv2d(z, weight, padding=1)
    phased = F.pixel_shuffle(F.conv2d(F.pixel_unshuffle(z, 2), phase.full_res_conv_to_phases(weight), padding=1), 2)
    torch.testing.assert_close(phased, full, rtol=1e-5, atol=1e-5)
    # a 3x3 tap reaches only the neighbouring block: 9 of each output phase's 36 taps per channel
    assert int((phase.full_res_conv_to_phases(torch.ones(1, 1, 3, 3)) != 0).sum()) == 4 * 9


def test_the_phase_form_depthnet_gives_the_same_disparity_as_the_trained_layout():
    torch.manual_seed(2)
    net = DepthNet("small").eval()
    for module in net.modules():  # trained-like batch-norm statistics, so the folding is exercised
        if isinstance(module, torch.nn.BatchNorm2d):
            module.running_mean.uniform_(-0.5, 0.5)
            module.running_var.uniform_(0.5, 2.0)
            module.bias.data.uniform_(-0.2, 0.2)
    image = torch.rand(2, 3, 64, 96) * 2 - 1
    with torch.no_grad():
        expected, got = net(image)[0], phase.PhaseDepthNet(net).eval()(image)[0]
    assert got.shape == expected.shape == (2, 1, 64, 96)
    torch.testing.assert_close(got, expected, rtol=1e-5, atol=1e-5)


def test_the_export_writes_the_small_depthnet_in_phase_form_and_the_others_as_trained():
    from export.wrappers import build_wrapper
    from training.model import GeoNet

    torch.manual_seed(3)
    small = GeoNet("small").eval()
    wrapper = build_wrapper("depthnet", small)
    assert isinstance(wrapper.depth_net, phase.PhaseDepthNet)
    image = torch.rand(1, 3, 64, 96) * 2 - 1
    with torch.no_grad():
        disparity, depth = wrapper(image)
        torch.testing.assert_close(disparity, small.depth_net(image)[0], rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(depth, 1 / disparity)
    for arch in ("resnet50", "vgg"):  # not measured (resnet50) or bilinear feedback (vgg): the trained layout
        net = DepthNet(arch)
        assert phase.export_depth_net(net) is net

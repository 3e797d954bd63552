"""DepthNet / PoseNet / ResFlowNet: shapes, official sizes, heads, BN, padding.

Parameter and MAC anchors come from an INDEPENDENT implementation
(../shared/reference/cpu_latency_anchors.md, "Networks" table; BN folded into
conv + bias there, which counts the same as conv + BN beta here).
"""

from __future__ import annotations

import functools

import pytest
import torch
import torch.nn as nn
import torch.nn.functional as F

from geonet_infer.conventions import DISP_HEADS, FLOW_SCALING, POSE
from training.networks import (
    BN_EPS,
    BatchNormNoScale,
    DepthNet,
    PoseNet,
    ResFlowNet,
    build_network,
)
from training.networks.blocks import (
    Conv2dSame,
    resize_bilinear_tf_legacy,
    tf_same_pads,
)
from training.summary import count_params_and_macs, network_table

# (kind, arch) -> (constructor, input channels). PoseNet here is seq 3 (2 sources).
NETS = {
    ("depth", "resnet50"): (lambda: DepthNet("resnet50"), 3),
    ("depth", "vgg"): (lambda: DepthNet("vgg"), 3),
    ("depth", "small"): (lambda: DepthNet("small"), 3),
    ("pose", "standard"): (lambda: PoseNet(2, "standard"), 9),
    ("pose", "small"): (lambda: PoseNet(2, "small"), 9),
    ("flow", "resnet50"): (lambda: ResFlowNet("resnet50"), 12),
    ("flow", "small"): (lambda: ResFlowNet("small"), 12),
}


@functools.cache
def cached_net(kind: str, arch: str) -> nn.Module:
    """One shared instance per net for read-only tests (building resnet50 takes ~0.5 s)."""
    torch.manual_seed(0)
    return NETS[(kind, arch)][0]().eval()


def run(net: nn.Module, x: torch.Tensor):
    with torch.no_grad():
        return net(x)


# ----------------------------------------------------------------------------- shapes


@pytest.mark.parametrize("height,width", [(128, 416), (64, 208)])
@pytest.mark.parametrize("kind,arch", list(NETS))
def test_output_shapes(kind, arch, height, width):
    net = cached_net(kind, arch)
    channels = NETS[(kind, arch)][1]
    out = run(net, torch.randn(2, channels, height, width))
    if kind == "pose":
        assert out.shape == (2, 2, 6)
        return
    assert isinstance(out, list) and len(out) == 4
    pred_ch = 1 if kind == "depth" else 2
    for s, pred in enumerate(out):
        assert pred.shape == (2, pred_ch, height // 2**s, width // 2**s), f"scale {s}"


@pytest.mark.parametrize(
    "kind,arch,height,width",
    [(kind, arch, 72, 232) for kind, arch in NETS if kind != "pose"]
    + [("depth", "small", 256, 832), ("flow", "small", 256, 832)],
)
def test_scale0_is_input_size_for_multiples_of_8(kind, arch, height, width):
    # 72 x 232: odd sizes from H/16 down, so every resize_like path runs.
    # 256 x 832 only for the small nets, to keep the suite short on 2 cores.
    net = cached_net(kind, arch)
    out = run(net, torch.randn(1, NETS[(kind, arch)][1], height, width))
    assert [tuple(p.shape[-2:]) for p in out] == [(height // 2**s, width // 2**s) for s in range(4)]


def test_posenet_seq5_and_direct_flow_shapes():
    pose = PoseNet(4, "small").eval()
    assert run(pose, torch.randn(2, 15, 64, 208)).shape == (2, 4, 6)
    flow = ResFlowNet("small", in_channels=6).eval()
    assert [p.shape for p in run(flow, torch.randn(2, 6, 64, 208))] == [
        (2, 2, 64 // 2**s, 208 // 2**s) for s in range(4)
    ]


def test_build_network_and_bad_arch():
    assert isinstance(build_network("pose", "small", num_source=2), PoseNet)
    with pytest.raises(ValueError):
        DepthNet("resnet18")
    with pytest.raises(ValueError):
        build_network("flow", "vgg")


# ----------------------------------------------------------------------------- sizes

# name: (kind, arch, input channels, params (M), conv GMACs at 1x128x416)
ANCHORS = {
    "depthnet_resnet50": ("depth", "resnet50", 3, 58.449, 9.154),
    "depthnet_vgg": ("depth", "vgg", 3, 31.597, 4.719),
    "posenet": ("pose", "standard", 9, 1.591, 0.193),
    "resflownet": ("flow", "resnet50", 12, 58.480, 9.558),
}


@pytest.mark.parametrize("name", list(ANCHORS))
def test_params_and_macs_match_independent_anchors(name):
    kind, arch, channels, params_m, gmacs = ANCHORS[name]
    params, macs = count_params_and_macs(cached_net(kind, arch), (1, channels, 128, 416))
    assert params / 1e6 == pytest.approx(params_m, rel=1e-3)
    assert macs / 1e9 == pytest.approx(gmacs, rel=1e-2)


@pytest.mark.parametrize("kind,max_params_m,max_gmacs", [("depth", 2.5, 0.5), ("flow", 2.5, 0.5), ("pose", 0.3, 0.2)])
def test_small_variants_within_budget(kind, max_params_m, max_gmacs):
    channels = NETS[(kind, "small")][1]
    params, macs = count_params_and_macs(cached_net(kind, "small"), (1, channels, 128, 416))
    assert params / 1e6 <= max_params_m
    assert macs / 1e9 <= max_gmacs


def test_count_params_and_macs_hand_computed_and_restores_mode():
    net = nn.Sequential(
        nn.Conv2d(3, 4, 3, 2, 1, bias=True), BatchNormNoScale(4), nn.Conv2d(4, 8, 1, groups=2, bias=False)
    )
    net.train()
    params, macs = count_params_and_macs(net, (1, 3, 10, 12))
    assert params == 3 * 4 * 9 + 4 + 4 + 8 * 2
    # conv1 out 4x5x6, 27 MACs each; grouped 1x1: out 8x5x6, 2 MACs each.
    assert macs == 4 * 5 * 6 * 27 + 8 * 5 * 6 * 2
    assert net.training and int(net[1].num_batches_tracked) == 0


def test_summary_table_lists_every_variant():
    rows = network_table(64, 208)
    assert {(name, variant.split(" ")[0]) for name, variant, *_ in rows} == {
        ("DepthNet", "resnet50"),
        ("DepthNet", "vgg"),
        ("DepthNet", "small"),
        ("PoseNet", "standard"),
        ("PoseNet", "small"),
        ("ResFlowNet", "resnet50"),
        ("ResFlowNet", "small"),
    }
    assert {shape[1] for name, _, shape, *_ in rows if name == "PoseNet"} == {9, 15}


# ----------------------------------------------------------------------------- heads


@pytest.mark.parametrize("arch", ["resnet50", "vgg", "small"])
def test_disparity_range_and_head_constants(arch):
    head = DISP_HEADS[arch]
    torch.manual_seed(0)
    net = DepthNet(arch).eval()
    for disp in run(net, 3 * torch.randn(1, 3, 64, 208)):
        assert disp.min() >= head.offset and disp.max() <= head.scale + head.offset
    # Saturate the sigmoid through the head bias: the ends of the range are exact.
    for bias, expected in ((50.0, head.scale + head.offset), (-50.0, head.offset)):
        for h in net.decoder.heads:
            nn.init.zeros_(h.conv.weight)
            nn.init.constant_(h.conv.bias, bias)
        for disp in run(net, torch.randn(1, 3, 64, 208)):
            torch.testing.assert_close(disp, torch.full_like(disp, expected))


def test_posenet_output_scale_and_layout():
    torch.manual_seed(0)
    net = PoseNet(2, "standard").train()
    pose = net(torch.rand(4, 9, 128, 416) * 2 - 1)
    # x0.01 at init: poses are small (rotations << 0.1 rad); without it ~0.1-1.
    assert pose.abs().max() < 0.05
    # Head bias b (12 values) -> pose[n, k] = 0.01 * b[6 n + k].
    nn.init.zeros_(net.pose_pred.weight)
    bias = torch.arange(12, dtype=torch.float32)
    with torch.no_grad():
        net.pose_pred.bias.copy_(bias)
    pose = run(net.eval(), torch.randn(2, 9, 64, 208))
    torch.testing.assert_close(pose, POSE.output_scale * bias.view(1, 2, 6).expand(2, 2, 6))


def test_resflownet_returns_pixels_and_feeds_normalised_flow():
    torch.manual_seed(0)
    net = ResFlowNet("small").eval()
    height, width = 64, 208  # W != H and W/H not a power of 2: a swapped x/y fails
    biases = [
        torch.tensor([0.5, -0.25]),
        torch.tensor([1.0, 2.0]),
        torch.tensor([-1.5, 0.75]),
        torch.tensor([0.3, 0.6]),
    ]
    for s, head in enumerate(net.decoder.heads):
        nn.init.zeros_(head.conv.weight)
        with torch.no_grad():
            head.conv.bias.copy_(biases[s])
    fed = {}
    # The finest 3 iconvs take the upsampled coarser prediction as their last 2 channels.
    levels = net.decoder.num_levels
    for scale in range(3):
        iconv = net.decoder.iconvs[levels - 1 - scale].conv

        def grab(module, inputs, scale=scale):
            fed[scale] = inputs[0][:, -2:]

        iconv.register_forward_pre_hook(grab)
    flows = run(net, torch.randn(2, 12, height, width))
    for s, flow in enumerate(flows):
        h_s, w_s = height // 2**s, width // 2**s
        expected = FLOW_SCALING * biases[s] * torch.tensor([w_s, h_s])
        torch.testing.assert_close(flow, expected.view(1, 2, 1, 1).expand(2, 2, h_s, w_s))
    for scale in range(3):  # fed from scale + 1: normalised, not pixels
        expected = FLOW_SCALING * biases[scale + 1]
        torch.testing.assert_close(fed[scale], expected.view(1, 2, 1, 1).expand_as(fed[scale]))


# ----------------------------------------------------------------------------- BN / init


@pytest.mark.parametrize("kind,arch", list(NETS))
def test_batchnorm_settings_no_gamma(kind, arch):
    net = cached_net(kind, arch)
    bns = [m for m in net.modules() if isinstance(m, nn.modules.batchnorm._BatchNorm)]
    assert bns and all(type(m) is BatchNormNoScale for m in bns)
    for m in bns:
        assert m.eps == BN_EPS == 1e-3 and m.momentum == 1e-3
        assert m.weight is None and m.bias is not None and m.bias.requires_grad
        assert [n for n, _ in m.named_parameters()] == ["bias"]
    # Every conv before a BN has no bias; every remaining conv (the heads) has one.
    convs = [m for m in net.modules() if isinstance(m, nn.Conv2d)]
    assert sum(c.bias is None for c in convs) == len(bns)
    assert sum(c.bias is not None for c in convs) == (1 if kind == "pose" else 4)


def test_bn_momentum_is_passed_down():
    for net in (
        DepthNet("small", bn_momentum=0.01),
        PoseNet(2, "small", bn_momentum=0.01),
        ResFlowNet("small", bn_momentum=0.01),
    ):
        assert {m.momentum for m in net.modules() if isinstance(m, BatchNormNoScale)} == {0.01}


def test_batchnorm_noscale_matches_torch_bn_with_unit_gamma():
    torch.manual_seed(0)
    ours = BatchNormNoScale(5, momentum=0.1)
    ref = nn.BatchNorm2d(5, eps=1e-3, momentum=0.1)
    with torch.no_grad():
        ours.bias.copy_(torch.randn(5))
        ref.bias.copy_(ours.bias)
    x = torch.randn(3, 5, 4, 6) * 2 + 1
    torch.testing.assert_close(ours(x), ref(x))  # train mode: batch statistics
    torch.testing.assert_close(ours.running_mean, ref.running_mean)
    torch.testing.assert_close(ours.running_var, ref.running_var)
    ours.eval(), ref.eval()
    torch.testing.assert_close(ours(x), ref(x))  # eval mode: running statistics


def test_train_forward_updates_stats_and_eval_differs():
    torch.manual_seed(0)
    net = DepthNet("small").train()
    x = torch.randn(2, 3, 64, 208)
    bn = net.encoder.conv1.bn
    with torch.no_grad():
        train_out = net(x)
    assert bn.running_mean.abs().sum() > 0 and int(bn.num_batches_tracked) == 1
    stats = bn.running_mean.clone()
    net.eval()
    eval_out = run(net, x)
    torch.testing.assert_close(bn.running_mean, stats)  # eval does not update
    assert not torch.allclose(train_out[0], eval_out[0], atol=1e-4)


def test_xavier_init_and_zero_biases():
    net = cached_net("depth", "resnet50")
    for m in net.modules():
        if isinstance(m, nn.Conv2d):
            fan_in = m.in_channels * m.kernel_size[0] * m.kernel_size[1]
            fan_out = m.out_channels * m.kernel_size[0] * m.kernel_size[1]
            bound = (6.0 / (fan_in + fan_out)) ** 0.5
            assert m.weight.abs().max() <= bound
            if m.bias is not None:
                assert torch.count_nonzero(m.bias) == 0
    for m in net.modules():
        if isinstance(m, BatchNormNoScale):
            assert torch.count_nonzero(m.bias) == 0


# ----------------------------------------------------------------------------- padding / resize


def test_tf_same_pads():
    # (left, right, top, bottom); TF puts the odd pixel after (bottom/right).
    assert tf_same_pads(128, 416, 7, 2) == (2, 3, 2, 3)
    assert tf_same_pads(128, 416, 3, 2) == (0, 1, 0, 1)
    assert tf_same_pads(13, 7, 3, 2) == (1, 1, 1, 1)  # odd sizes: symmetric
    assert tf_same_pads(32, 104, 5, 1) == (2, 2, 2, 2)


def test_conv2d_same_stride2_is_shifted_symmetric_conv():
    # TF 'SAME' k3 s2 on an even size centres output i on input 2i + 1, whereas a
    # symmetric pad-1 conv centres it on 2i: shift the input by one pixel to compare.
    torch.manual_seed(0)
    same = Conv2dSame(2, 3, 3, 2)
    x = torch.randn(1, 2, 8, 10)
    # So SAME stride 2 = the odd positions of a symmetric (pad 1) stride-1 conv.
    expected = F.conv2d(x, same.weight, same.bias, stride=1, padding=1)[:, :, 1::2, 1::2]
    torch.testing.assert_close(same(x), expected)
    # ... and differs from PyTorch's symmetric stride-2 conv (the even positions).
    symmetric = F.conv2d(x, same.weight, same.bias, stride=2, padding=1)
    assert not torch.allclose(same(x), symmetric)
    assert same(torch.randn(1, 2, 7, 9)).shape == (1, 3, 4, 5)


def test_resize_bilinear_tf_legacy_values():
    # TF1 resize_bilinear, align_corners=False, legacy: src = dst * in / out, clamped.
    x = torch.tensor([0.0, 1.0, 2.0, 3.0]).view(1, 1, 1, 4)
    out = resize_bilinear_tf_legacy(x, (1, 8))
    torch.testing.assert_close(out.flatten(), torch.tensor([0, 0.5, 1, 1.5, 2, 2.5, 3, 3]))
    x = torch.tensor([0.0, 10.0, 20.0]).view(1, 1, 3, 1)
    out = resize_bilinear_tf_legacy(x, (5, 1))
    torch.testing.assert_close(out.flatten(), torch.tensor([0.0, 6.0, 12.0, 18.0, 20.0]))
    # Separable 2-D: a bilinear ramp a*u + b*v stays a ramp on the source coordinates.
    v, u = torch.meshgrid(torch.arange(3.0), torch.arange(4.0), indexing="ij")
    out = resize_bilinear_tf_legacy((2 * u + 3 * v).view(1, 1, 3, 4), (6, 8))
    v2, u2 = torch.meshgrid(torch.arange(6.0) / 2, torch.arange(8.0) / 2, indexing="ij")
    expected = 2 * u2.clamp(max=3) + 3 * v2.clamp(max=2)
    torch.testing.assert_close(out[0, 0], expected)


def test_motion_gate_multiplies_the_trunks_poses_and_a_closed_gate_stops_the_camera():
    """PoseNet(gate="soft") (round 19): its poses are the trunk's times the gate's probability, one per
    snippet; an ungated PoseNet has no gate weights, so the weights of every earlier model still load."""
    from training.networks import PoseNet

    torch.manual_seed(0)
    gated = PoseNet(2, arch="small", gate="soft").eval()
    plain = PoseNet(2, arch="small").eval()
    assert not any(k.startswith("gate.") for k in plain.state_dict())
    plain.load_state_dict({k: v for k, v in gated.state_dict().items() if not k.startswith("gate.")})
    x = torch.rand(3, 9, 64, 192) * 2 - 1
    with torch.no_grad():
        probability = torch.sigmoid(gated.gate.logits(x))
        torch.testing.assert_close(gated(x), plain(x) * probability[:, None, None])
        assert 0.9 < float(probability.min())  # a new gate starts open: the trunk's poses nearly unchanged
        gated.gate.logit.bias.fill_(-60.0)  # closed: every pose is the identity
        assert float(gated(x).abs().max()) < 1e-20


def test_a_hard_motion_gate_is_a_step_at_one_half_outside_training():
    """gate="hard" (round 20): in eval mode the gate is 1 where its logit is positive and 0 elsewhere, so a
    moving snippet's poses are exactly the trunk's; in training mode it is the sigmoid, as a soft gate."""
    from training.networks import PoseNet

    torch.manual_seed(1)
    net = PoseNet(2, arch="small", gate="hard")
    x = torch.rand(4, 9, 64, 192) * 2 - 1
    with torch.no_grad():
        net.gate.logit.bias.copy_(-net.gate.logits(x)[1:3].mean() + net.gate.logit.bias)  # logits on both sides of 0
        logits = net.gate.logits(x)
        assert (logits > 0).any() and (logits < 0).any()
        net.eval()
        assert net.gate(x).flatten().tolist() == (logits > 0).float().tolist()
        net.gate.train()
        torch.testing.assert_close(net.gate(x).flatten(), torch.sigmoid(logits))
    with pytest.raises(ValueError, match="gate"):
        PoseNet(2, arch="small", gate="on")


@pytest.mark.parametrize("width", [16, 8])
def test_a_motion_gates_parameters_follow_its_width(width):
    """--gate-width W (round 22): five 3x3 convs of W, 2W, 2W, 4W, 4W channels over the 9 input channels, each
    with a bias, and one linear unit: counted here by hand."""
    from training.networks import PoseNet

    widths = [9, width, 2 * width, 2 * width, 4 * width, 4 * width]
    by_hand = sum(a * b * 9 + b for a, b in zip(widths, widths[1:])) + 4 * width + 1
    gate = PoseNet(2, arch="small", gate="soft", gate_width=width).gate
    assert sum(p.numel() for p in gate.parameters()) == by_hand
    assert by_hand == {16: 70_689, 8: 18_065}[width]

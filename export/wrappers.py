"""Export modules: one ``nn.Module`` per ONNX graph, with the graph's fixed I/O names.

Every graph takes images ALREADY NORMALISED to the network range
(``conventions.IMAGE_NORM``: x / 255 * 2 - 1); the runtime normalises in numpy.
One rule for all graphs, so the rigid-flow op's zero-padded warp sees exactly
the values it saw in training.

=================  ===========================================  ==========================================
graph              inputs                                        outputs
=================  ===========================================  ==========================================
depthnet.onnx      image (B,3,H,W)                               disparity (B,1,H,W), depth (B,1,H,W)
posenet.onnx       snippet (B,3L,H,W) [target, sources]          pose (B,L-1,6), pose_matrix (B,L-1,4,4)
rigidflow.onnx     depth (B,1,H,W), pose (B,6), intrinsics       rigid_flow (B,2,H,W), warped (B,3,H,W),
                   (B,3,3), target (B,3,H,W), source (B,3,H,W)   error (B,1,H,W)
resflownet.onnx    flow_input (B,12,H,W)                         residual_flow (B,2,H,W), flow (B,2,H,W)
=================  ===========================================  ==========================================

The wrappers only re-use training code (``training.model.rigid_warp``,
``training.geometry``), so the exported math is the trained math.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import torch
import torch.nn as nn

from export.phase_form import export_depth_net
from geonet_infer.conventions import IMAGE_NORM, kitti_like_K
from geonet_infer.core.snippets import resflow_channels
from training.geometry import l2_norm, pose_vec_to_mat
from training.losses import LossWeights
from training.model import (
    DIRECT_FLOW_PARTS,
    GeoNet,
    direct_flownet_input,
    normalize_disparity_scale,
    rigid_warp,
)

GRAPH_NAMES = ("depthnet", "posenet", "rigidflow", "resflownet")
RIGID_GRAPHS = ("depthnet", "posenet", "rigidflow")  # what a stage 'rigid' checkpoint can export
# ResFlowNet's input channels, laid out once by geonet_infer.core.snippets.RESFLOW_INPUT
_PARTS = {name: slice(r.start, r.stop) for name, r in resflow_channels().items()}
FLOW_INPUT_CHANNELS = max(part.stop for part in _PARTS.values())  # 12
RIGID_FLOW_CHANNELS = _PARTS["rigid_flow"]  # channels of flownet_input holding the rigid flow (px): 9, 10


@dataclass(frozen=True)
class IOSpec:
    """Names, shapes ("B" = dynamic batch) and dtypes of one graph's inputs and outputs."""

    inputs: tuple[tuple[str, tuple], ...]
    outputs: tuple[tuple[str, tuple], ...]
    dtype: str = "float32"


def io_spec(graph: str, height: int, width: int, seq_length: int) -> IOSpec:
    """The fixed I/O contract of ``graph`` at H x W (what the manifest records)."""
    H, W, N = height, width, seq_length - 1
    if graph == "depthnet":
        return IOSpec(
            inputs=(("image", ("B", 3, H, W)),), outputs=(("disparity", ("B", 1, H, W)), ("depth", ("B", 1, H, W)))
        )
    if graph == "posenet":
        return IOSpec(
            inputs=(("snippet", ("B", 3 * seq_length, H, W)),),
            outputs=(("pose", ("B", N, 6)), ("pose_matrix", ("B", N, 4, 4))),
        )
    if graph == "rigidflow":
        return IOSpec(
            inputs=(
                ("depth", ("B", 1, H, W)),
                ("pose", ("B", 6)),
                ("intrinsics", ("B", 3, 3)),
                ("target", ("B", 3, H, W)),
                ("source", ("B", 3, H, W)),
            ),
            outputs=(("rigid_flow", ("B", 2, H, W)), ("warped", ("B", 3, H, W)), ("error", ("B", 1, H, W))),
        )
    if graph == "resflownet":
        return IOSpec(
            inputs=(("flow_input", ("B", FLOW_INPUT_CHANNELS, H, W)),),
            outputs=(("residual_flow", ("B", 2, H, W)), ("flow", ("B", 2, H, W))),
        )
    raise ValueError(f"unknown graph {graph!r}; expected one of {GRAPH_NAMES}")


class DepthExport(nn.Module):
    """image (B,3,H,W) normalised -> disparity, depth = 1 / disparity (B,1,H,W), scale 0.

    The ``scale * sigmoid + 0.01`` head is part of DepthNet, so it is in the graph. A model
    trained with ``--scale-normalize`` saw each disparity map divided by its mean; the graph does
    the same, so its depth has the scale the pose (and the rigid flow) was trained with.
    """

    def __init__(self, depth_net: nn.Module, scale_normalize: bool = False):
        super().__init__()
        self.depth_net = depth_net
        self.scale_normalize = scale_normalize

    def forward(self, image: torch.Tensor):
        disparity = self.depth_net(image)[0]
        if self.scale_normalize:
            disparity = normalize_disparity_scale(disparity)
        return disparity, 1.0 / disparity


class PoseExport(nn.Module):
    """snippet (B,3L,H,W) [target, sources in temporal order] -> pose (B,L-1,6), pose_matrix (B,L-1,4,4).

    ``pose`` is [tx, ty, tz, rx, ry, rz] (the x0.01 is inside PoseNet);
    ``pose_matrix`` maps target-camera points to source-camera points.
    """

    def __init__(self, pose_net: nn.Module, num_source: int):
        super().__init__()
        self.pose_net = pose_net
        self.num_source = num_source

    def forward(self, snippet: torch.Tensor):
        pose = self.pose_net(snippet)
        matrix = pose_vec_to_mat(pose.reshape(-1, 6)).reshape(-1, self.num_source, 4, 4)
        return pose, matrix


class RigidFlowExport(nn.Module):
    """The rigid-flow op of training (``training.model.rigid_warp``) as a graph.

    depth (B,1,H,W) of the target, pose (B,6) target -> source, intrinsics (B,3,3)
    at H x W, target and source (B,3,H,W) normalised ->
    rigid_flow (B,2,H,W) px, warped (B,3,H,W) = source warped onto the target
    (network range, zero padding), error (B,1,H,W) = l2_norm(photometric error),
    i.e. the 12th ResFlowNet input channel. K^-1 is closed-form (no Inverse op).
    ``alpha`` weighs DSSIM against L1 in that error; it is baked into the graph, so the
    manifest records it (``conventions.photometric_alpha``, :func:`photometric_alpha`).

    ``dynamic_spatial``: traced with symbolic H, W (``export.to_onnx``), so the pixel
    grid is computed in the graph from the input shapes instead of being folded
    into H x W constants (0.64 MB of a 0.66 MB file at 128x416); the file still
    declares the fixed H x W.
    """

    dynamic_spatial = True

    def __init__(self, alpha: float = LossWeights.alpha_recon):
        super().__init__()
        self.alpha = alpha

    def forward(self, depth, pose, intrinsics, target, source):
        T = pose_vec_to_mat(pose)
        flow, warped, error = rigid_warp(depth, T, intrinsics, target, source, self.alpha)
        return flow, warped, l2_norm(error)


class ResFlowExport(nn.Module):
    """flow_input (B,12,H,W) (``training.model.flownet_input`` order) ->
    residual_flow (B,2,H,W) px and flow = residual + rigid flow (channels 9:11), scale 0.

    ``direct_alpha`` (a ``direct_flow`` model, its photometric α): the net reads the frames alone
    (``training.model.direct_flownet_input`` of channels 0:3 and 3:6, folded: :func:`fold_direct_input`) and
    its output is the flow; the residual returned is that flow minus the rigid flow given, so the interface
    is unchanged."""

    def __init__(self, flow_net: nn.Module, direct_alpha: float | None = None):
        super().__init__()
        self.flow_net = flow_net if direct_alpha is None else fold_direct_input(flow_net)
        self.direct_alpha = direct_alpha

    def forward(self, flow_input: torch.Tensor):
        if self.direct_alpha is not None:
            target, source = flow_input[:, _PARTS["target"]], flow_input[:, _PARTS["source"]]
            frames = direct_flownet_input(target, source, self.direct_alpha, folded=True)
            flow = self.flow_net(frames)[0]
            return flow - flow_input[:, RIGID_FLOW_CHANNELS], flow
        residual = self.flow_net(flow_input)[0]  # the graph's ops in the order the shipped templates have
        return residual, residual + flow_input[:, RIGID_FLOW_CHANNELS]


def fold_direct_input(flow_net: nn.Module) -> nn.Module:
    """A copy of a direct ResFlowNet whose first convolution reads only ``training.model.DIRECT_FLOW_PARTS``
    (target, source, error: 7 channels, ``direct_flownet_input(..., folded=True)``) instead of all 12.

    In a direct net's input the warped frame is the source frame itself and the rigid flow is zero, so the
    warped frame's weights add to the source's and the rigid flow's drop out: the same function (up to float
    summation order), 5 input channels fewer in the first convolution, which INT8 keeps FP32."""
    folded = copy.deepcopy(flow_net)
    conv = folded.encoder.conv1.conv
    weight = conv.weight.detach()
    by_part = {name: weight[:, _PARTS[name]] for name in DIRECT_FLOW_PARTS}
    by_part["source"] = by_part["source"] + weight[:, _PARTS["warped"]]
    conv.weight = nn.Parameter(torch.cat([by_part[name] for name in DIRECT_FLOW_PARTS], dim=1))
    conv.in_channels = conv.weight.shape[1]
    return folded


def photometric_alpha(model: GeoNet) -> float:
    """The α of ``α·DSSIM + (1−α)·L1`` that ``rigidflow.onnx`` of ``model`` computes: the one it trained with."""
    return model.weights.alpha_recon


def build_wrapper(graph: str, model: GeoNet) -> nn.Module:
    """The export module of ``graph`` around ``model``'s (eval-mode) networks."""
    if graph == "depthnet":
        wrapper = DepthExport(export_depth_net(model.depth_net), model.scale_normalize)
    elif graph == "posenet":
        wrapper = PoseExport(model.pose_net, model.num_source)
    elif graph == "rigidflow":
        wrapper = RigidFlowExport(photometric_alpha(model))
    elif graph == "resflownet":
        if model.flow_net is None:
            raise ValueError("this GeoNet has no ResFlowNet (stage 'rigid')")
        wrapper = ResFlowExport(model.flow_net, photometric_alpha(model) if model.direct_flow else None)
    else:
        raise ValueError(f"unknown graph {graph!r}; expected one of {GRAPH_NAMES}")
    return wrapper.eval()


def example_inputs(
    graph: str, height: int, width: int, seq_length: int, batch: int = 1, generator: torch.Generator | None = None
) -> tuple[torch.Tensor, ...]:
    """Plausible example inputs (the export trace and smoke checks use them).

    Images are uniform in [-1, 1]; depth in [1, 50]; small poses; a KITTI-like K.
    """
    g = generator if generator is not None else torch.Generator().manual_seed(0)
    spec = io_spec(graph, height, width, seq_length)
    shapes = {name: (batch,) + tuple(shape[1:]) for name, shape in spec.inputs}
    if graph == "rigidflow":
        depth = 1.0 + 49.0 * torch.rand(shapes["depth"], generator=g)
        pose = 0.02 * (torch.rand(shapes["pose"], generator=g) - 0.5)
        K = torch.tensor(kitti_like_K(height, width), dtype=torch.float32).repeat(batch, 1, 1)
        images = [IMAGE_NORM.apply(torch.rand(shapes[n], generator=g)) for n in ("target", "source")]
        return (depth, pose, K, *images)
    # Trace examples only: any values in [-1, 1] serve (resflownet mixes images and flow).
    return tuple(torch.rand(shapes[name], generator=g) * 2 - 1 for name, _ in spec.inputs)

"""GeoNet as a whole: the three nets wired together, and the two stages' losses.

Batch layout follows the official code so every loss is a mean over the same
elements: ``N`` sources are stacked along the batch i-major (source i occupies
rows ``[i*B, (i+1)*B)``), and the target is tiled ``N`` times to match.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass, field

import torch
import torch.nn as nn
import torch.nn.functional as F

from geonet_infer.conventions import IMAGE_NORM, NUM_SCALES
from geonet_infer.core.cascade import RESFLOW_INPUT
from training.geometry import (
    flow_consistency,
    flow_warp,
    in_view_mask,
    intrinsics_at_scale,
    invert_intrinsics,
    invert_rigid,
    l2_norm,
    pose_vec_to_mat,
    rigid_flow,
)
from training.losses import (
    LossWeights,
    SpeedUnit,
    batch_reference_step,
    edge_aware_smoothness,
    flow_endpoint_error,
    gate_error,
    has_true_pose,
    masked_mean,
    motion_labels,
    overlap_step_error,
    path_lengths,
    photometric_error,
    pose_keep_error,
    scale_aligned_pose_error,
    scale_invariant_log_error,
    speed_error,
    steady_speed_error,
    stride_ratio_error,
)
from training.networks import DepthNet, PoseNet, ResFlowNet
from training.networks.posenet import GATE_WIDTH

RIGID_ZEROED = 0.25  # share of a --rigid-corruption batch whose rigid flow is zeroed


def image_pyramid(image: torch.Tensor, num_scales: int = NUM_SCALES) -> list[torch.Tensor]:
    """Area-downsampled copies (official ``resize_area``; floor sizes).

    Args:
        image: (B, C, H, W).
    Returns:
        list of (B, C, H // 2**s, W // 2**s), s = 0..num_scales-1.
    """
    _, _, H, W = image.shape
    return [image] + [F.interpolate(image, size=(H // 2**s, W // 2**s), mode="area") for s in range(1, num_scales)]


def rigid_warp(
    depth: torch.Tensor,
    T: torch.Tensor,
    K: torch.Tensor,
    frame_from: torch.Tensor,
    frame_to: torch.Tensor,
    alpha: float = LossWeights.alpha_recon,
):
    """Rigid flow of ``frame_from``, ``frame_to`` warped onto it, and the photometric error.

    This is the op exported as ``rigidflow.onnx``.

    Args:
        depth: (B, 1, H, W) depth of ``frame_from``.
        T: (B, 4, 4) transform from ``frame_from``'s camera to ``frame_to``'s.
        K: (B, 3, 3) intrinsics at H x W.
        frame_from, frame_to: (B, 3, H, W) network-range images.
    Returns:
        flow (B, 2, H, W) pixels, warped (B, 3, H, W), error (B, 3, H, W).
    """
    flow = rigid_flow(depth, T, K, invert_intrinsics(K))
    warped = flow_warp(frame_to, flow)
    return flow, warped, photometric_error(warped, frame_from, alpha)


def normalize_disparity_scale(disp: torch.Tensor) -> torch.Tensor:
    """Official ``--scale_normalize``: (B, 1, H, W) disparity divided by its own spatial mean.

    Used in training and by the exported DepthNet graph, so depth keeps the scale pose learned.
    """
    return disp / disp.mean(dim=(1, 2, 3), keepdim=True)


def flownet_input(frame_from, frame_to, warped, flow, error, parts=None) -> torch.Tensor:
    """The 12 ResFlowNet channels, in the official order, which the runtime reads from the same
    :data:`geonet_infer.core.cascade.RESFLOW_INPUT`.

    ``[I_from (3), I_to (3), I_to rigidly warped to I_from (3), rigid flow (2),
    L2 norm of the rigid photometric error (1)]`` -> (B, 12, H, W). ``parts``: only these parts, in this
    order (:data:`DIRECT_FLOW_PARTS`); a part left out may be given as None.
    """
    by_name = {"target": frame_from, "source": frame_to, "warped": warped, "rigid_flow": flow, "error": l2_norm(error)}
    return torch.cat([by_name[name] for name in parts or [name for name, _ in RESFLOW_INPUT]], dim=1)


def network_rows(target: torch.Tensor, sources: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """[0, 1] frames -> network range: target (B, 3, H, W), sources (B, N, 3, H, W), and the sources as rows
    (N*B, 3, H, W), source-major (source i at rows ``[i*B, (i+1)*B)``, the order of every per-source tensor)."""
    target_n, sources_n = IMAGE_NORM.apply(target), IMAGE_NORM.apply(sources)
    B, N = sources.shape[:2]
    return target_n, sources_n, sources_n.transpose(0, 1).reshape(N * B, *sources_n.shape[2:])


# The parts of a direct ResFlowNet's input that carry information: its "warped" frame is "source" and its
# "rigid_flow" is zero (direct_flownet_input), so the export folds them away (export.wrappers.fold_direct_input).
DIRECT_FLOW_PARTS = ("target", "source", "error")


def direct_flownet_input(frame_from, frame_to, alpha: float, folded: bool = False) -> torch.Tensor:
    """:func:`flownet_input` for a camera at rest (zero rigid flow): ``frame_to`` itself as the warped frame and
    the photometric error of the frames as they are; what a ``direct_flow`` ResFlowNet reads, in training and
    in its exported graph. (B, 3, H, W) network-range frames -> (B, 12, H, W); ``folded``: only the
    :data:`DIRECT_FLOW_PARTS`, in that order (B, 7, H, W), what the exported graph's folded net reads."""
    error = photometric_error(frame_to, frame_from, alpha)
    if folded:
        return flownet_input(frame_from, frame_to, None, None, error, parts=DIRECT_FLOW_PARTS)
    return flownet_input(frame_from, frame_to, frame_to, torch.zeros_like(frame_from[:, :2]), error)


@dataclass
class RigidOutputs:
    """Per-scale tensors of the rigid stage (lists indexed by scale)."""

    disp: list  # (B*(1+N), 1, H_s, W_s): target rows first, then sources i-major
    poses: torch.Tensor  # (B, N, 6)
    fwd_flow: list  # (N*B, 2, H_s, W_s) target -> source i
    bwd_flow: list  # (N*B, 2, H_s, W_s) source i -> target
    fwd_warp: list  # sources warped to the target
    bwd_warp: list  # target warped to each source
    fwd_error: list  # (N*B, 3, H_s, W_s)
    bwd_error: list
    extra_poses: torch.Tensor | None = None  # (B_extra, N, 6): PoseNet on rigid_forward's extra_pose_input


@dataclass
class StageLoss:
    total: torch.Tensor
    terms: dict = field(default_factory=dict)  # name -> float, for logging


def _as_floats(**terms) -> dict:
    return {name: float(torch.as_tensor(value).detach()) for name, value in terms.items()}


class GeoNet(nn.Module):
    """DepthNet + PoseNet (+ ResFlowNet in stage ``flow``).

    Inputs to every method are [0, 1] images; normalisation happens here once.
    """

    def __init__(
        self,
        arch: str = "resnet50",
        num_source: int = 2,
        with_flow: bool = False,
        bn_momentum: float = 1e-3,
        weights: LossWeights | None = None,
        mask_out_of_view: bool = False,
        automask: bool = False,
        scale_normalize: bool = False,
        rigid_corruption: float = 1.0,
        hard_gate: bool = False,
        direct_flow: bool = False,
        gate_width: int = GATE_WIDTH,
    ):
        super().__init__()
        self.arch = arch
        self.num_source = num_source
        # Sources are in temporal order around the target: [t-1, t+1] or [t-2, t-1, t+1, t+2].
        self.next_source = num_source // 2  # index of frame t+1, the ground-truth flow's frame
        self.weights = weights if weights is not None else LossWeights()
        # Deviation (off by default = official): drop pixels whose rigid flow leaves the source
        # frame from the rigid photometric loss. Without it, zero-padded samples at the image
        # border reward far depth there (forward motion pushes border pixels out of view).
        self.mask_out_of_view = mask_out_of_view
        # Deviation (off by default): monodepth2's auto-mask. A pixel whose unwarped source already
        # matches the target better than the rigid warp does (an object moving with the camera,
        # flat sky) is left out, so such objects do not teach infinite depth.
        self.automask = automask
        # Official --scale_normalize (its released model_sn, not in the paper): every disparity
        # map is divided by its own spatial mean before depth, warping and smoothness use it.
        self.scale_normalize = scale_normalize
        self.depth_net = DepthNet(arch, bn_momentum=bn_momentum)
        pose_arch = "small" if arch == "small" else "standard"
        gate = ("hard" if hard_gate else "soft") if self.weights.pose_gate > 0 else None
        self.pose_net = PoseNet(num_source, arch=pose_arch, bn_momentum=bn_momentum, gate=gate, gate_width=gate_width)
        # Deviation (1 = off): in stage flow's training the poses behind the rigid flow ResFlowNet sees are
        # scaled per snippet (:meth:`corrupted_pose_factors`), so it learns to correct a wrong rigid flow.
        self.rigid_corruption = rigid_corruption
        # Deviation (off = official): ResFlowNet predicts the whole flow from the two frames, its rigid channels
        # fed as for a camera at rest (:func:`direct_flownet_input`): GeoNet's DirFlowNet ablation (paper
        # Table 4) in ResFlowNet's interface. The exported graph subtracts the rigid flow it is given, so the
        # runtime's flow = rigid + residual is this flow.
        self.direct_flow = direct_flow
        flow_arch = "small" if arch == "small" else "resnet50"
        self.flow_net = ResFlowNet(flow_arch, bn_momentum=bn_momentum) if with_flow else None
        self.speed_unit = SpeedUnit()  # a plain attribute: not in the state dict, re-learnt on resume
        self.start_pose_net: PoseNet | None = None  # set by keep_pose_of; never in the state dict

    def keep_pose_of(self, pose_net: PoseNet) -> None:
        """Hold a frozen copy of ``pose_net`` for ``weights.pose_keep`` (bypassing nn.Module's registration,
        so checkpoints and exports never see it)."""
        start = copy.deepcopy(pose_net).eval().requires_grad_(False)
        object.__setattr__(self, "start_pose_net", start)

    # ----------------------------------------------------------------- rigid
    def rigid_forward(
        self,
        target: torch.Tensor,
        sources: torch.Tensor,
        K: torch.Tensor,
        extra_target: torch.Tensor | None = None,
        extra_sources: torch.Tensor | None = None,
        pose_factors: torch.Tensor | None = None,
    ) -> tuple[RigidOutputs, list, list]:
        """Depth of every frame, poses, and rigid warps at every scale.

        Args:
            target: (B, 3, H, W) in [0, 1].
            sources: (B, N, 3, H, W) in [0, 1], temporal order.
            K: (B, 3, 3) intrinsics at H x W.
            extra_target, extra_sources: (B_extra, 3, H, W) and (B_extra, N, 3, H, W) in [0, 1], more
                snippets for PoseNet alone, run in the same call as the batch's so that in training they
                share its batch-norm statistics (a separate call of a row or two would normalise them
                otherwise and feed the running statistics); their poses come back as ``extra_poses``.
            pose_factors: (B, 1, 1) multiplying each snippet's pose vectors before the rigid warps (the
                poses returned are PoseNet's), or None.
        Returns:
            (outputs, target pyramid tiled N times, source pyramid), images network-range.
        """
        B, N = sources.shape[:2]
        target_n, sources_n, source_rows = network_rows(target, sources)
        disp = self.depth_net(torch.cat([target_n, source_rows], dim=0))
        if self.scale_normalize:
            disp = [normalize_disparity_scale(d) for d in disp]
        pose_target, pose_sources = target_n, sources_n
        if extra_target is not None:  # appended rows: one call, one set of batch statistics
            pose_target = torch.cat([target_n, IMAGE_NORM.apply(extra_target)])
            pose_sources = torch.cat([sources_n, IMAGE_NORM.apply(extra_sources)])
        poses = self.pose_net(torch.cat([pose_target, pose_sources.flatten(1, 2)], dim=1))
        poses, extra_poses = poses[:B], (poses[B:] if extra_target is not None else None)
        warp_poses = poses if pose_factors is None else poses * pose_factors

        T_fwd = pose_vec_to_mat(warp_poses.transpose(0, 1).reshape(N * B, 6))
        T_bwd = invert_rigid(T_fwd)
        K_rows = K.repeat(N, 1, 1)
        target_pyr = image_pyramid(target_n.repeat(N, 1, 1, 1))
        source_pyr = image_pyramid(source_rows)
        out = RigidOutputs(disp, poses, [], [], [], [], [], [], extra_poses)
        for s in range(NUM_SCALES):
            depth_s = 1.0 / disp[s]
            K_s = intrinsics_at_scale(K_rows, s)
            flow, warp, err = rigid_warp(
                depth_s[:B].repeat(N, 1, 1, 1), T_fwd, K_s, target_pyr[s], source_pyr[s], self.weights.alpha_recon
            )
            out.fwd_flow.append(flow), out.fwd_warp.append(warp), out.fwd_error.append(err)
            flow, warp, err = rigid_warp(
                depth_s[B:], T_bwd, K_s, source_pyr[s], target_pyr[s], self.weights.alpha_recon
            )
            out.bwd_flow.append(flow), out.bwd_warp.append(warp), out.bwd_error.append(err)
        return out, target_pyr, source_pyr

    def rigid_loss(
        self,
        target,
        sources,
        K,
        depth_gt: torch.Tensor | None = None,
        pose_gt: torch.Tensor | None = None,
        twin_target: torch.Tensor | None = None,
        twin_sources: torch.Tensor | None = None,
        has_twin: torch.Tensor | None = None,
        next_target: torch.Tensor | None = None,
        next_sources: torch.Tensor | None = None,
        has_next: torch.Tensor | None = None,
    ) -> StageLoss:
        """Stage 1: rigid warping + disparity smoothness, summed over scales.

        With ``weights.depth_supervision`` > 0 and ``depth_gt`` (B, 1, H, W) metres (0 = none;
        synthetic scenes), the target's depth at every scale, upsampled to H x W, also pays the
        scale-invariant log error against it (a deviation from GeoNet, for pre-training).
        With ``weights.pose_supervision`` > 0 and ``pose_gt`` (B, N, 4, 4) true motion target ->
        sources (zeros = none), PoseNet also pays the scale-aligned pose error against it, and with
        ``weights.pose_speed`` > 0 the speed error under the run's unit (:func:`speed_error`), a still
        snippet then measured against the run's mean moving step (:class:`SpeedUnit`). With
        ``weights.pose_keep`` (or ``pose_keep_shape``) > 0 and :meth:`keep_pose_of` called, the snippets
        without true poses pay :func:`pose_keep_error` (scale-free) against the starting PoseNet. With
        ``weights.pose_steady`` > 0 every snippet pays :func:`steady_speed_error`. With
        ``weights.pose_stride`` > 0 and the twins of ``SequenceDataset(load_twins=True)``
        (``twin_target`` (B, 3, H, W), ``twin_sources`` (B, N, 3, H, W), ``has_twin`` (B,) bool), each
        ``stride2`` copy pays :func:`stride_ratio_error` against its normal snippet. With
        ``weights.pose_overlap`` > 0 and the next snippets of ``SequenceDataset(load_next=True)``
        (``next_target``, ``next_sources``, ``has_next``, shaped as the twins), each snippet that has one
        pays :func:`overlap_step_error` against it. Twins and next snippets go through PoseNet in the
        batch's own call (one set of batch-norm statistics, as at inference).
        """
        w = self.weights
        twin_rows = next_rows = None
        extra_targets, extra_sources = [], []
        if w.pose_stride > 0 and has_twin is not None and bool(has_twin.any()):
            twin_rows = has_twin.nonzero().squeeze(1)
            extra_targets.append(twin_target[twin_rows]), extra_sources.append(twin_sources[twin_rows])
        if w.pose_overlap > 0 and has_next is not None and bool(has_next.any()):
            next_rows = has_next.nonzero().squeeze(1)
            extra_targets.append(next_target[next_rows]), extra_sources.append(next_sources[next_rows])
        if extra_targets:
            out, target_pyr, source_pyr = self.rigid_forward(
                target, sources, K, extra_target=torch.cat(extra_targets), extra_sources=torch.cat(extra_sources)
            )
        else:
            out, target_pyr, source_pyr = self.rigid_forward(target, sources, K)
        extra_T = None
        if out.extra_poses is not None:
            extra_T = pose_vec_to_mat(out.extra_poses.flatten(0, 1)).view(*out.extra_poses.shape[:2], 4, 4)
        N = self.num_source
        B = target.shape[0]
        rigid_warp_loss = disp_smooth_loss = 0.0
        for s in range(NUM_SCALES):
            # Symmetric in its two images, so one map serves both directions.
            identity_error = photometric_error(source_pyr[s], target_pyr[s], w.alpha_recon) if self.automask else None
            rigid_warp_loss = rigid_warp_loss + w.rigid_warp * N / 2 * (
                self._photometric_mean(out.fwd_error[s], out.fwd_flow[s], identity_error)
                + self._photometric_mean(out.bwd_error[s], out.bwd_flow[s], identity_error)
            )
            images_s = torch.cat([target_pyr[s][:B], source_pyr[s]], dim=0)
            disp_smooth_loss = disp_smooth_loss + w.disp_smooth / 2**s * edge_aware_smoothness(out.disp[s], images_s)
        total = rigid_warp_loss + disp_smooth_loss
        terms = {"rigid_warp": rigid_warp_loss, "disp_smooth": disp_smooth_loss}
        if w.depth_supervision > 0 and depth_gt is not None:
            size = depth_gt.shape[-2:]
            depth_loss = sum(
                scale_invariant_log_error(
                    1.0 / F.interpolate(out.disp[s][:B], size=size, mode="bilinear", align_corners=False), depth_gt
                )
                for s in range(NUM_SCALES)
            )
            terms["depth_supervised"] = w.depth_supervision * depth_loss
            total = total + terms["depth_supervised"]
        supervise_pose = w.pose_supervision > 0 and pose_gt is not None
        keep_pose = w.keeps_pose and self.start_pose_net is not None
        pairs_poses = twin_rows is not None or next_rows is not None
        if supervise_pose or keep_pose or w.pose_steady > 0 or pairs_poses:  # the motions (B, N, 4, 4), once
            T = pose_vec_to_mat(out.poses.flatten(0, 1)).view(*out.poses.shape[:2], 4, 4)
        if supervise_pose:
            still_ref_step = None
            if w.pose_speed > 0:
                paths = path_lengths(T, pose_gt)
                unit, moving_path = self.speed_unit.update(*paths)
                terms["pose_speed"] = w.pose_speed * speed_error(*paths, unit.to(T.device))
                still_ref_step = None if moving_path is None else moving_path.to(T.device) / N
            pose_error = scale_aligned_pose_error(T, pose_gt, still_ref_step=still_ref_step)
            terms["pose_supervised"] = w.pose_supervision * pose_error
            total = total + terms["pose_supervised"] + terms.get("pose_speed", 0.0)
        if keep_pose:
            with torch.no_grad():
                pose_input = torch.cat([IMAGE_NORM.apply(target), IMAGE_NORM.apply(sources).flatten(1, 2)], dim=1)
                start = self.start_pose_net(pose_input)
            T_start = pose_vec_to_mat(start.flatten(0, 1)).view(*start.shape[:2], 4, 4)
            no_truth = torch.ones(B, dtype=T.dtype, device=T.device)
            if pose_gt is not None:
                no_truth = 1.0 - has_true_pose(pose_gt).to(T.dtype)
            if w.pose_keep > 0:
                terms["pose_keep"] = w.pose_keep * pose_keep_error(T, T_start, no_truth)
            if w.pose_keep_shape > 0:
                terms["pose_keep_shape"] = w.pose_keep_shape * pose_keep_error(T, T_start, no_truth, scale_free=True)
            total = total + terms.get("pose_keep", 0.0) + terms.get("pose_keep_shape", 0.0)
        if w.pose_steady > 0:
            terms["pose_steady"] = w.pose_steady * steady_speed_error(T, batch_reference_step(T))
            total = total + terms["pose_steady"]
        n_twins = 0 if twin_rows is None else len(twin_rows)  # extra_T: the twins' rows, then the next ones'
        if twin_rows is not None:
            terms["pose_stride"] = w.pose_stride * stride_ratio_error(T[twin_rows], extra_T[:n_twins])
            total = total + terms["pose_stride"]
        if next_rows is not None:
            terms["pose_overlap"] = w.pose_overlap * overlap_step_error(T[next_rows], extra_T[n_twins:])
            total = total + terms["pose_overlap"]
        return StageLoss(total, _as_floats(**terms, total=total))

    def _photometric_mean(
        self, error: torch.Tensor, flow: torch.Tensor, identity_error: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Mean rigid photometric error over the pixels the enabled masks keep.

        Args:
            error: (B, 3, H, W) error of the rigid warp.
            flow: (B, 2, H, W) the rigid flow that made it.
            identity_error: (B, 3, H, W) error of the unwarped pair (needed with ``automask``).
        """
        if not (self.mask_out_of_view or self.automask):
            return error.mean()
        keep = torch.ones_like(error[:, :1])
        if self.mask_out_of_view:
            keep = keep * in_view_mask(flow)
        if self.automask:
            warped_better = error.mean(1, keepdim=True) < identity_error.mean(1, keepdim=True)
            keep = keep * warped_better.to(error.dtype)
        return masked_mean(error, keep)

    # ------------------------------------------------------------------ flow
    def flow_forward(self, target, sources, K):
        """Full (residual + rigid) flows both ways at every scale.

        The rigid part comes from the frozen DepthNet/PoseNet under no_grad.
        Returns (fwd_full, bwd_full, target_pyr, source_pyr), each flow list
        holding (N*B, 2, H_s, W_s) pixels.
        """
        if self.direct_flow:
            return self._direct_flow_forward(target, sources)
        corrupt = self.flow_net is not None and self.flow_net.training and self.rigid_corruption > 1
        with torch.no_grad():
            factors = self.corrupted_pose_factors(target.shape[0], target.device) if corrupt else None
            rigid, target_pyr, source_pyr = self.rigid_forward(target, sources, K, pose_factors=factors)
        fwd_in = flownet_input(target_pyr[0], source_pyr[0], rigid.fwd_warp[0], rigid.fwd_flow[0], rigid.fwd_error[0])
        bwd_in = flownet_input(source_pyr[0], target_pyr[0], rigid.bwd_warp[0], rigid.bwd_flow[0], rigid.bwd_error[0])
        residual = self.flow_net(torch.cat([fwd_in, bwd_in], dim=0))
        NB = fwd_in.shape[0]
        fwd_full = [residual[s][:NB] + rigid.fwd_flow[s] for s in range(NUM_SCALES)]
        bwd_full = [residual[s][NB:] + rigid.bwd_flow[s] for s in range(NUM_SCALES)]
        return fwd_full, bwd_full, target_pyr, source_pyr

    def _direct_flow_forward(self, target, sources):
        """:meth:`flow_forward` of a ``direct_flow`` model: DepthNet and PoseNet are not run."""
        target_n, _, source_rows = network_rows(target, sources)
        target_pyr, source_pyr = image_pyramid(target_n.repeat(sources.shape[1], 1, 1, 1)), image_pyramid(source_rows)
        alpha = self.weights.alpha_recon
        fwd_in = direct_flownet_input(target_pyr[0], source_pyr[0], alpha)
        bwd_in = direct_flownet_input(source_pyr[0], target_pyr[0], alpha)
        flows = self.flow_net(torch.cat([fwd_in, bwd_in], dim=0))
        NB = fwd_in.shape[0]
        return [f[:NB] for f in flows], [f[NB:] for f in flows], target_pyr, source_pyr

    def corrupted_pose_factors(self, batch: int, device: torch.device) -> torch.Tensor:
        """(B, 1, 1) factors for the poses behind a training batch's rigid flow: 0 for a share
        :data:`RIGID_ZEROED` of the snippets (ResFlowNet finds the whole flow), else log-uniform in
        [1 / c, c], c = ``rigid_corruption``.

        Issue 53, round 19: on the KITTI test drive every model's rigid flow explained the next frame worse
        than no motion (wrong depth on near trucks, a constant step), and ResFlowNet, trained only on
        rigid flows that were nearly right, passed the error on; fed zero rigid flow instead, round 14's
        ResFlowNet beat no motion on all 39 moving pairs of frames 10-48.
        """
        log_c = math.log(self.rigid_corruption)
        factors = torch.exp((2 * torch.rand(batch, device=device) - 1) * log_c)
        factors = factors * (torch.rand(batch, device=device) >= RIGID_ZEROED)
        return factors[:, None, None]

    def gate_loss(self, target, sources, pose_gt: torch.Tensor, **_unused) -> StageLoss:
        """Stage rigid with ``--gate-only``: the motion gate alone against :func:`motion_labels` (DepthNet and
        PoseNet's trunk are not run)."""
        pose_input = torch.cat([IMAGE_NORM.apply(target), IMAGE_NORM.apply(sources).flatten(1, 2)], dim=1)
        logits = self.pose_net.gate.logits(pose_input)
        moving = motion_labels(pose_gt)
        error = gate_error(logits, moving)
        total = self.weights.pose_gate * error
        open_still = (torch.sigmoid(logits) * (1 - moving)).sum() / (1 - moving).sum().clamp(min=1)
        return StageLoss(total, _as_floats(pose_gate=total, gate_on_still=open_still, total=total))

    def flow_loss(self, target, sources, K, flow_gt: torch.Tensor | None = None) -> StageLoss:
        """Stage 2: full-flow warping (consistency-masked), flow smoothness, consistency.

        With ``weights.flow_supervision`` > 0 and ``flow_gt`` (B, 3, H, W) = u, v px, valid
        (synthetic scenes: flow target -> next frame), the full forward flow to the next frame at
        every scale, upsampled to H x W, also pays its end-point error against it (a deviation
        from GeoNet, for pre-training).
        """
        w = self.weights
        fwd_full, bwd_full, target_pyr, source_pyr = self.flow_forward(target, sources, K)
        N = self.num_source
        warp_loss = smooth_loss = consistency_loss = 0.0
        for s in range(NUM_SCALES):
            fwd_err = photometric_error(flow_warp(source_pyr[s], fwd_full[s]), target_pyr[s], w.alpha_recon)
            bwd_err = photometric_error(flow_warp(target_pyr[s], bwd_full[s]), source_pyr[s], w.alpha_recon)
            if w.flow_consistency > 0:
                diff_fwd, mask_tgt = flow_consistency(
                    fwd_full[s], bwd_full[s], s, w.consistency_alpha, w.consistency_beta
                )
                diff_bwd, mask_src = flow_consistency(
                    bwd_full[s], fwd_full[s], s, w.consistency_alpha, w.consistency_beta
                )
                warp_loss = warp_loss + w.flow_warp * N / 2 * (
                    masked_mean(fwd_err, mask_tgt) + masked_mean(bwd_err, mask_src)
                )
                consistency_loss = consistency_loss + w.flow_consistency / 2 * (
                    masked_mean(diff_fwd, mask_tgt) + masked_mean(diff_bwd, mask_src)
                )
            else:
                warp_loss = warp_loss + w.flow_warp * N / 2 * (fwd_err.mean() + bwd_err.mean())
            smooth_loss = smooth_loss + w.flow_smooth / 2 ** (s + 1) * (
                edge_aware_smoothness(fwd_full[s], target_pyr[s]) + edge_aware_smoothness(bwd_full[s], source_pyr[s])
            )
        total = warp_loss + smooth_loss + consistency_loss
        terms = {"flow_warp": warp_loss, "flow_smooth": smooth_loss, "flow_consistency": consistency_loss}
        if w.flow_supervision > 0 and flow_gt is not None:
            B = target.shape[0]
            rows = slice(self.next_source * B, (self.next_source + 1) * B)  # fwd rows are source-major
            flow_sup = sum(flow_endpoint_error(fwd_full[s][rows], flow_gt) for s in range(NUM_SCALES))
            terms["flow_supervised"] = w.flow_supervision * flow_sup
            total = total + terms["flow_supervised"]
        return StageLoss(total, _as_floats(**terms, total=total))

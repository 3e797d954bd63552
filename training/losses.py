"""GeoNet's loss terms, per the official implementation (spec section 5).

All images here are network-range ([-1, 1]); the SSIM constants tuned for
[0, 1] images are kept as in the official code.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F

SSIM_C1 = 0.01**2
SSIM_C2 = 0.03**2


@dataclass(frozen=True)
class LossWeights:
    """Loss weights and constants (official defaults, paper section 4.1)."""

    rigid_warp: float = 1.0
    disp_smooth: float = 0.5
    flow_warp: float = 1.0
    flow_smooth: float = 0.2
    flow_consistency: float = 0.2
    alpha_recon: float = 0.85  # weight of DSSIM vs L1 in the photometric error
    consistency_alpha: float = 3.0
    consistency_beta: float = 0.05
    # Not in GeoNet (0 = official): weight of the scale-invariant log-depth error against the
    # synthetic generator's ground truth, for supervised pre-training on synthetic scenes.
    depth_supervision: float = 0.0
    # Not in GeoNet (0 = official): weight of the end-point error of the full flow against the
    # synthetic generator's ground truth (flow target -> next frame), for supervised pre-training.
    flow_supervision: float = 0.0
    # Not in GeoNet (0 = official): weight of the scale-aligned pose error against true poses
    # (KITTI odometry's, the synthetic generator's), for samples prepared with --train-pose.
    pose_supervision: float = 0.0
    # Not in GeoNet (0 = off): weight of the speed error (:func:`speed_error`): each moving snippet's
    # predicted path against its true one under one unit for the whole run, not one per snippet.
    pose_speed: float = 0.0
    # Not in GeoNet (0 = off): weight of the pull toward the starting PoseNet on snippets without true
    # poses (:func:`pose_keep_error`), so fine-tuning for the stops keeps how it drives.
    pose_keep: float = 0.0
    # Not in GeoNet (0 = off): the same pull on the motion's shape only (``pose_keep_error(...,
    # scale_free=True)``): step directions and length ratios held, each snippet's speed free.
    pose_keep_shape: float = 0.0
    # Not in GeoNet (0 = off): weight of :func:`steady_speed_error`, the spread of a snippet's step
    # lengths (the camera's speed barely changes within a snippet).
    pose_steady: float = 0.0
    # Not in GeoNet (0 = off): weight of :func:`stride_ratio_error`, each ``stride2`` copy's translations
    # against twice those of its target's normal snippet (needs samples prepared with --motion-mix).
    pose_stride: float = 0.0
    # Not in GeoNet (0 = off): weight of :func:`overlap_step_error`, the step t -> t+1 of each snippet
    # against the same step in the next target's snippet (neighbouring PoseNet calls agree on speed).
    pose_overlap: float = 0.0
    # Not in GeoNet (0 = none): PoseNet gets a motion gate (``training.networks.posenet.MotionGate``),
    # and stage rigid pays W x :func:`gate_error` against :func:`motion_labels`.
    pose_gate: float = 0.0

    @property
    def keeps_pose(self) -> bool:
        """Whether a pose-keep term is on, so the starting PoseNet must be held (:meth:`GeoNet.keep_pose_of`)."""
        return self.pose_keep > 0 or self.pose_keep_shape > 0


def _mean_3x3(x: torch.Tensor) -> torch.Tensor:
    # TF 'SAME' average pooling: border windows average only the real pixels.
    return F.avg_pool2d(x, 3, stride=1, padding=1, count_include_pad=False)


def ssim(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Per-pixel SSIM over 3x3 windows.

    Args:
        x, y: (B, C, H, W).
    Returns:
        (B, C, H, W) SSIM; equals 1 where x == y.
    """
    mu_x, mu_y = _mean_3x3(x), _mean_3x3(y)
    sigma_x = _mean_3x3(x * x) - mu_x**2
    sigma_y = _mean_3x3(y * y) - mu_y**2
    sigma_xy = _mean_3x3(x * y) - mu_x * mu_y
    numerator = (2 * mu_x * mu_y + SSIM_C1) * (2 * sigma_xy + SSIM_C2)
    denominator = (mu_x**2 + mu_y**2 + SSIM_C1) * (sigma_x + sigma_y + SSIM_C2)
    return numerator / denominator


def dssim(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Structural dissimilarity ``clip((1 - SSIM) / 2, 0, 1)``, (B, C, H, W)."""
    return torch.clamp((1.0 - ssim(x, y)) / 2.0, 0.0, 1.0)


def photometric_error(
    warped: torch.Tensor, reference: torch.Tensor, alpha: float = LossWeights.alpha_recon
) -> torch.Tensor:
    """``alpha * DSSIM + (1 - alpha) * |warped - reference|`` per channel.

    Args:
        warped, reference: (B, 3, H, W) network-range images.
    Returns:
        (B, 3, H, W) error map.
    """
    return alpha * dssim(warped, reference) + (1.0 - alpha) * (warped - reference).abs()


def edge_aware_smoothness(field: torch.Tensor, image: torch.Tensor) -> torch.Tensor:
    """First-order smoothness weighted by ``exp(-mean_rgb |grad I|)``.

    For a multi-channel field (flow) this equals the official average of the
    per-component terms, since every component has the same pixel count.

    Args:
        field: (B, C, H, W) disparity (C=1) or flow (C=2).
        image: (B, 3, H, W) the matching network-range image.
    Returns:
        scalar ``mean|d_x f * w_x| + mean|d_y f * w_y|``.
    """
    field_dx = field[:, :, :, :-1] - field[:, :, :, 1:]
    field_dy = field[:, :, :-1, :] - field[:, :, 1:, :]
    weight_x = torch.exp(-(image[:, :, :, :-1] - image[:, :, :, 1:]).abs().mean(1, keepdim=True))
    weight_y = torch.exp(-(image[:, :, :-1, :] - image[:, :, 1:, :]).abs().mean(1, keepdim=True))
    return (field_dx * weight_x).abs().mean() + (field_dy * weight_y).abs().mean()


def masked_mean(values: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """``sum(mean_c(values) * mask) / sum(mask)``.

    Args:
        values: (B, C, H, W).
        mask: (B, 1, H, W) with 0/1 entries.
    Returns:
        scalar; 0 when the mask is empty (the official code divides by zero there).
    """
    weighted = (values.mean(dim=1, keepdim=True) * mask).sum()
    return weighted / mask.sum().clamp(min=1.0)


def flow_endpoint_error(flow: torch.Tensor, flow_gt: torch.Tensor) -> torch.Tensor:
    """Mean end-point error over the valid ground-truth pixels, per image, then over images.

    Args:
        flow: (B, 2, h, w) predicted flow in pixels of its own resolution; resized (bilinear) to
            the ground truth's H x W with the vectors scaled by W / w and H / h.
        flow_gt: (B, 3, H, W): u, v px and valid 0/1.
    Returns:
        scalar mean over the images that have a valid pixel; 0 when none has.
    """
    H, W = flow_gt.shape[-2:]
    h, w = flow.shape[-2:]
    if (h, w) != (H, W):
        flow = F.interpolate(flow, size=(H, W), mode="bilinear", align_corners=False)
        flow = flow * flow.new_tensor([W / w, H / h]).reshape(1, 2, 1, 1)
    valid = flow_gt[:, 2]
    # eps inside the sqrt: its gradient is infinite where the prediction is exact
    epe = torch.sqrt((flow - flow_gt[:, :2]).square().sum(dim=1) + 1e-8) * valid
    count = valid.sum(dim=(1, 2))
    has_gt = (count > 0).to(flow.dtype)
    per_image = epe.sum(dim=(1, 2)) / count.clamp(min=1.0)
    return (per_image * has_gt).sum() / has_gt.sum().clamp(min=1.0)


def scale_invariant_log_error(depth: torch.Tensor, depth_gt: torch.Tensor) -> torch.Tensor:
    """Eigen et al.'s scale-invariant log error (lambda = 1), per image, as an RMS.

    ``sqrt(mean(d^2) - mean(d)^2)`` with ``d = log(depth) - log(depth_gt)`` over the pixels with
    ground truth: the spread of the log ratio, blind to one global scale, since a monocular
    net's scale is set by the pose it learns with, not by the ground truth.

    Args:
        depth: (B, 1, H, W) predicted depth, > 0.
        depth_gt: (B, 1, H, W) metres, 0 = no ground truth.
    Returns:
        scalar mean over the images that have ground truth; 0 when none has.
    """
    valid = (depth_gt > 0).to(depth.dtype)
    count = valid.sum(dim=(1, 2, 3))
    d = (torch.log(depth) - torch.log(depth_gt.clamp(min=1e-3))) * valid
    n = count.clamp(min=1.0)
    mean = d.sum(dim=(1, 2, 3)) / n
    # centred (two-pass) variance: mean(d^2) - mean(d)^2 cancels in float32 and leaves ~1e-3 of spread
    # where the log ratio is one constant
    centred = (d - mean.view(-1, 1, 1, 1)) * valid
    variance = centred.square().sum(dim=(1, 2, 3)) / n
    has_gt = (count > 0).to(depth.dtype)
    # eps inside the sqrt: its gradient is infinite at a perfect (zero-spread) prediction
    return (torch.sqrt(variance + 1e-8) * has_gt).sum() / has_gt.sum().clamp(min=1.0)


def has_true_pose(T_gt: torch.Tensor) -> torch.Tensor:
    """(B,) bool: the snippets of ``T_gt`` (B, N, 4, 4) that carry true motions (all zeros = none)."""
    return (T_gt[:, :, 3, 3] != 0).all(dim=1)


def scale_aligned_pose_error(
    T: torch.Tensor, T_gt: torch.Tensor, still_ref_step: torch.Tensor | None = None
) -> torch.Tensor:
    """Error of predicted snippet motions against true ones, blind to the monocular scale.

    Per snippet, the predicted translations are scaled by the least-squares factor onto the true
    ones (the alignment of the official snippet ATE); the error is the aligned translation error
    relative to the true path length, plus the chordal rotation error ``||R - R_gt||_F``. The
    scale factor is not differentiated through: it only says which translation the net's own
    scale should have.

    A still snippet (true path under :data:`STILL_PATH`: identity labels, issue 53) has no scale to
    align; its translation error is the predicted path relative to the mean predicted step of the
    batch's moving snippets (the net's own unit, not differentiated; :data:`STILL_REF_STEP` when the
    batch has none), so a still camera learns to predict no motion whatever its depth scale.
    ``still_ref_step`` (the run's mean moving step, :class:`SpeedUnit`) replaces both: a batch of still
    snippets alone then does not pull every step toward the fixed constant (round 4's scale collapse).

    Args:
        T: (B, N, 4, 4) predicted motion target -> each source.
        T_gt: (B, N, 4, 4) true motion, all zeros for a snippet without.
        still_ref_step: scalar tensor or None.
    Returns:
        scalar mean over the snippets that have true poses; 0 when none has.
    """
    has_gt = has_true_pose(T_gt).to(T.dtype)  # (B,)
    t, t_gt = T[..., :3, 3], T_gt[..., :3, 3]  # (B, N, 3)
    true_path = t_gt.norm(dim=-1).sum(dim=1)  # (B,)
    still = (true_path < STILL_PATH).to(T.dtype) * has_gt
    moving = has_gt - still
    scale = ((t * t_gt).sum(dim=(1, 2)) / t.square().sum(dim=(1, 2)).clamp(min=1e-12)).detach()
    aligned = (scale.view(-1, 1, 1) * t - t_gt).norm(dim=-1).sum(dim=1) / true_path.clamp(min=1e-3)
    predicted_path = t.norm(dim=-1).sum(dim=1)  # (B,)
    n_steps = t.shape[1]
    if still_ref_step is not None:
        ref_step = still_ref_step.to(T.dtype).clamp(min=1e-6)
    elif moving.sum() > 0:
        ref_step = ((predicted_path * moving).sum() / moving.sum() / n_steps).detach().clamp(min=1e-6)
    else:
        ref_step = torch.as_tensor(STILL_REF_STEP, dtype=T.dtype, device=T.device)
    translation = moving * aligned + still * predicted_path / (n_steps * ref_step)
    rotation = (T[..., :3, :3] - T_gt[..., :3, :3]).flatten(2).norm(dim=-1).mean(dim=1)
    return ((translation + rotation) * has_gt).sum() / has_gt.sum().clamp(min=1.0)


def path_lengths(T: torch.Tensor, T_gt: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(predicted path, true path, moving) per snippet, each (B,): the summed translation lengths of
    the motions target -> each source, and 1.0 where the snippet has true poses that move.

    Args:
        T, T_gt: (B, N, 4, 4) as in :func:`scale_aligned_pose_error` (T_gt all zeros = no truth).
    """
    has_gt = has_true_pose(T_gt).to(T.dtype)
    true_path = T_gt[..., :3, 3].norm(dim=-1).sum(dim=1)
    moving = has_gt * (true_path >= STILL_PATH).to(T.dtype)
    return T[..., :3, 3].norm(dim=-1).sum(dim=1), true_path, moving


def speed_error(
    predicted_path: torch.Tensor, true_path: torch.Tensor, moving: torch.Tensor, unit: torch.Tensor
) -> torch.Tensor:
    """How far each moving snippet's speed is from the truth under one unit: mean over the moving
    snippets of ``|unit * predicted_path - true_path| / true_path``; 0 when the batch has none.

    The scale-aligned pose error fits a scale per snippet, so it never says how fast the camera moves:
    a PoseNet whose step jitters from snippet to snippet pays nothing for it, and the official snippet
    ATE (5 frames, two 3-frame calls chained) does (issue 53, round 4). With one ``unit`` (true metres
    per predicted unit, not differentiated: :class:`SpeedUnit`) for every snippet of a run, the
    speeds must agree with each other; valid where every sample with true poses shares one camera
    scale (one rig, DepthNet frozen).

    Args:
        predicted_path, true_path, moving: (B,) from :func:`path_lengths`.
        unit: scalar tensor.
    """
    error = (unit * predicted_path - true_path).abs() / true_path.clamp(min=STILL_PATH)
    return (error * moving).sum() / moving.sum().clamp(min=1.0)


class SpeedUnit:
    """The run's unit for :func:`speed_error` and the reference a still snippet is measured against:
    running means (the first batch sets them) over each batch's moving snippets of the least-squares
    factor ``Σ(true·predicted) / Σ(predicted²)`` and of the predicted path."""

    def __init__(self, momentum: float = 0.9):
        self.momentum = momentum
        self.unit: float | None = None
        self.path: float | None = None

    def _blend(self, old: float | None, new: float) -> float:
        return new if old is None else self.momentum * old + (1 - self.momentum) * new

    def update(
        self, predicted_path: torch.Tensor, true_path: torch.Tensor, moving: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """(unit, mean moving path): 1.0 and None until a batch has a moving snippet."""
        p, t = predicted_path.detach() * moving, true_path.detach() * moving
        if moving.sum() > 0:
            self.unit = self._blend(self.unit, float((p * t).sum() / p.square().sum().clamp(min=1e-12)))
            self.path = self._blend(self.path, float(p.sum() / moving.sum()))
        unit = torch.as_tensor(self.unit if self.unit is not None else 1.0, dtype=predicted_path.dtype)
        return unit, None if self.path is None else torch.as_tensor(self.path, dtype=predicted_path.dtype)


def pose_keep_error(
    T: torch.Tensor, T_start: torch.Tensor, keep: torch.Tensor, scale_free: bool = False
) -> torch.Tensor:
    """How far the predicted motions moved from the starting PoseNet's, on the snippets in ``keep``.

    Issue 53, round 6: every stop round made the steps of steady driving worse, in length and in
    direction (docs/stop_diagnosis.md), where the bundled PoseNet was best. On the snippets without true
    poses (moving footage; the still copies carry identity poses and learn to stop) this error holds the
    net to the starting one's motion: the translation difference relative to the starting path, plus the
    chordal rotation difference ``||R - R_start||_F``.

    ``scale_free`` (round 8) compares the motion's shape only: each snippet's translations divided by its
    own path length, the predicted and the starting ones alike, so a snippet's speed stays free (the
    still copies and the photometric loss set it) while its step directions and the ratio of its step
    lengths are held: what the scale-aligned snippet ATE measures. Round 7's term held the speed too,
    and with it the starting net's blindness to stops.

    Args:
        T, T_start: (B, N, 4, 4) predicted and starting motions target -> each source.
        keep: (B,) 1.0 for the snippets to hold, 0.0 for the others.
        scale_free: compare translations each normalised by its snippet's path.
    Returns:
        scalar mean over the kept snippets; 0 when none is.
    """
    t, t_start = T[..., :3, 3], T_start[..., :3, 3]
    start_path = t_start.norm(dim=-1).sum(dim=1).clamp(min=1e-3)
    if scale_free:
        path = t.norm(dim=-1).sum(dim=1).clamp(min=1e-3)
        translation = (t / path[:, None, None] - t_start / start_path[:, None, None]).norm(dim=-1).sum(dim=1)
    else:
        translation = (t - t_start).norm(dim=-1).sum(dim=1) / start_path
    rotation = (T[..., :3, :3] - T_start[..., :3, :3]).flatten(2).norm(dim=-1).mean(dim=1)
    return ((translation + rotation) * keep).sum() / keep.sum().clamp(min=1.0)


STILL_PATH = 1e-6  # a true path shorter than this (metres or unit steps) is a still camera
STILL_REF_STEP = 0.1  # the bundled PoseNet's step at driving speed, in its own units (docs/models.md)


def snippet_steps(T: torch.Tensor) -> torch.Tensor:
    """(B, N, 4, 4) motions target -> each source, sources in temporal order around the target ->
    (B, N) lengths of the camera's steps between consecutive frames of each snippet."""
    t = T[..., :3, 3]
    k = t.shape[1] // 2
    # The camera's positions in time order, the target's (the origin) between the sources'.
    positions = torch.cat([t[:, :k], torch.zeros_like(t[:, :1]), t[:, k:]], dim=1)
    return (positions[:, 1:] - positions[:, :-1]).norm(dim=-1)


def batch_reference_step(T: torch.Tensor) -> torch.Tensor:
    """:func:`steady_speed_error`'s ``reference_step`` for a batch: half the median of the snippets' mean
    steps, not differentiated (the still copies, under half a batch, stay below it). (B, N, 4, 4) -> scalar."""
    return 0.5 * snippet_steps(T).mean(dim=1).median().detach()


def steady_speed_error(T: torch.Tensor, reference_step: torch.Tensor | None = None) -> torch.Tensor:
    """How unevenly a snippet's steps are predicted: mean over the steps of ``|step - mean step|``,
    divided by the larger of the snippet's mean step and ``reference_step``; mean over the batch.

    Issue 53, round 10: the stop rounds lost the held-out snippet ATE to step-length jitter (06: a
    5-frame snippet's steps spread 3.5 % against 0.2 % in the truth, docs/stop_diagnosis.md), and the
    scale-aligned errors never see it within a snippet. Within a snippet of a few frames a car's speed
    barely changes, whether it drives, creeps or stands; no truth is needed, so every snippet pays it.
    ``reference_step`` (a typical moving step, not differentiated) keeps a still snippet's relative
    spread of near-zero steps from counting as much as a moving one's.

    Args:
        T: (B, N, 4, 4) motions target -> each source, sources in temporal order around the target
            (``geonet_infer.core.snippets.snippet_indices``: N / 2 before it, N / 2 after it).
        reference_step: scalar, or None (the snippet's own mean step alone).
    Returns:
        scalar.
    """
    steps = snippet_steps(T)
    mean_step = steps.mean(dim=1, keepdim=True)
    scale = mean_step.detach()
    if reference_step is not None:
        scale = scale.clamp(min=float(reference_step))
    return ((steps - mean_step).abs().mean(dim=1, keepdim=True) / scale.clamp(min=1e-6)).mean()


def overlap_step_error(T_this: torch.Tensor, T_next: torch.Tensor) -> torch.Tensor:
    """How far two overlapping snippets disagree on the length of the step they share:
    mean of ``(log |t_this(t -> t+1)| - log |t_next(t+1 -> t)|)^2``.

    Issue 53, round 16: the stop rounds' PoseNets measured speed but each call on its own: on held-out
    KITTI odometry 06 the step t -> t+1 from the call on (t-1, t, t+1) and from the call on
    (t, t+1, t+2) differed by 12.0 % (round 14, log RMS; the bundled model 2.5 %) while the two steps
    inside one call agreed within 0.6 % (``experiments/stop_overlap_jitter.py``). A snippet trajectory is chained
    from several calls, so that disagreement is the step-length spread that cost those rounds the
    held-out pose. A motion and its inverse have translations of the same length, so the shared step
    is the first source after the target in ``T_this`` and the last source before it in ``T_next``.

    Args:
        T_this: (B, N, 4, 4) motions target t -> each source, sources in temporal order
            (N / 2 before the target, N / 2 after it).
        T_next: (B, N, 4, 4) the same for the snippets of target t+1.
    Returns:
        scalar.
    """
    half = T_this.shape[1] // 2
    this = T_this[:, half, :3, 3].norm(dim=-1).clamp(min=1e-6).log()
    nxt = T_next[:, half - 1, :3, 3].norm(dim=-1).clamp(min=1e-6).log()
    return ((this - nxt) ** 2).mean()


def stride_ratio_error(T_fast: torch.Tensor, T_slow: torch.Tensor, ratio: float = 2.0) -> torch.Tensor:
    """How far the translations of a sped-up snippet are from ``ratio`` times those of the same target's
    normal snippet: mean over sources of ``(log |t_fast| - log |t_slow| - log ratio)^2``.

    Issue 53, round 13: every stop round's PoseNet told a still snippet from a moving one but not a fast
    one from a slow one (held-out KITTI odometry: frames t-2, t, t+2 gave 0.96-1.22 times the step of
    t-1, t, t+1, against 2 in the truth), so the drive's creeping pairs got a cruising step. The
    ``stride2`` copies of ``training.prepare --motion-mix`` hold t-2, t, t+2; paired with the normal
    snippet of the same target (same augmentation), the ratio of their steps needs no truth. Logs make
    the term scale-free, so it fixes no speed of its own.

    Args:
        T_fast: (B, N, 4, 4) motions target -> sources of the stride-``ratio`` snippets.
        T_slow: (B, N, 4, 4) the same targets' stride-1 snippets.
    Returns:
        scalar.
    """
    fast = T_fast[..., :3, 3].norm(dim=-1).clamp(min=1e-6).log()
    slow = T_slow[..., :3, 3].norm(dim=-1).clamp(min=1e-6).log()
    return ((fast - slow - math.log(ratio)) ** 2).mean()


def motion_labels(T_gt: torch.Tensor) -> torch.Tensor:
    """(B,) 1.0 where the camera moves, 0.0 where it stands still, from true motions (B, N, 4, 4).

    A snippet with true motions is still when their path is under :data:`STILL_PATH` (the still copies'
    identity poses, the synthetic queues' stops); a snippet without them (all zeros) counts as moving:
    the footage without true poses here is driving footage, whose still copies carry identity poses
    (``training.prepare --motion-mix static=P``).
    """
    true_path = T_gt[..., :3, 3].norm(dim=-1).sum(dim=1)
    still = has_true_pose(T_gt) & (true_path < STILL_PATH)
    return (~still).to(T_gt.dtype)


def gate_error(logits: torch.Tensor, moving: torch.Tensor) -> torch.Tensor:
    """Binary cross-entropy of a motion gate's logits (B,) against labels (B,) in {0, 1}.

    Issue 53, round 19: every PoseNet trained to see the stops lost the held-out pose of steady driving
    (rounds 1-18), as one net answered both whether and how the camera moves. The gate answers whether;
    the trunk, frozen, keeps how.
    """
    return F.binary_cross_entropy_with_logits(logits, moving)

"""Evaluation metrics of the official GeoNet protocols (numpy only).

Depth: Eigen-split metrics with per-image median scaling and the Garg crop.
Flow: KITTI 2015 end-point error and outlier rate (Fl) / accuracy (ACC).
Pose: the snippet "ATE" of SfMLearner/GeoNet, quirk included, plus a true RMSE.

Every function is pure: arrays in, numbers/arrays out. See docs/evaluation.md.
"""

from __future__ import annotations

import cv2
import numpy as np

from geonet_infer.conventions import rigid_inverse  # noqa: F401 -- also part of this module's API
from geonet_infer.errors import InputError

# Crop fractions (row_start, row_end, col_start, col_end) of the image size,
# truncated to int exactly like the official ``.astype(np.int32)``.
# Garg ECCV16 crop: what GeoNet/SfMLearner/monodepth report.
GARG_CROP = (0.40810811, 0.99189189, 0.03594771, 0.96405229)
# monodepth's "eigen_crop" (found by trial and error to reproduce Eigen NIPS14).
EIGEN_CROP = (0.3324324, 0.91351351, 0.0359477, 0.96405229)
CROPS = {"garg": GARG_CROP, "eigen": EIGEN_CROP}

DEPTH_KEYS = ("abs_rel", "sq_rel", "rmse", "rmse_log", "a1", "a2", "a3")

# KITTI flow outlier thresholds: EPE > 3 px AND EPE / |gt| > 5 %.
FLOW_OUTLIER_PX = 3.0
FLOW_OUTLIER_REL = 0.05


# --------------------------------------------------------------------------- depth
def crop_mask(shape, crop="garg"):
    """Boolean evaluation-crop mask.

    shape: (H, W). crop: "garg", "eigen" or None (everything).
    Returns (H, W) bool, True inside rows [int(f0*H), int(f1*H)) and
    cols [int(f2*W), int(f3*W)).
    """
    height, width = int(shape[0]), int(shape[1])
    if crop is None:
        return np.ones((height, width), dtype=bool)
    if crop not in CROPS:
        raise InputError(None, f"unknown depth crop {crop!r}", "use 'garg' (the official protocol), 'eigen' or None")
    f = CROPS[crop]
    # np.int32 truncation as in the official eval (e.g. 0.408*375 = 153.04 -> 153).
    r0, r1 = int(f[0] * height), int(f[1] * height)
    c0, c1 = int(f[2] * width), int(f[3] * width)
    mask = np.zeros((height, width), dtype=bool)
    mask[r0:r1, c0:c1] = True
    return mask


def resize_depth_to(pred, shape):
    """Resize a predicted DEPTH map to the ground-truth size, as the official eval.

    pred: (h, w) float depth. shape: (H, W). Returns (H, W) float32.
    cv2 bilinear on depth (not on disparity: that is monodepth2's variant).
    """
    pred = np.asarray(pred, dtype=np.float32)
    if pred.ndim != 2:
        raise InputError(
            None,
            f"predicted depth must be 2-D (h, w), got shape {pred.shape}",
            "squeeze batch/channel axes before evaluating",
        )
    height, width = int(shape[0]), int(shape[1])
    return cv2.resize(pred, (width, height), interpolation=cv2.INTER_LINEAR)


def depth_errors(gt, pred):
    """The 7 standard depth errors on already-masked, already-scaled 1-D arrays.

    gt, pred: (N,) positive depths. Returns dict abs_rel, sq_rel, rmse,
    rmse_log, a1, a2, a3 (delta = max(gt/pred, pred/gt) < 1.25**k, strict).
    """
    gt = np.asarray(gt, dtype=np.float64)
    pred = np.asarray(pred, dtype=np.float64)
    thresh = np.maximum(gt / pred, pred / gt)
    diff = gt - pred
    return {
        "abs_rel": float(np.mean(np.abs(diff) / gt)),
        "sq_rel": float(np.mean(diff**2 / gt)),
        "rmse": float(np.sqrt(np.mean(diff**2))),
        "rmse_log": float(np.sqrt(np.mean((np.log(gt) - np.log(pred)) ** 2))),
        "a1": float(np.mean(thresh < 1.25)),
        "a2": float(np.mean(thresh < 1.25**2)),
        "a3": float(np.mean(thresh < 1.25**3)),
    }


def depth_metrics(gt, pred, min_depth=1e-3, max_depth=80.0, crop="garg", median_scaling=True):
    """Per-image Eigen depth metrics, official GeoNet/SfMLearner protocol.

    gt: (H, W) ground-truth depth, 0 where unknown. pred: (H, W) predicted
    depth, already resized to the GT size (see :func:`resize_depth_to`).
    Steps: mask = min_depth < gt < max_depth AND crop;
    scale = median(gt[mask]) / median(pred[mask]) (1 if not median_scaling);
    pred *= scale; THEN clamp pred to [min_depth, max_depth]; errors on mask.
    Clamping before scaling would change the median and the result (the
    SfmLearner-Pytorch #31/#117 mismatch), hence the order.
    Returns dict with DEPTH_KEYS, "scale" and "n_valid" (pixels used).
    """
    gt = np.asarray(gt, dtype=np.float64)
    pred = np.asarray(pred, dtype=np.float64)
    if gt.ndim != 2 or gt.shape != pred.shape:
        raise InputError(
            None,
            f"gt shape {gt.shape} and prediction shape {pred.shape} differ or are not 2-D",
            "resize the prediction with resize_depth_to(pred, gt.shape)",
        )
    mask = (gt > min_depth) & (gt < max_depth) & crop_mask(gt.shape, crop)
    if not mask.any():
        raise InputError(
            None,
            "no ground-truth pixel inside the depth range and crop",
            f"check the GT map (valid depths in ({min_depth}, {max_depth})) and the crop",
        )
    gt_valid = gt[mask]
    pred_valid = pred[mask]
    scale = 1.0
    if median_scaling:
        pred_median = np.median(pred_valid)
        if not pred_median > 0:
            raise InputError(
                None,
                f"median predicted depth is {pred_median}, cannot median-scale",
                "predicted depths must be positive",
            )
        scale = float(np.median(gt_valid) / pred_median)
    pred_valid = np.clip(pred_valid * scale, min_depth, max_depth)
    result = depth_errors(gt_valid, pred_valid)
    result["scale"] = scale
    result["n_valid"] = int(mask.sum())
    return result


FLOOR_BIN = 0.002  # log-depth bin of depth_floor_share: 0.2 % in depth


def depth_floor_share(pred, bin_width=FLOOR_BIN):
    """Share of the lower image half's pixels in the fullest ``bin_width``-wide bin of log depth.

    A depth net whose last decoder features are all zero somewhere (dead ReLUs) outputs its
    head's bias there: one depth for the whole region, whatever the scene. A road scene's
    depth map spreads over many values (a share of a few %); a share near the region's size
    is such a floor. No ground truth needed.

    Args:
        pred: (H, W) positive depth, any scale.
    Returns: share in (0, 1].
    """
    pred = np.asarray(pred, dtype=np.float64)
    if pred.ndim != 2 or not (np.isfinite(pred).all() and (pred > 0).all()):
        raise InputError(None, "depth_floor_share needs an (H, W) map of finite positive depth")
    lower = np.log(pred[pred.shape[0] // 2 :].ravel())
    counts = np.bincount(((lower - lower.min()) / bin_width).astype(np.int64))
    return float(counts.max() / lower.size)


def aggregate(results):
    """Mean of each numeric key over per-image result dicts.

    results: list of dicts (same keys). Returns dict key -> float mean, plus
    "count" (number of images). The official scripts average per image, not
    per pixel, for depth (7 errors), flow (EPE, ACC) and pose (ATE).
    """
    results = list(results)
    if not results:
        raise InputError(None, "nothing to aggregate", "evaluate at least one sample")
    out = {}
    for key in results[0]:
        out[key] = float(np.mean([r[key] for r in results]))
    out["count"] = len(results)
    return out


def aggregate_std(results):
    """Standard deviation (population, np.std) of each numeric key; pose reports mean ± std."""
    results = list(results)
    if not results:
        raise InputError(None, "nothing to aggregate", "evaluate at least one sample")
    return {key: float(np.std([r[key] for r in results])) for key in results[0]}


# --------------------------------------------------------------------------- flow
def flow_epe(gt, valid, pred):
    """KITTI flow errors of one image (official GeoNet flowlib formula).

    gt: (H, W, 2) ground-truth flow (u, v) in pixels. valid: (H, W) bool (or
    nonzero) GT mask. pred: (H, W, 2) predicted flow at the GT size (see
    :func:`resize_flow_nearest`).
    Returns dict epe (mean end-point error over valid pixels), fl (outlier
    fraction: EPE > 3 px AND EPE / (|gt| + 1e-5) > 0.05, strict), acc = 1 - fl,
    n_valid. The 1e-5 guard on |gt| is the official one.
    """
    gt = np.asarray(gt, dtype=np.float64)
    pred = np.asarray(pred, dtype=np.float64)
    valid = np.asarray(valid) != 0
    if gt.shape != pred.shape or gt.ndim != 3 or gt.shape[2] != 2 or valid.shape != gt.shape[:2]:
        raise InputError(
            None,
            f"flow shapes differ: gt {gt.shape}, valid {valid.shape}, pred {pred.shape}",
            "gt and pred must be (H, W, 2) and valid (H, W); resize pred with resize_flow_nearest",
        )
    n_valid = int(valid.sum())
    if n_valid == 0:
        raise InputError(None, "ground-truth flow has no valid pixel", "check the GT mask channel")
    epe = np.sqrt(np.sum((gt - pred) ** 2, axis=2))[valid]
    mag = np.sqrt(np.sum(gt**2, axis=2))[valid] + 1e-5
    outlier = (epe > FLOW_OUTLIER_PX) & (epe / mag > FLOW_OUTLIER_REL)
    fl = float(outlier.sum()) / n_valid
    return {"epe": float(epe.mean()), "fl": fl, "acc": 1.0 - fl, "n_valid": n_valid}


def resize_flow_nearest(flow, shape):
    """Resize a flow field like the official eval: nearest neighbour, then rescale vectors.

    flow: (h, w, 2) (u, v) in pixels of the small image. shape: (H, W).
    Returns (H, W, 2) float32 with u *= W / w and v *= H / h.
    """
    flow = np.asarray(flow, dtype=np.float32)
    if flow.ndim != 3 or flow.shape[2] != 2:
        raise InputError(None, f"flow must be (h, w, 2), got {flow.shape}", "pass (u, v) channels last")
    src_h, src_w = flow.shape[:2]
    height, width = int(shape[0]), int(shape[1])
    out = cv2.resize(flow, (width, height), interpolation=cv2.INTER_NEAREST)
    out[:, :, 0] *= width / src_w
    out[:, :, 1] *= height / src_h
    return out


def resize_flow_gt(flow, valid, shape):
    """Resize ground-truth flow and its mask (nearest), vectors scaled as in :func:`resize_flow_nearest`.

    flow: (h, w, 2) (u, v) px; valid: (h, w) bool. shape: (H, W).
    Returns flow (H, W, 2) float32 and valid (H, W) bool; nearest, so no vector is blended
    across an object edge or with an invalid pixel.
    """
    height, width = int(shape[0]), int(shape[1])
    mask = cv2.resize(np.asarray(valid, dtype=np.uint8), (width, height), interpolation=cv2.INTER_NEAREST) > 0
    return resize_flow_nearest(flow, (height, width)), mask


# --------------------------------------------------------------------------- pose
def _align_first_and_scale(gt_xyz, pred_xyz):
    """Official snippet alignment. gt_xyz, pred_xyz: (N, 3). Returns error vectors (N, 3).

    Shift pred so its first position equals gt's, then the least-squares scale
    about the ORIGIN: s = sum(gt * pred) / sum(pred ** 2). No rotation: both
    snippets are in their first frame's coordinates, so gt[0] = pred[0] = 0
    in practice and the origin is the first position.
    """
    gt_xyz = np.asarray(gt_xyz, dtype=np.float64)
    pred_xyz = np.asarray(pred_xyz, dtype=np.float64)
    if gt_xyz.shape != pred_xyz.shape or gt_xyz.ndim != 2 or gt_xyz.shape[1] != 3 or len(gt_xyz) < 2:
        raise InputError(
            None,
            f"trajectory shapes differ or are too short: gt {gt_xyz.shape}, pred {pred_xyz.shape}",
            "pass matched (N, 3) positions with N >= 2",
        )
    pred_xyz = pred_xyz + (gt_xyz[0] - pred_xyz[0])[None, :]
    denom = np.sum(pred_xyz**2)
    # A trajectory standing still at the origin has no scale to fit: keep 1. "At the origin"
    # is relative to the GT's extent: GT files store the first position to ~1e-9, and fitting
    # a scale to that rounding noise would make a zero-motion prediction look good.
    scale = np.sum(gt_xyz * pred_xyz) / denom if denom > 1e-12 * np.sum(gt_xyz**2) else 1.0
    return pred_xyz * scale - gt_xyz


def ate_snippet(gt_xyz, pred_xyz):
    """Snippet "ATE" exactly as SfMLearner/GeoNet (and monodepth2) compute it.

    gt_xyz, pred_xyz: (N, 3) matched positions (N = 5 for the paper's
    snippets). After :func:`_align_first_and_scale`,
    value = sqrt(sum ||e_i||^2) / N.
    QUIRK kept for comparability with published numbers: it divides by N,
    not sqrt(N), so it is NOT an RMSE; it equals ate_rmse_true / sqrt(N)
    (x 0.447 for N = 5). See SfmLearner-Pytorch #88.
    """
    err = _align_first_and_scale(gt_xyz, pred_xyz)
    return float(np.sqrt(np.sum(err**2)) / len(err))


def ate_rmse_true(gt_xyz, pred_xyz):
    """Root-mean-square position error after the same alignment as :func:`ate_snippet`.

    gt_xyz, pred_xyz: (N, 3). value = sqrt(mean_i ||e_i||^2). Not comparable
    with the paper's 0.012 numbers; use it to judge the trajectory itself.
    """
    err = _align_first_and_scale(gt_xyz, pred_xyz)
    return float(np.sqrt(np.mean(np.sum(err**2, axis=1))))


def umeyama_sim3(src_xyz, dst_xyz):
    """Scale s, rotation R and translation t with dst ≈ s R src + t, least squares (Umeyama, PAMI 1991;
    the alignment of evo's ``-as``).

    src_xyz, dst_xyz: (N, 3) matched positions, N >= 3 and not all on one point.
    Returns (s, R (3, 3), t (3,)).
    """
    src, dst = np.asarray(src_xyz, np.float64), np.asarray(dst_xyz, np.float64)
    mu_src, mu_dst = src.mean(axis=0), dst.mean(axis=0)
    a, b = src - mu_src, dst - mu_dst
    var_src = np.mean(np.sum(a**2, axis=1))
    if len(src) < 3 or var_src <= 0:
        raise InputError(None, f"cannot align {len(src)} positions that do not spread", "score a longer trajectory")
    U, D, Vt = np.linalg.svd(b.T @ a / len(src))
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1  # a reflection is not a rotation
    R = U @ S @ Vt
    s = float(np.trace(np.diag(D) @ S) / var_src)
    return s, R, mu_dst - s * R @ mu_src


def align_sim3(gt_c2w, est_c2w):
    """``est_c2w`` (N, 4, 4) camera-to-world moved onto ``gt_c2w`` by the Sim(3) that best maps its
    positions onto the true ones (:func:`umeyama_sim3`): positions s R p + t, rotations R R_i.
    Returns (aligned (N, 4, 4), s)."""
    s, R, t = umeyama_sim3(est_c2w[:, :3, 3], gt_c2w[:, :3, 3])
    aligned = np.array(est_c2w, np.float64, copy=True)
    aligned[:, :3, :3] = R @ aligned[:, :3, :3]
    aligned[:, :3, 3] = (s * (R @ aligned[:, :3, 3].T)).T + t
    return aligned, s


def ape_rmse(gt_c2w, est_c2w) -> float:
    """Absolute position error of a whole trajectory after a Sim(3) alignment (evo's ``evo_ape ... -as``,
    translation part): sqrt(mean_i ||p_i - p_gt_i||^2), in the ground truth's units."""
    aligned, _ = align_sim3(gt_c2w, est_c2w)
    return float(np.sqrt(np.mean(np.sum((aligned[:, :3, 3] - gt_c2w[:, :3, 3]) ** 2, axis=1))))


def rpe_translation_rmse(gt_c2w, est_c2w) -> float:
    """Relative pose error per frame after the same Sim(3) alignment (evo's ``evo_rpe ... -as``, delta 1
    frame, translation part): the RMSE over consecutive pairs of the translation of
    inv(inv(G_i) G_i+1) inv(E_i) E_i+1."""
    aligned, _ = align_sim3(gt_c2w, est_c2w)
    gt_steps = rigid_inverse(gt_c2w[:-1]) @ gt_c2w[1:]
    est_steps = rigid_inverse(aligned[:-1]) @ aligned[1:]
    errors = rigid_inverse(gt_steps) @ est_steps
    return float(np.sqrt(np.mean(np.sum(errors[:, :3, 3] ** 2, axis=1))))


def snippet_poses_to_global(T_tgt_to_src, target_index=None):
    """Poses of every snippet frame in the FIRST frame's coordinates (official dump_pose_seq_TUM).

    T_tgt_to_src: (N, 4, 4) predicted target->frame transforms of an N-frame
    snippet, identity for the target itself; or (N-1, 4, 4) source poses only
    with ``target_index`` giving where the target's identity is inserted
    (2 for the 5-frame snippets: PoseNet predicts the 4 sources).
    Returns (N, 4, 4): G_p = T_first @ inv(T_p), the pose of frame p
    (camera p -> camera first), so G_0 = identity.
    The same function converts GT snippets when T_p = world->camera_p
    (inverse of KITTI's camera-to-world odometry poses).
    """
    T = np.asarray(T_tgt_to_src, dtype=np.float64)
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise InputError(None, f"poses must be (N, 4, 4), got {T.shape}", "stack 4x4 transforms")
    if target_index is not None:
        T = np.insert(T, target_index, np.eye(4), axis=0)
    return T[0][None] @ rigid_inverse(T)

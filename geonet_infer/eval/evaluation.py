"""Scoring loops shared by ``geonet-infer eval`` (ONNX), ``python -m training.evaluate``
(PyTorch checkpoints) and the results report: one metric code path for every method.

A method is a plain numpy callable (model adapters below, baselines in
:mod:`geonet_infer.eval.baselines`, torch predictors in ``training.evaluate``):

* depth ``fn(rgb uint8 (H, W, 3)) -> depth (h, w)``, resized to the GT size (bilinear, on depth);
* flow ``fn(frames, K) -> flow (h, w, 2)`` from ``frames[-2]`` to ``frames[-1]`` (``frames`` =
  [t-1, t, t+1] or the pair [t, t+1]), resized to the GT size with nearest neighbour and
  vectors scaled per axis (the official test);
* pose ``fn(frames (5), K) -> poses (5, 4, 4)`` of each frame in the first frame's coordinates.

Any callable may return ``(array, info_dict)``; ``info`` is kept with the item. A
prediction holding NaN or infinity is *reported*: the item's metrics become NaN, so
every mean over it is NaN too (never dropped), and ``errors`` names the item.
Depth scaled by the camera height (``scaling="camera_height"``) can fail on a frame
whose prediction shows no plausible ground plane: such a frame is *not scored* (never
median-scaled instead); ``errors`` and ``ground_fit_failed`` name it, the means cover
the other frames and ``count`` says how many those are.
Broken data (missing file, size mismatch, no valid ground-truth pixel) raises
:class:`~geonet_infer.errors.GeoNetError` naming the file.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np

from geonet_infer.core.scale import check_camera_height, fit_ground_plane
from geonet_infer.errors import GeoNetError, InputError
from geonet_infer.eval import metrics
from geonet_infer.eval.adapters import (  # noqa: F401  (re-exported: this module's names before the split)
    BASELINES,
    _needs_K,
    baseline_fns,
    model_depth_fn,
    model_flow_fn,
    model_fn,
    model_pose_fn,
    refuse_random_init,
    snippet_from_pose_calls,
)
from geonet_infer.eval.datasets import SNIPPET, Dataset, layout_class
from geonet_infer.io import read_image, write_kitti_poses, write_tum_poses
from geonet_infer.io.atomic import atomic_write, json_safe

MIN_DEPTH, MAX_DEPTH = 1e-3, 80.0
SCALINGS = ("median", "camera_height", "none")
# Paper column order (Tables 1-3), then our extra columns. (header, key, format)
COLUMNS = {
    "depth": [
        ("AbsRel", "abs_rel", "{:.3f}"),
        ("SqRel", "sq_rel", "{:.3f}"),
        ("RMSE", "rmse", "{:.3f}"),
        ("RMSElog", "rmse_log", "{:.3f}"),
        ("δ<1.25", "a1", "{:.3f}"),
        ("δ<1.25²", "a2", "{:.3f}"),
        ("δ<1.25³", "a3", "{:.3f}"),
    ],
    "flow": [
        ("EPE Noc", "epe_noc", "{:.2f}"),
        ("EPE All", "epe_all", "{:.2f}"),
        ("Fl-noc", "fl_noc", "{:.1%}"),
        ("Fl-all", "fl_all", "{:.1%}"),
    ],
    "pose": [("ATE (paper, ÷N)", "ate_snippet", "{:.4f}"), ("ATE RMSE", "ate_rmse_true", "{:.4f}")],
}
COUNT_LABEL = {"depth": "frames", "flow": "pairs", "pose": "snippets"}


# ----------------------------------------------------------------------------- calling methods
def _call(fn, *args) -> tuple[np.ndarray, dict]:
    out = fn(*args)
    if isinstance(out, tuple):
        return np.asarray(out[0]), dict(out[1])
    return np.asarray(out), {}


def _nonfinite(pred: np.ndarray) -> int:
    return int(pred.size - np.count_nonzero(np.isfinite(pred)))


def _nan_row(keys) -> dict:
    return {k: math.nan for k in keys}


def _intrinsics(item, fn, override: np.ndarray | None) -> np.ndarray | None:
    """K for methods that need it: ``override`` (at the item's frame size) or the item's calibration."""
    if not getattr(fn, "needs_intrinsics", False):
        return None
    if override is not None:
        return np.asarray(override, dtype=np.float64)
    K = item.intrinsics()
    if K is None:
        raise InputError(
            item.frames[-1],
            "no camera intrinsics for this pair",
            "the model's rigid flow needs K: add the calibration file of this layout or pass --intrinsics FX,FY,CX,CY",
        )
    return K


def _read_frames(paths: list[Path]) -> list[np.ndarray]:
    frames = [read_image(p) for p in paths]
    for p, f in zip(paths, frames):
        if f.shape != frames[-1].shape:
            raise InputError(
                p,
                f"frame is {f.shape[1]}x{f.shape[0]}, {paths[-1].name} is {frames[-1].shape[1]}x{frames[-1].shape[0]}",
                "frames of one item must share a size",
            )
    return frames


def _result(
    task: str, method: str, dataset: Dataset, settings: dict, rows: list[dict], errors: list[dict], std: bool = False
) -> dict:
    keys = [k for _, k, _ in COLUMNS[task]]
    # Rows marked not scored (a failed ground fit) stay in items and errors but not in the means.
    values = [{k: r[k] for k in keys} for r in rows if r.get("ground_fit") != "failed"]
    out = {
        "task": task,
        "method": method,
        "data": dataset.describe(),
        "settings": settings,
        "metrics": metrics.aggregate(values) if values else _nan_row(keys) | {"count": 0},
        "items": rows,
        "errors": errors,
    }
    if std:
        out["std"] = metrics.aggregate_std(values)
    return out


# ----------------------------------------------------------------------------- depth
def depth_intrinsics(item, layout: str) -> np.ndarray:
    """K at the image size of a depth item, as its layout reads it (:meth:`Layout.depth_intrinsics`)."""
    return layout_class(layout).depth_intrinsics(item)


def evaluate_depth(
    fn: Callable,
    dataset: Dataset,
    *,
    method: str = "model",
    max_depth: float = MAX_DEPTH,
    min_depth: float = MIN_DEPTH,
    crop: str | None = "auto",
    scaling: str = "median",
    camera_height: float | None = None,
    intrinsics: np.ndarray | None = None,
    observe: Callable | None = None,
) -> dict:
    """Eigen depth metrics of ``fn`` on every item, averaged per image.

    crop: "garg", "eigen", None, or "auto" (Garg on KITTI, none on synthetic frames, which have
    no bonnet or empty sky band to crop).
    scaling: "median" (per image, median GT / median prediction: the paper's protocol), "none"
    (raw depths: metric or stereo-scaled models), or "camera_height": per image, the factor that
    puts the ground plane fitted to the prediction (:func:`geonet_infer.core.scale.fit_ground_plane`)
    ``camera_height`` metres below the camera, no ground truth used. ``intrinsics``: K at the
    image size for that fit; default the item's calibration (:func:`depth_intrinsics`). A frame
    without a plausible ground plane is not scored: named in ``errors`` and ``ground_fit_failed``.
    ``observe(item, rgb, gt, pred, row)`` sees each scored frame; ``pred`` is resized to the GT
    but not scaled (``row["scale"]`` is the factor applied). Returns the result dict (see module
    docstring).
    """
    if scaling not in SCALINGS:
        raise InputError(None, f"unknown depth scaling {scaling!r}", f"choose one of {', '.join(SCALINGS)}")
    if scaling == "camera_height":
        check_camera_height(camera_height)
    if crop == "auto":
        crop = layout_class(dataset.layout).depth_crop
    keys = [k for _, k, _ in COLUMNS["depth"]]
    rows, errors, fit_failed = [], [], []
    for item in dataset.items:
        rgb = read_image(item.image)
        gt = item.load_gt(rgb.shape[:2])
        mask = (gt > min_depth) & (gt < max_depth) & metrics.crop_mask(gt.shape, crop)
        if not mask.any():
            raise InputError(
                item.gt,
                f"no ground-truth pixel in ({min_depth:g}, {max_depth:g}) m inside the {crop or 'full-image'} crop",
                "check the ground truth of this frame",
            )
        pred, info = _call(fn, rgb)
        if pred.ndim != 2:
            raise InputError(
                item.image,
                f"predicted depth has shape {pred.shape}, expected (H, W)",
                "the depth method must return one 2-D map per image",
            )
        bad = _nonfinite(pred)
        # what the frame's ground truth offers, whatever the method does: checkable against the data itself
        row = {"name": item.name, "gt_pixels": int(mask.sum()), "gt_min": float(gt[mask].min())}
        row["gt_max"] = float(gt[mask].max())
        if bad:
            errors.append({"item": item.name, "problem": f"prediction has {bad} NaN/inf values"})
            rows.append(row | _nan_row(keys) | info)
            continue
        pred = metrics.resize_depth_to(pred, gt.shape)
        scale = 1.0
        if scaling == "camera_height":
            K = np.asarray(intrinsics, np.float64) if intrinsics is not None else depth_intrinsics(item, dataset.layout)
            try:  # the runtime's own fit (what `predict --camera-height` applies), on the depth at GT size
                fit = fit_ground_plane(pred, K)
            except GeoNetError as err:  # the prediction shows no road: the method's failure on this frame
                problem = f"ground plane fit failed: {err.problem}"
                errors.append({"item": item.name, "problem": problem})
                fit_failed.append(item.name)
                rows.append(row | _nan_row(keys) | {"ground_fit": "failed", "problem": problem} | info)
                continue
            assert camera_height is not None  # checked above: scaling by camera height needs one
            scale = fit.scale_for(camera_height)
            info = {"ground_height": fit.height, "ground_inliers": fit.inlier_fraction} | info
        try:
            scores = metrics.depth_metrics(
                gt, pred * scale, min_depth, max_depth, crop=crop, median_scaling=scaling == "median"
            )
        except GeoNetError as err:  # e.g. non-positive median prediction: the method's fault
            errors.append({"item": item.name, "problem": err.problem})
            scores = _nan_row(keys)
        if scaling == "camera_height":
            scores["scale"] = scale
        rows.append(row | scores | info)
        if observe is not None:
            observe(item, rgb, gt, pred, rows[-1])
    settings = {
        "min_depth": min_depth,
        "max_depth": max_depth,
        "crop": crop,
        "scaling": scaling,
        "resize": "prediction depth resized to GT size, cv2 bilinear",
    }
    if scaling == "camera_height":
        settings["camera_height"] = camera_height
    result = _result("depth", method, dataset, settings, rows, errors)
    result["ground_truth"] = ground_truth_summary(rows, crop, min_depth, max_depth)
    if scaling == "camera_height":
        result["ground_fit_failed"] = fit_failed
    return result


def ground_truth_summary(rows: list[dict], crop: str | None, min_depth: float, max_depth: float) -> dict:
    """The depth ground truth the rows were scored on: frames, pixels inside the mask, depth range."""
    return {
        "frames": len(rows),
        "pixels": sum(r["gt_pixels"] for r in rows),
        "min_m": min(r["gt_min"] for r in rows),
        "max_m": max(r["gt_max"] for r in rows),
        "crop": crop,
        "mask": f"{min_depth:g} < GT < {max_depth:g} m",
    }


def ground_truth_line(summary: dict) -> str:
    """One line for people: ``ground truth: 3 frames, 45,310 pixels (garg crop, 0.001 < GT < 80 m), 4.3–79.9 m``."""
    return (
        f"ground truth: {summary['frames']} frame{'s' if summary['frames'] != 1 else ''}, {summary['pixels']:,} pixels "
        f"({summary['crop'] or 'no'} crop, {summary['mask']}), depth {summary['min_m']:.2f}–{summary['max_m']:.2f} m"
    )


# ----------------------------------------------------------------------------- flow
def evaluate_flow(
    fn: Callable,
    dataset: Dataset,
    *,
    method: str = "model",
    intrinsics: np.ndarray | None = None,
    observe: Callable | None = None,
) -> dict:
    """EPE on non-occluded (Noc) and all (All = KITTI "occ") GT pixels, and the Fl outlier rates.

    ``intrinsics``: K at the frames' size for items without a calibration file (Middlebury).
    ``observe(item, frames, gt_all, valid_all, pred, row)`` sees each scored pair.
    """
    keys = [k for _, k, _ in COLUMNS["flow"]]
    rows, errors = [], []
    for item in dataset.items:
        frames = _read_frames(item.frames)
        gt_noc, valid_noc = item.load_gt("noc")
        gt_all, valid_all = item.load_gt("occ")
        height, width = frames[-1].shape[:2]
        for path, gt in ((item.gt_noc, gt_noc), (item.gt_occ, gt_all)):
            if gt.shape[:2] != (height, width):
                raise InputError(
                    path,
                    f"flow ground truth is {gt.shape[1]}x{gt.shape[0]}, the frames are {width}x{height}",
                    "ground truth and frames must have the same size",
                )
        pred, info = _call(fn, frames, _intrinsics(item, fn, intrinsics))
        if pred.ndim != 3 or pred.shape[2] != 2:
            raise InputError(
                item.frames[-2],
                f"predicted flow has shape {pred.shape}, expected (H, W, 2)",
                "the flow method must return (u, v) per pixel",
            )
        row = {"name": item.name, "snippet": item.snippet}
        bad = _nonfinite(pred)
        if bad:
            errors.append({"item": item.name, "problem": f"prediction has {bad} NaN/inf values"})
            rows.append(row | _nan_row(keys) | info)
            continue
        if pred.shape[:2] != (height, width):
            pred = metrics.resize_flow_nearest(pred, (height, width))
        scored: dict[str, dict] = {}
        for which, gt, valid, path in (
            ("noc", gt_noc, valid_noc, item.gt_noc),
            ("all", gt_all, valid_all, item.gt_occ),
        ):
            if not valid.any():
                raise InputError(path, "flow ground truth has no valid pixel", "check the GT's valid channel")
            r = metrics.flow_epe(gt, valid, pred)
            scored |= {f"epe_{which}": r["epe"], f"fl_{which}": r["fl"], f"n_valid_{which}": r["n_valid"]}
        rows.append(row | scored | info)
        if observe is not None:
            observe(item, frames, gt_all, valid_all, pred, rows[-1])
    settings = {
        "resize": "nearest to GT size, u *= W/w, v *= H/h (official test)",
        "fl": f"EPE > {metrics.FLOW_OUTLIER_PX:g} px and > {metrics.FLOW_OUTLIER_REL:.0%} of |gt|",
    }
    return _result("flow", method, dataset, settings, rows, errors)


# ----------------------------------------------------------------------------- pose
def gt_snippet(camera_to_world: np.ndarray) -> np.ndarray:
    """GT camera-to-world poses -> poses in the snippet's first frame (official path: world->camera,
    then :func:`~geonet_infer.eval.metrics.snippet_poses_to_global`)."""
    return metrics.snippet_poses_to_global(metrics.rigid_inverse(camera_to_world))


def ate_rows(gt_xyz: np.ndarray, pred_xyz: np.ndarray) -> dict:
    """Paper ATE (÷N quirk) and true RMSE of one snippet. First positions are subtracted so they are
    exactly 0 (``inv(C) @ C`` leaves ~1e-16, to which the alignment would fit a huge scale)."""
    gt_xyz = gt_xyz - gt_xyz[0]
    pred_xyz = pred_xyz - pred_xyz[0]
    return {
        "ate_snippet": metrics.ate_snippet(gt_xyz, pred_xyz),
        "ate_rmse_true": metrics.ate_rmse_true(gt_xyz, pred_xyz),
    }


def evaluate_pose(
    fn: Callable,
    dataset: Dataset,
    *,
    method: str = "model",
    observe: Callable | None = None,
    trajectories: Path | None = None,
) -> dict:
    """Snippet ATE (paper's alignment and ÷N) and true RMSE, mean and std over snippets; and, where the
    snippets follow each other frame by frame, the whole trajectory (:func:`whole_trajectory`) scored as
    evo scores it: APE RMSE after a Sim(3) alignment and RPE per frame (``result["trajectory"]``).

    ``observe(item, gt_poses, pred_poses, row)`` sees each snippet (both in first-frame coordinates).
    ``trajectories``: a folder to write the true and the chained trajectory into, KITTI and TUM files
    (``gt_kitti.txt``, ``<method>_kitti.txt``, ``gt_tum.txt``, ``<method>_tum.txt``; time = frame index),
    the files ``evo_ape kitti gt_kitti.txt model_kitti.txt -as`` reads.
    """
    keys = [k for _, k, _ in COLUMNS["pose"]]
    rows, errors, preds = [], [], []
    for item in dataset.items:
        frames = _read_frames(item.frames)
        K = item.intrinsics() if getattr(fn, "needs_intrinsics", False) else None
        pred, info = _call(fn, frames, K)
        if pred.shape != (SNIPPET, 4, 4):
            raise InputError(
                item.frames[0],
                f"predicted snippet poses have shape {pred.shape}, expected ({SNIPPET}, 4, 4)",
                "one pose per snippet frame",
            )
        row = {"name": item.name}
        bad = _nonfinite(pred)
        if bad:
            errors.append({"item": item.name, "problem": f"prediction has {bad} NaN/inf values"})
            rows.append(row | _nan_row(keys) | info)
            continue
        gt = gt_snippet(item.gt_c2w)
        preds.append(pred)
        rows.append(row | ate_rows(gt[:, :3, 3], pred[:, :3, 3]) | info)
        if observe is not None:
            observe(item, gt, pred, rows[-1])
    settings = {
        "snippet": SNIPPET,
        "alignment": "first positions matched, scale s = Σ(gt·pred)/Σ(pred²), no rotation",
        "ate_snippet": "sqrt(Σ|e|²)/N: the paper's value (divides by N, not sqrt(N): NOT an RMSE)",
        "ate_rmse_true": "sqrt(Σ|e|²/N) after the same alignment",
    }
    result = _result("pose", method, dataset, settings, rows, errors, std=True)
    whole = whole_trajectory(dataset.items, preds) if not errors else None
    if whole is not None:
        gt_c2w, est_c2w, names = whole
        try:
            _, scale = metrics.align_sim3(gt_c2w, est_c2w)
        except InputError as err:  # a path standing still (identity poses) has no Sim(3) to fit
            result["trajectory"] = {"frames": len(names), "not_scored": err.problem}
            return result
        result["trajectory"] = {
            "frames": len(names),
            "ape_rmse": metrics.ape_rmse(gt_c2w, est_c2w),
            "rpe_rmse": metrics.rpe_translation_rmse(gt_c2w, est_c2w),
            "sim3_scale": scale,
            "chaining": "each snippet's first step (frame 1 in frame 0's coordinates), the last snippet's whole",
            "alignment": "Sim(3), Umeyama over every position (evo -as); errors of the translation part",
        }
        if trajectories is not None:
            result["trajectory"]["files"] = write_trajectories(Path(trajectories), method, gt_c2w, est_c2w)
    return result


def whole_trajectory(items: list, preds: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray, list[str]] | None:
    """The snippets' frames as one trajectory: (true camera-to-world (N, 4, 4), the predicted one chained
    from each snippet's first step and the last snippet's poses, frame names); None unless every snippet
    starts one frame after the one before (``--stride 1`` over one run of frames)."""
    if not items or len(items) != len(preds):
        return None
    for a, b in zip(items, items[1:]):
        if a.frames[1] != b.frames[0]:
            return None
    est = [np.eye(4)]
    for pred in preds[:-1]:
        est.append(est[-1] @ pred[1])
    start = est[-1]
    est += [start @ p for p in preds[-1][1:]]
    gt = [item.gt_c2w[0] for item in items] + list(items[-1].gt_c2w[1:])
    names = [Path(item.frames[0]).stem for item in items] + [Path(f).stem for f in items[-1].frames[1:]]
    return np.array(gt, np.float64), np.array(est, np.float64), names


def write_trajectories(folder: Path, method: str, gt_c2w: np.ndarray, est_c2w: np.ndarray) -> dict[str, str]:
    """The true and the predicted trajectory as KITTI and TUM pose files (time = frame index); returns
    {"gt_kitti": path, "kitti": path, "gt_tum": ..., "tum": ...}."""
    folder.mkdir(parents=True, exist_ok=True)
    times = np.arange(len(gt_c2w), dtype=np.float64)
    stem = "".join(c if c.isalnum() or c in "-." else "_" for c in method)
    files = {}
    for key, name, poses in (("gt_", "gt", gt_c2w), ("", stem, est_c2w)):
        files[f"{key}kitti"] = str(folder / f"{name}_kitti.txt")
        files[f"{key}tum"] = str(folder / f"{name}_tum.txt")
        write_kitti_poses(files[f"{key}kitti"], poses)
        write_tum_poses(files[f"{key}tum"], times, poses)
    return files


EVALUATORS = {"depth": evaluate_depth, "flow": evaluate_flow, "pose": evaluate_pose}


# ----------------------------------------------------------------------------- output
def _fmt(value, fmt: str) -> str:
    if value is None:
        return "–"
    return "nan" if not math.isfinite(value) else fmt.format(value)


def table_rows(result: dict, label: str, data_label: str | None = None) -> list[str]:
    """One markdown row per result: label, data, the paper's columns (mean ± std for pose), count."""
    task = result["task"]
    cells = [label, data_label or result["data"]["description"]]
    for _, key, fmt in COLUMNS[task]:
        cell = _fmt(result["metrics"].get(key), fmt)
        if "std" in result:
            cell += " ± " + _fmt(result["std"].get(key), fmt)
        cells.append(cell)
    failed = len(result.get("ground_fit_failed", []))
    cells.append(str(result["metrics"]["count"]) + (f" (+{failed} not scored: no ground plane)" if failed else ""))
    return ["| " + " | ".join(cells) + " |"]


def table_header(task: str) -> list[str]:
    headers = ["method", "data"] + [h for h, _, _ in COLUMNS[task]] + [COUNT_LABEL[task]]
    return ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]


def format_table(labelled: list[tuple[str, dict]]) -> str:
    """A markdown table of ``[(label, result), ...]`` of one task."""
    task = labelled[0][1]["task"]
    lines = table_header(task)
    for label, result in labelled:
        lines += table_rows(result, label)
    return "\n".join(lines)


def write_json(path, payload) -> None:
    text = json.dumps(json_safe(payload), indent=2, allow_nan=False)
    with atomic_write(Path(path)) as tmp:
        tmp.write_text(text + "\n")

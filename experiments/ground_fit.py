"""How well the camera-height ground fit recovers scale, on synthetic frames with exact depth.

    .venv/bin/python experiments/ground_fit.py --data data/synth_dense_dev [--data data/synth40:seq_0036,seq_0037]
        [--precision fp32] [--max-seen-through 1.0]

For each synthetic folder (``python -m training.synth``; the camera rides 1.65 m above the
road, ``training.synth.scene.CAM_HEIGHT``) it runs :func:`geonet_infer.core.scale.fit_ground_plane`
twice per frame: on the ground-truth depth (does the fitter find the road when the depth is
right?) and on the bundled model's prediction (the scale a user gets). Printed per folder:

* on ground truth: frames fitted, and how many of them put the road within 5 % of 1.65 m;
* on predictions: frames fitted, the median |log(fit scale / GT-median scale)| (0 = the
  fit agrees with the per-image median scaling of the evaluation protocol), and AbsRel with the
  fitted scale next to AbsRel with median scaling on the same frames.

``--max-seen-through 1.0`` turns off the check that skips a plane the image sees the road
through (a truck bed, a car roof), which reproduces the fitter before that check.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import geonet_infer  # noqa: E402
from geonet_infer.core.scale import fit_ground_plane  # noqa: E402
from geonet_infer.errors import GeoNetError  # noqa: E402
from geonet_infer.eval import metrics  # noqa: E402
from geonet_infer.eval.datasets import load_dataset  # noqa: E402
from geonet_infer.eval.evaluation import MAX_DEPTH, MIN_DEPTH, depth_intrinsics  # noqa: E402
from geonet_infer.io import read_image  # noqa: E402
from training.synth.scene import CAM_HEIGHT  # noqa: E402


def _height_or_nan(depth: np.ndarray, K: np.ndarray, **options) -> float:
    try:
        return fit_ground_plane(depth, K, **options).height
    except GeoNetError:
        return float("nan")


def score_folder(predictor, root: str, sequences: list[str] | None, **options) -> dict:
    data = load_dataset("depth", root, layout="synth", sequences=sequences)
    gt_heights, log_errors, fitted_absrel, median_absrel = [], [], [], []
    for item in data.items:
        rgb = read_image(item.image)
        gt = item.load_gt(rgb.shape[:2])
        K = depth_intrinsics(item, data.layout)
        gt_heights.append(_height_or_nan(np.where(gt > 0, gt, np.nan), K, **options))
        pred = metrics.resize_depth_to(predictor.depth(rgb).depth, gt.shape)
        height = _height_or_nan(pred, K, **options)
        if not np.isfinite(height):
            continue
        valid = (gt > MIN_DEPTH) & (gt < MAX_DEPTH)
        scale = CAM_HEIGHT / height
        log_errors.append(abs(np.log(scale * np.median(pred[valid]) / np.median(gt[valid]))))
        args = (gt, pred * scale, MIN_DEPTH, MAX_DEPTH)
        fitted_absrel.append(metrics.depth_metrics(*args, crop=None, median_scaling=False)["abs_rel"])
        median_absrel.append(metrics.depth_metrics(*args, crop=None, median_scaling=True)["abs_rel"])
    gt_heights = np.array(gt_heights)
    return {
        "frames": len(data.items),
        "gt_fitted": int(np.isfinite(gt_heights).sum()),
        "gt_within_5pct": int((np.abs(gt_heights / CAM_HEIGHT - 1) < 0.05).sum()),
        "pred_fitted": len(log_errors),
        "median_abs_log_scale_error": float(np.median(log_errors)) if log_errors else float("nan"),
        "absrel_fitted": float(np.mean(fitted_absrel)) if fitted_absrel else float("nan"),
        "absrel_median_same_frames": float(np.mean(median_absrel)) if median_absrel else float("nan"),
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument(
        "--data", action="append", required=True, help="a training.synth folder, optionally :SEQ,SEQ (repeatable)"
    )
    p.add_argument("--precision", default="fp32", choices=("fp32", "int8"))
    p.add_argument("--max-seen-through", type=float, default=None, help="fit_ground_plane's max_seen_through")
    args = p.parse_args(argv)
    options = {} if args.max_seen_through is None else {"max_seen_through": args.max_seen_through}
    predictor = geonet_infer.load(precision=args.precision, threads=2)
    print(
        "| data | frames | GT: fitted / within 5 % of 1.65 m | prediction: fitted | median abs log scale error "
        "| AbsRel, fitted scale / median scaling |"
    )
    print("|---|---|---|---|---|---|")
    for spec in args.data:
        root, _, listed = spec.partition(":")
        r = score_folder(predictor, root, listed.split(",") if listed else None, **options)
        print(
            f"| {spec} | {r['frames']} | {r['gt_fitted']} / {r['gt_within_5pct']} "
            f"| {r['pred_fitted']} | {r['median_abs_log_scale_error']:.3f} "
            f"| {r['absrel_fitted']:.3f} / {r['absrel_median_same_frames']:.3f} |"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

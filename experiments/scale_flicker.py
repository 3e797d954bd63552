"""Metric-scale flicker before and after smoothing, and metric depth AbsRel on the KITTI drive.

    python experiments/scale_flicker.py [--data ../shared/realdata] [--out docs/scale_flicker.json]
        [--dashcam-height 1.2] [--precision fp32]

Per sequence, the bundled model's depth runs through ``Predictor.iter_sequence`` with a camera
height, as ``geonet-infer predict --camera-height`` does:

* KITTI raw drive ``kitti_raw_2011_09_26_sfnd`` (78 frames, its own calibration, 1.65 m, KITTI's
  documented mounting height);
* Udacity dashcam ``udacity_dashcam/test_video.mp4`` (38 frames, ``calib_advanced_lane_lines.txt``)
  at ``--dashcam-height`` (unknown for this car; the flicker, a ratio, does not depend on it).

"before" is the factor each frame got before smoothing (its own ground fit; a frame without one
keeps the previous frame's: ``--scale-smoothing 0``), "after" the smoothed factor predict applies
now (``geonet_infer.core.scale.SCALE_HALF_WINDOW`` frames each side). Flicker = the p95 over consecutive
frames of max(r, 1/r), r = the ratio of their factors (:func:`geonet_infer.core.scale.scale_flicker`).
Depth: AbsRel (and the other Eigen metrics) of the *metric* depth, no per-image median scaling,
on the drive's Velodyne frames 0-9, scored by :func:`geonet_infer.eval.evaluation.evaluate_depth`
(``scaling="none"``, Garg crop, 80 m), each frame with the factor the whole-drive run gave it.
Beside them, ``geonet-infer eval depth --scaling camera_height`` (each frame's own fit, scored by
the eval) as a cross-check of "before". Prints a table and writes the JSON.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import geonet_infer  # noqa: E402
from geonet_infer.core.scale import SCALE_HALF_WINDOW, scale_flicker, smooth_scales  # noqa: E402
from geonet_infer.eval import evaluation  # noqa: E402
from geonet_infer.eval.datasets import load_dataset  # noqa: E402
from geonet_infer.io.calib import read_camera  # noqa: E402
from geonet_infer.io.frames import open_frames  # noqa: E402

KITTI_HEIGHT_M = 1.65
DRIVE = "kitti_raw_2011_09_26_sfnd"
DASHCAM = "udacity_dashcam/test_video.mp4"
DASHCAM_CALIB = "udacity_dashcam/calib_advanced_lane_lines.txt"


def run_sequence(predictor, path: Path, calib: Path, height: float) -> dict:
    """Each frame's name, raw fit, factor before smoothing, smoothed factor, and smoothed metric depth."""
    source = open_frames(path)
    camera = read_camera(calib)
    names, raw, after, depth = [], [], [], {}
    frames = (f.rgb for f in source)  # these inputs have no bad frames; predict would skip and record one
    for r in predictor.iter_sequence(frames, camera, tasks=("depth",), camera_height=height, names=source.frame_names):
        names.append(r.name)
        raw.append(r.metric_scale_raw)
        after.append(r.metric_scale)
        depth[r.name] = r.depth
    before = smooth_scales(raw, 0)  # window 0: each frame's own fit, a gap keeps the previous one
    return {
        "path": str(path),
        "camera_height_m": height,
        "frames": len(names),
        "frames_without_fit": sum(v is None for v in raw),
        "flicker_p95": {"before": scale_flicker(before), "after": scale_flicker(after)},
        "flicker_max": {"before": scale_flicker(before, 100), "after": scale_flicker(after, 100)},
        "per_frame": {"frames": names, "raw": raw, "before": before, "after": after},
        "_depth": depth,
    }


def depth_scores(seq: dict, drive: Path) -> dict:
    """Metric-depth metrics on the drive's ground-truth frames with the factors before and after."""
    dataset = load_dataset("depth", drive, "kitti-raw")
    factors = dict(zip(seq["per_frame"]["frames"], zip(seq["per_frame"]["before"], seq["per_frame"]["after"])))
    out = {"frames": [item.name for item in dataset.items]}
    for which, k in (("before", 0), ("after", 1)):
        depths = iter(
            [seq["_depth"][item.name] * factors[item.name][k] / factors[item.name][1] for item in dataset.items]
        )
        result = evaluation.evaluate_depth(lambda rgb, d=depths: next(d), dataset, method=which, scaling="none")
        out[which] = result["metrics"]
        out[f"{which}_per_frame_abs_rel"] = [row["abs_rel"] for row in result["items"]]
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=Path("../shared/realdata"))
    parser.add_argument("--out", type=Path, default=Path("docs/scale_flicker.json"))
    parser.add_argument("--dashcam-height", type=float, default=1.2, help="metres (default: 1.2)")
    parser.add_argument("--precision", default="fp32")
    args = parser.parse_args(argv)
    predictor = geonet_infer.load(precision=args.precision)
    drive = args.data / DRIVE
    kitti = run_sequence(predictor, drive, drive / "calib_cam_to_cam.txt", KITTI_HEIGHT_M)
    dash = run_sequence(predictor, args.data / DASHCAM, args.data / DASHCAM_CALIB, args.dashcam_height)
    depth = depth_scores(kitti, drive)
    per_frame_eval = evaluation.evaluate_depth(
        evaluation.model_depth_fn(predictor),
        load_dataset("depth", drive, "kitti-raw"),
        scaling="camera_height",
        camera_height=KITTI_HEIGHT_M,
    )
    depth["eval_camera_height_per_frame"] = per_frame_eval["metrics"]
    depth["eval_camera_height_fit_failed"] = per_frame_eval["ground_fit_failed"]
    result = {
        "command": " ".join(["python experiments/scale_flicker.py", *(argv if argv is not None else sys.argv[1:])]),
        "model": str(predictor.model_dir.name),
        "precision": args.precision,
        "smoothing_half_window": SCALE_HALF_WINDOW,
        "sequences": {
            "kitti_drive": {k: v for k, v in kitti.items() if k != "_depth"},
            "dashcam": {k: v for k, v in dash.items() if k != "_depth"},
        },
        "kitti_depth_metric": depth,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print("| sequence | frames | camera height | flicker p95 before | after | max before | after |")
    print("|---|---|---|---|---|---|---|")
    for label, seq in (("KITTI drive", kitti), ("dashcam test_video", dash)):
        p95, top = seq["flicker_p95"], seq["flicker_max"]
        print(
            f"| {label} | {seq['frames']} | {seq['camera_height_m']:g} m | {p95['before']:.3f} | {p95['after']:.3f} "
            f"| {top['before']:.3f} | {top['after']:.3f} |"
        )
    print()
    print("| KITTI drive frames 0-9, metric depth | AbsRel | SqRel | RMSE | δ<1.25 |")
    print("|---|---|---|---|---|")
    rows = (("before (each frame's own fit)", depth["before"]), ("after (smoothed)", depth["after"]))
    rows += (("eval depth --scaling camera_height", depth["eval_camera_height_per_frame"]),)
    for label, m in rows:
        print(f"| {label} | {m['abs_rel']:.3f} | {m['sq_rel']:.3f} | {m['rmse']:.3f} | {m['a1']:.3f} |")
    print(f"\nwrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

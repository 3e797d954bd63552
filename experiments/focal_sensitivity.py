"""The focal length of real footage (issue 58), two tables for docs/intrinsics.md:

* ``--estimates``: ``--intrinsics estimate`` on every calibrated real set in ../shared against its
  calibrated focal: the estimate or the refusal, and the time taken;
* what a wrong focal length costs: the calibrated K of a clip scaled by 1 + e, for e in -50 %..+50 %,
  and what changes: the rigid flow's warp error and the output check (rigid flow no better than no
  motion), and ORB-VO's poses against the poses it gives with the calibrated K.

    python -m experiments.focal_sensitivity --json docs/focal_sensitivity.json --markdown -
    python -m experiments.focal_sensitivity --estimates --json docs/focal_estimates.json --markdown -

The clips: the KITTI raw drive in ../shared (P_rect_02) and the calibrated Udacity dashcam clip (its
distortion removed as --calib does). The rigid flow comes from the bundled model's depth and pose and K,
so its error is the model's too; ORB-VO's depend on K alone (its step lengths come from the depth).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

import geonet_infer
from geonet_infer.io import read_camera
from geonet_infer.io.camera import Camera
from geonet_infer.io.frames import open_frames

ERRORS = (-0.5, -0.25, -0.1, 0.0, 0.1, 0.25, 0.5)
REALDATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "realdata"
CLIPS = {  # name -> (input, its calibration, frames used)
    "KITTI raw drive (1242x375, fx 721.5)": (
        "kitti_raw_2011_09_26_sfnd", "kitti_raw_2011_09_26_sfnd/calib_cam_to_cam.txt", 78,
    ),
    "Udacity dashcam test_video (1280x720, fx 1159)": (
        "udacity_dashcam/test_video.mp4", "udacity_dashcam/calib_advanced_lane_lines.txt", 80,
    ),
}  # fmt: skip


def scaled(camera: Camera, factor: float) -> Camera:
    K = camera.K.copy()
    K[0, 0] *= factor
    K[1, 1] *= factor
    return Camera(K, camera.dist, camera.size, f"{camera.source} x{factor:g}", "flag")


def angle_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))))


def pose_deviation(steps: list[np.ndarray], reference: list[np.ndarray]) -> dict:
    """Median over the steps of the rotation between each step and the reference's (degrees), and of
    the angle between their translation directions (degrees; steps that barely move left out)."""
    rot, direction = [], []
    for a, b in zip(steps, reference):
        rot.append(angle_deg(a[:3, :3] @ b[:3, :3].T))
        ta, tb = a[:3, 3], b[:3, 3]
        if np.linalg.norm(ta) > 1e-9 and np.linalg.norm(tb) > 1e-9:
            cos = float(ta @ tb / np.linalg.norm(ta) / np.linalg.norm(tb))
            direction.append(float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))))
    return {
        "rotation_deg": float(np.median(rot)),
        "direction_deg": float(np.median(direction)) if direction else None,
    }


def run_clip(predictor, frames: list, camera: Camera) -> list[dict]:
    rows, reference = [], None
    for e in sorted(ERRORS, key=lambda v: v != 0.0):  # the calibrated K first: the poses' reference
        cam = scaled(camera, 1 + e)
        seq = predictor.predict_sequence(frames, cam)
        check = seq.check
        orb = predictor.predict_sequence(frames, cam, pose_method="orbvo", flow_method="dis", check=False)
        steps = [f.pose_to_next for f in orb.frames[:-1]]
        if reference is None:
            reference = steps
        rows.append(
            {
                "focal_error": e,
                "pairs": check.pairs,
                "rigid_no_better": check.rigid_no_better,
                "median_rigid_error": check.median_rigid_error,
                "median_still_error": check.median_still_error,
                "orbvo_vs_calibrated": pose_deviation(steps, reference),
            }
        )
    return sorted(rows, key=lambda r: r["focal_error"])


def markdown(results: dict) -> str:
    lines = [
        "| clip | focal error | rigid flow no better than no motion | median rigid warp error (no motion) "
        "| ORB-VO step rotation vs calibrated, median ° | ORB-VO direction vs calibrated, median ° |",
        "|---|---|---|---|---|---|",
    ]
    for clip, rows in results.items():
        for r in rows:
            o = r["orbvo_vs_calibrated"]
            direction = "–" if o["direction_deg"] is None else f"{o['direction_deg']:.2f}"
            lines.append(
                f"| {clip} | {r['focal_error']:+.0%} | {r['rigid_no_better']} of {r['pairs']} | "
                f"{r['median_rigid_error']:.2f} ({r['median_still_error']:.2f}) | "
                f"{o['rotation_deg']:.3f} | {direction} |"
            )
    return "\n".join(lines)


# set -> (frames, calibrated fx at the frames' size, where that value is written)
ESTIMATE_SETS = {
    "KITTI raw drive (78 frames)": ("kitti_raw_2011_09_26_sfnd", 721.5377, "calib_cam_to_cam.txt P_rect_02"),
    "KITTI odometry 00 (6 frames)": ("kitti_odometry_00/sequences/00", 718.856, "calib.txt P0"),
    "KITTI odometry 01 (51 frames, motorway)": ("kitti_odometry_01/sequences/01", 718.856, "calib.txt P0"),
    "KITTI odometry 06 (51 frames)": ("kitti_odometry_06/sequences/06", 707.0912, "calib.txt P0"),
    "KITTI 2015 flow pair 000010": ("kitti2015_flow_000010/training/image_2", None, "no file (KITTI: 707-722)"),
    "KITTI object, 3 single frames": ("kitti_object_3frames/training/image_2", 721.5377, "calib/000000.txt P2"),
    "EuRoC V1_01 micro (20 frames, still)": ("euroc_v1_01_micro", 458.654, "mav0/cam0/sensor.yaml"),
    "RGB-D slambook (5 sparse views)": ("rgbd_kinect_slambook/color", 518.0, "its README (the book)"),
    "Udacity dashcam test_video (38 frames)": (
        "udacity_dashcam/test_video.mp4", 1158.774754, "calib_advanced_lane_lines.txt",
    ),
}  # fmt: skip


def estimates(data: Path) -> list[dict]:
    from geonet_infer.core.self_calibration import MAX_FRAMES, estimate_focal

    rows = []
    for name, (inp, fx, where) in ESTIMATE_SETS.items():
        source = open_frames(data / inp)
        e = estimate_focal(f.rgb for _, f in zip(range(MAX_FRAMES), source) if f.ok)
        rows.append(
            {
                "set": name,
                "calibrated_fx": fx,
                "calibration": where,
                "estimate": e.focal,
                "error": None if e.focal is None or fx is None else e.focal / fx - 1,
                "refusal": e.reason or None,
                "pairs": e.pairs,
                "pairs_tried": e.pairs_tried,
                "seconds": e.seconds,
            }
        )
    return rows


def estimates_markdown(rows: list[dict]) -> str:
    lines = ["| set | calibrated fx (where) | `--intrinsics estimate` | time |", "|---|---|---|---|"]
    for r in rows:
        fx = "–" if r["calibrated_fx"] is None else f"{r['calibrated_fx']:g}"
        said = (
            f"refused: {r['refusal']}"
            if r["estimate"] is None
            else f"{r['estimate']:.1f} ({r['error']:+.1%}, {r['pairs']} pairs)"
        )
        lines.append(f"| {r['set']} | {fx} ({r['calibration']}) | {said} | {r['seconds']:.1f} s |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=REALDATA)
    parser.add_argument("--json", type=Path)
    parser.add_argument("--markdown", help="'-' for stdout, or a file")
    parser.add_argument("--estimates", action="store_true", help="the estimates table instead")
    args = parser.parse_args(argv)
    if args.estimates:
        rows = estimates(args.data)
        if args.json:
            args.json.write_text(json.dumps({"estimates": rows}, indent=1) + "\n")
        if args.markdown:
            text = estimates_markdown(rows)
            print(text) if args.markdown == "-" else Path(args.markdown).write_text(text + "\n")
        return 0
    predictor = geonet_infer.load()
    results = {}
    for clip, (inp, calib, n) in CLIPS.items():
        source = open_frames(args.data / inp)
        frames = [f.rgb for _, f in zip(range(n), source) if f.ok]
        results[clip] = run_clip(predictor, frames, read_camera(args.data / calib))
        print(f"{clip}: done", file=sys.stderr)
    if args.json:
        args.json.write_text(json.dumps({"model": "small_synth", "clips": results}, indent=1) + "\n")
    if args.markdown:
        text = markdown(results)
        print(text) if args.markdown == "-" else Path(args.markdown).write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

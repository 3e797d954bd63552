"""The triangulated depth teacher (``training.prepare --teacher-depth triangulate``) against stereo.

An independent yardstick: OpenCV SGBM depth from each frame's right camera
(:mod:`geonet_infer.eval.stereo`, the real validation depth of ``python -m benchmarks.eval_all``), on KITTI
odometry 00 frame 0 and 06 frame 12 (validation frames: measured here, never trained on). The
teacher has no metric scale, so its depth is scaled per image to SGBM's median over the pixels
both have. Printed per frame and motion (the teacher's, from the flow; two-view ORB-VO for
comparison): coverage (fraction of pixels labelled), overlap with SGBM, AbsRel, and the AbsRel of
a constant depth (SGBM's median) on the same pixels::

    python -m experiments.teacher_depth_check [--realdata ../shared/realdata]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from geonet_infer.eval.stereo import focal_and_baseline, stereo_depth
from geonet_infer.io import read_calib_K, read_image
from training.teachers import flow_motion, teacher_flow, teacher_motion, triangulate_depth

# (sequence folder, target frame): grey left camera image_0 (P0), right camera image_1 (P1)
FRAMES = (("kitti_odometry_00/sequences/00", 0), ("kitti_odometry_06/sequences/06", 12))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--realdata", type=Path, default=Path("../shared/realdata"))
    args = parser.parse_args(argv)
    for folder, n in FRAMES:
        seq = args.realdata / folder
        target, following = (read_image(seq / "image_0" / f"{k:06d}.png") for k in (n, n + 1))
        K = read_calib_K(seq / "calib.txt", "P0")
        fx, baseline = focal_and_baseline(seq / "calib.txt", "P0", "P1")
        stereo = stereo_depth(target, read_image(seq / "image_1" / f"{n:06d}.png"), fx, baseline)
        flow = teacher_flow(target, following)
        orb = teacher_motion([target, following], K, 0)
        motions = {"flow": flow_motion(flow, K), "orbvo": None if orb is None else orb[0]}
        print(
            f"{folder} frame {n}: SGBM covers {np.mean(stereo > 0):.3f}, "
            f"forward-backward valid {flow.valid_fraction:.3f}"
        )
        for name, motion in motions.items():
            if motion is None:
                print(f"  motion {name}: failed")
                continue
            label = triangulate_depth(flow.flow, flow.valid, motion, K)
            both = label.valid & (stereo > 0)
            truth = stereo[both]
            scaled = label.depth[both] * np.median(truth) / np.median(label.depth[both])
            abs_rel = np.mean(np.abs(scaled - truth) / truth)
            constant = np.mean(np.abs(np.median(truth) - truth) / truth)
            print(
                f"  motion {name:5s}: coverage {label.valid_fraction:.3f}, with SGBM {both.mean():.3f}, "
                f"AbsRel {abs_rel:.3f} (constant depth {constant:.3f}), t = {np.round(motion[:3, 3], 3)}"
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

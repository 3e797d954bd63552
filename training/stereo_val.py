"""Real validation depth from rectified KITTI stereo pairs (OpenCV SGBM), outside the test drive.

``python -m training.stereo_val --out data/kitti_stereo_val`` writes the stereo pairs of
``../shared/realdata/kitti_odometry_{00,06}`` as a KITTI-raw layout folder that
``python -m training.evaluate --data data/kitti_stereo_val`` and ``geonet-infer eval depth`` read:
``image_02/data/<name>.png`` (the left image) and ``proj_depth/groundtruth/image_02/<name>.png``
(depth in KITTI's 1/256 m PNG, 0 = no value).

Why: the only real Velodyne depth of a whole drive in ../shared is the test drive
(``kitti_raw_2011_09_26_sfnd``), and recipes must not be chosen on it. These two frames come
from two other KITTI drives (odometry sequences 00 and 06). Their depth is OpenCV's
semi-global matching, kept only where the left and right disparities agree within one pixel:
``depth = fx * baseline / disparity``, with fx and the baseline read from the sequence's
``calib.txt`` projection matrices. It is a noisy yardstick (two frames, SGBM errors at
occlusions and on thin poles), fit for comparing recipes, not for publishing.
``python -m benchmarks.eval_all`` scores these frames with the other real depth outside the test drive
(the real validation figure); the matcher lives in :mod:`geonet_infer.eval.stereo`, which both use.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from geonet_infer.errors import GeoNetError
from geonet_infer.eval.stereo import (  # noqa: F401  (re-exported: the names this module always had)
    BLOCK,
    LR_TOLERANCE,
    MAX_DISPARITY,
    PAIRS,
    StereoPair,
    build,
    focal_and_baseline,
    sgbm_disparity,
    stereo_depth,
)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m training.stereo_val", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--realdata", type=Path, default=Path("../shared/realdata"), help="folder of the real extracts")
    p.add_argument("--out", type=Path, required=True, help="output folder (KITTI raw layout)")
    args = p.parse_args(argv)
    try:
        rows = build(args.realdata, args.out)
    except GeoNetError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    for r in rows:
        print(
            f"{r['name']}: {r['source']}, fx {r['fx']:.1f} px, baseline {r['baseline_m']:.3f} m, "
            f"{100 * r['valid_fraction']:.0f}% pixels with depth, median {r['median_depth_m']:.1f} m"
        )
    print(f"wrote {len(rows)} frames to {args.out}; score with: python -m training.evaluate --data {args.out} ...")
    return 0


if __name__ == "__main__":
    sys.exit(main())

#!/usr/bin/env bash
# The real KITTI odometry frames that fine-tuning may use, linked into a dev-kit layout that
# `training.prepare --kind kitti_odom` reads (grey image_0 + calib.txt, poses/ beside sequences/):
# sequence 06 frames 31-50 and 01 frames 0-30. Sequence 00 and 06's frames 0-30 are held out: they
# hold the stereo-SGBM validation frames and the snippets the pose rules are judged on.
#   bash scripts/link_real_odom.sh [REALDATA (../shared/realdata)] [OUT (data/real_odom_src)]
set -euo pipefail
cd "$(dirname "$0")/.."
REALDATA=${1:-../shared/realdata} ODOM_SRC=${2:-data/real_odom_src}
for spec in "06 31 50" "01 0 30"; do
    read -r seq first last <<<"$spec"
    dst=$ODOM_SRC/sequences/$seq
    mkdir -p "$dst/image_0" "$ODOM_SRC/poses"
    ln -sf "$(realpath "$REALDATA/kitti_odometry_$seq/sequences/$seq/calib.txt")" "$dst/calib.txt"
    ln -sf "$(realpath "$REALDATA/kitti_odometry_$seq/poses/$seq.txt")" "$ODOM_SRC/poses/$seq.txt"
    for i in $(seq "$first" "$last"); do
        f=$(printf '%06d.png' "$i")
        ln -sf "$(realpath "$REALDATA/kitti_odometry_$seq/sequences/$seq/image_0/$f")" "$dst/image_0/$f"
    done
done

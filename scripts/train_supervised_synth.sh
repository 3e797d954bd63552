#!/usr/bin/env bash
# The transfer experiments of docs/training.md ("Toward real video: what was measured"), on a
# 2-core CPU: depth-supervised synthetic pre-training with real dashcam clips mixed into the
# batches, then dense traffic added, each scored on the synthetic held-out sequences and on the
# real KITTI test frames 0-9 (never trained on).
#   bash scripts/train_supervised_synth.sh      # about 100 minutes after the reference rigid run
# Starts from the stage-rigid run of scripts/build_bundled_model.sh (runs/small_rigid/last.pt;
# INIT overrides). Environment: SUP_MINUTES (62), DENSE_MINUTES (30) cap the two stages;
# THREADS (2) torch threads.
set -euo pipefail
cd "$(dirname "$0")/.."
SUP_MINUTES=${SUP_MINUTES:-62} DENSE_MINUTES=${DENSE_MINUTES:-30} INIT=${INIT:-runs/small_rigid/last.pt}
export OMP_NUM_THREADS=${THREADS:-2}
PY=.venv/bin/python
[ -x "$PY" ] || { python3 -m venv .venv && $PY -m pip install --quiet -e '.[train,dev]'; }
run() { echo "+ $*"; "$@"; }
DATA=data/synth40 PREP=data/synth40_depth DENSE=data/synth_dense DENSE_PREP=data/synth_dense_depth
REAL=data/udacity CLIPS=../shared/realdata/udacity_dashcam KITTI=../shared/realdata/kitti_raw_2011_09_26_sfnd
[ -f "$INIT" ] || { echo "no $INIT: run scripts/build_bundled_model.sh (its stage rigid) first, or set INIT" >&2; exit 2; }

# data: light and dense synthetic traffic with their depth, and the four calibrated Udacity clips
[ -f "$DATA/seq_0039/poses.txt" ] || run $PY -m training.synth --out $DATA --sequences 40 --frames 40 --seed 2026 --workers 2
[ -f "$PREP/heldout.txt" ] || run $PY -m training.prepare --kind synth --src $DATA --out $PREP --heldout 4 --workers 2 --train-depth
[ -f "$DENSE/seq_0023/poses.txt" ] || run $PY -m training.synth --out $DENSE --sequences 24 --frames 40 --seed 2027 \
    --traffic dense --workers 2
[ -f "$DENSE_PREP/heldout.txt" ] || run $PY -m training.prepare --kind synth --src $DENSE --out $DENSE_PREP --heldout 2 \
    --workers 2 --train-depth
if [ ! -f "$REAL/train.txt" ]; then  # the calibrated 1280x720 clips only (the 960x540 ones have a guessed camera)
    mkdir -p data/udacity_clips
    for c in challenge project_video_clip_a project_video_clip_b test_video; do
        ln -sf "$(realpath $CLIPS/$c.mp4)" data/udacity_clips/$c.mp4
    done
    run $PY -m training.prepare --kind video --src data/udacity_clips --calib $CLIPS/calib_advanced_lane_lines.txt \
        --crop 0,229,1280,394 --out $REAL
fi

common=(--stage rigid --arch small --bn-momentum 0.01 --num-workers 0 --mask-out-of-view --automask
        --depth-supervision 1 --val-every 250 --save-every 250 --log-every 25)
# B: light traffic, supervised, with the real clips in the batches (self-supervised only: no depth)
run $PY -m training.train "${common[@]}" --data-dir $PREP --extra-data-dir $REAL --out-dir runs/sup_mixed \
    --init-checkpoint "$INIT" --max-steps 4000 --max-minutes "$SUP_MINUTES"
# C: dense traffic added
run $PY -m training.train "${common[@]}" --data-dir $DENSE_PREP --extra-data-dir $PREP --extra-data-dir $REAL \
    --out-dir runs/sup_dense --init-checkpoint runs/sup_mixed/last.pt --max-steps 5000 --max-minutes "$DENSE_MINUTES"

for r in runs/sup_mixed runs/sup_dense; do
    run $PY -m training.evaluate --checkpoint $r/last.pt --data $DATA --heldout $PREP/heldout.txt --task depth
    run $PY -m training.evaluate --checkpoint $r/last.pt --data $KITTI --task depth
done

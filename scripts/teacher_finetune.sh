#!/usr/bin/env bash
# Issue 46: fine-tune the bundled ResFlowNet on real footage labelled by a classical teacher (OpenCV DIS
# flow, forward-backward checked), beside GeoNet's own flow losses; export the candidate and score it with
# `python -m benchmarks.eval_all` and the held-back clip (experiments/teacher_experiment.py applies the shipping
# rule written before scoring, docs/models.md "Classical-teacher experiment").
#
#   bash scripts/teacher_finetune.sh                      prepare + train (CPU) + export + score
#   STEPS=3000 DEVICE=cuda NUM_WORKERS=6 bash scripts/teacher_finetune.sh train     one step of it
#
# Steps (each skips what is already there): prepare | train | finish (combine, export, score); none = all.
# Training footage (never the test drive kitti_raw_2011_09_26_sfnd, nor any scored frame), listed by
# prepare in data/t_*/train.txt:
#   * three calibrated 1280x720 Udacity clips: challenge, project_video_clip_a, project_video_clip_b
#     (test_video.mp4, the fourth calibrated clip, is held back: the rule's real flow validation);
#   * the two 960x540 Udacity clips with their GUESSED intrinsics (solidWhiteRight, solidYellowLeft): the
#     guess only shapes the rigid-flow input, the DIS label does not depend on it;
#   * grey KITTI odometry 06 frames 31-50 and 01 frames 0-30 (as the real-pose experiment: no yardstick's).
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PY:-.venv/bin/python}
STEPS=${STEPS:-600} MINUTES=${MINUTES:-100} DEVICE=${DEVICE:-auto} NUM_WORKERS=${NUM_WORKERS:-1}
FLOW_SUPERVISION=${FLOW_SUPERVISION:-1} LR=${LR:-2e-4} BATCH=${BATCH:-4}
OUT=${OUT:-runs/teacher_flow} INIT=${INIT:-weights/small_synth.pt} INT8_OPS=${INT8_OPS:-Conv,Relu,Add,MaxPool}
REALDATA=${REALDATA:-../shared/realdata} CLIPS=${CLIPS:-../shared/realdata/udacity_dashcam}
STEP=${1:-all}
run() { echo "+ $*"; "$@"; }
want() { [ "$STEP" = all ] || [ "$STEP" = "$1" ]; }
mkdir -p "$OUT" data

if want prepare; then
    mkdir -p data/t_clips data/t_clips_guess data/t_holdback
    for c in challenge project_video_clip_a project_video_clip_b; do ln -sf "$(realpath "$CLIPS/$c.mp4")" data/t_clips/; done
    for c in solidWhiteRight solidYellowLeft; do ln -sf "$(realpath "$CLIPS/$c.mp4")" data/t_clips_guess/; done
    ln -sf "$(realpath "$CLIPS/test_video.mp4")" data/t_holdback/
    [ -f data/t_udacity/train.txt ] || run $PY -m training.prepare --kind video --src data/t_clips \
        --calib "$CLIPS/calib_advanced_lane_lines.txt" --crop 0,229,1280,394 --out data/t_udacity \
        --teacher-flow dis --val-fraction 0
    [ -f data/t_udacity_guess/train.txt ] || run $PY -m training.prepare --kind video --src data/t_clips_guess \
        --calib "$CLIPS/intrinsics_960x540_GUESS_UNVERIFIED.txt" --crop 0,215,960,295 --out data/t_udacity_guess \
        --teacher-flow dis --val-fraction 0
    [ -f data/t_holdback_prepared/train.txt ] || run $PY -m training.prepare --kind video --src data/t_holdback \
        --calib "$CLIPS/calib_advanced_lane_lines.txt" --crop 0,229,1280,394 --out data/t_holdback_prepared \
        --teacher-flow dis --val-fraction 0
    ODOM_SRC=data/real_odom_src  # the real-pose experiment's frames
    [ -f data/t_odom/train.txt ] || bash scripts/link_real_odom.sh "$REALDATA" "$ODOM_SRC"
    [ -f data/t_odom/train.txt ] || run $PY -m training.prepare --kind kitti_odom --src $ODOM_SRC \
        --out data/t_odom --seq-length 3 --val-fraction 0 --teacher-flow dis
fi

if want train; then
    run $PY -m training.train --stage flow --arch small --device "$DEVICE" --num-workers "$NUM_WORKERS" \
        --data-dir data/t_udacity --extra-data-dir data/t_udacity_guess --extra-data-dir data/t_odom \
        --init-checkpoint "$INIT" --out-dir "$OUT/flow" --flow-supervision "$FLOW_SUPERVISION" --lr "$LR" \
        --batch-size "$BATCH" --max-steps "$STEPS" --max-minutes "$MINUTES" --val-every 1000000 \
        --save-every 200 --log-every 20
fi

if want finish; then
    # the flow stage froze DepthNet/PoseNet: its checkpoint holds the whole model
    if [ "${COMBINED:-}" = ready ]; then  # made by the caller (stop round 22)
        echo "+ using $OUT/combined.pt as it is"
    elif [ -n "${RECALIBRATE:-}" ]; then  # the weights with their batch-norm statistics recomputed (stop round 21)
        run $PY -m training.recalibrate "$OUT/flow/last.pt" "$OUT/combined.pt" --batches "$RECALIBRATE"
    else
        run $PY -m training.checkpoint --weights-only "$OUT/flow/last.pt" "$OUT/combined.pt"
    fi
    run $PY -m export --checkpoint "$OUT/combined.pt" --out "$OUT/model" --force --precision fp32,int8 \
        --calib-data data/synth40/seq_0000/image --calib-method percentile --calib-frames 40 --int8-ops "$INT8_OPS"
    run $PY -m benchmarks.eval_all --data "$REALDATA" --model "$OUT/model" --json "$OUT/real_eval.json" \
        --markdown "$OUT/real_eval.md" || true  # exit 1 = a set missing or NaN: the JSON says which
fi

#!/usr/bin/env bash
# Adapt the bundled model to your own footage, self-supervised (no labels needed), and export it
# as a model directory that geonet_infer.load() and `geonet-infer --model` take.
#
#   bash scripts/adapt_to_clip.sh CLIP CALIB OUT [CROP]
#
# CLIP: a video file, a folder of videos, or a folder of frames; CALIB: its calibration (any
# format geonet_infer.io.read_camera reads; distortion is undone); OUT: working folder (the model
# ends up in OUT/model); CROP: optional X,Y,W,H kept after undistortion (cut the bonnet and sky).
# STEPS / FLOW_STEPS: fine-tuning steps of the two stages (default 300 / 100);
# PRECISION: fp32 or fp32,int8 (default; INT8 is calibrated on your own frames).
#
# Steps: prepare snippets -> fine-tune DepthNet+PoseNet from weights/small_synth.pt (stage rigid)
# -> put the published ResFlowNet on top -> fine-tune it (stage flow, depth/pose frozen) -> export.
set -euo pipefail
cd "$(dirname "$0")/.."
[ $# -ge 3 ] || { echo "usage: bash scripts/adapt_to_clip.sh CLIP CALIB OUT [X,Y,W,H]" >&2; exit 2; }
CLIP=$1 CALIB=$2 OUT=$3 CROP=${4:-}
STEPS=${STEPS:-300} FLOW_STEPS=${FLOW_STEPS:-100} PRECISION=${PRECISION:-fp32,int8}
WEIGHTS=${WEIGHTS:-weights/small_synth.pt}
PY=.venv/bin/python
if ! "$PY" -c "import torch" 2>/dev/null; then
    [ -x "$PY" ] || "${PYTHON:-python3}" -m venv .venv
    "$PY" -m pip install --quiet -e '.[train]'
fi
kind=video; [ -d "$CLIP" ] && ! ls "$CLIP" | grep -qiE '\.(mp4|avi|mov|mkv|webm)$' && kind=frames
common=(--arch small --bn-momentum 0.01 --num-workers 0 --mask-out-of-view --automask --lr 1e-4
        --val-every 1000000 --save-every 100)
run() { echo "+ $*"; "$@"; }
run "$PY" -m training.prepare --kind "$kind" --src "$CLIP" --calib "$CALIB" ${CROP:+--crop "$CROP"} \
    --out "$OUT/data" --val-fraction 0
run "$PY" -m training.train --stage rigid "${common[@]}" --data-dir "$OUT/data" --out-dir "$OUT/rigid" \
    --init-checkpoint "$WEIGHTS" --max-steps "$STEPS"
run "$PY" -m training.checkpoint --combine "$OUT/rigid/last.pt" "$WEIGHTS" "$OUT/combined.pt"
run "$PY" -m training.train --stage flow "${common[@]}" --data-dir "$OUT/data" --out-dir "$OUT/flow" \
    --init-checkpoint "$OUT/combined.pt" --max-steps "$FLOW_STEPS"
calib=()  # INT8 is calibrated on the first of your own (prepared) sequences
if [[ $PRECISION == *int8* ]]; then
    calib=(--calib-data "$(find "$OUT/data/.frames" -name '*.png' | head -n 1 | xargs dirname)")
fi
run "$PY" -m export --checkpoint "$OUT/flow/last.pt" --out "$OUT/model" --force --precision "$PRECISION" "${calib[@]}"
echo "done: geonet-infer predict $CLIP --out $OUT/pred --calib $CALIB --model $OUT/model"

#!/usr/bin/env bash
# After scripts/train_small_synth.sh: train the small ResFlowNet on top of the frozen rigid
# run (stage flow), score it, then export all four graphs in fp32 and INT8 and measure the
# INT8 accuracy delta on the held-out synthetic sequences (written into the manifest).
#   bash scripts/export_small_synth.sh     # outputs runs/small_flow, models/small_synth
# Environment overrides: STEPS (1500), MINUTES (15).
set -euo pipefail
cd "$(dirname "$0")/.."
STEPS=${STEPS:-1500}
MINUTES=${MINUTES:-15}
PY=.venv/bin/python
run() { echo "+ $*"; "$@"; }
run $PY -m training.train --stage flow --arch small --data-dir data/synth40_prepared --out-dir runs/small_flow \
    --init-checkpoint runs/small_rigid/last.pt --max-steps "$STEPS" --max-minutes "$MINUTES" \
    --bn-momentum 0.01 --num-workers 1 --val-every 250 --save-every 250 --log-every 25
run $PY -m training.evaluate --checkpoint runs/small_flow/last.pt --synth-dir data/synth40 \
    --prepared-dir data/synth40_prepared --task flow --stride 2 --out runs/small_flow/eval_flow.json
# calibrate INT8 on a training sequence (never a held-out one)
run $PY -m export --checkpoint runs/small_flow/last.pt --out models/small_synth --force \
    --precision fp32,int8 --calib-data data/synth40/seq_0000/image --calib-method percentile --calib-frames 40 \
    --eval-synth-dir data/synth40 --eval-prepared-dir data/synth40_prepared --eval-stride 2

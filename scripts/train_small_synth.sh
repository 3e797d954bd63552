#!/usr/bin/env bash
# Reproduce the reference run of the `small` GeoNet on synthetic data (stage rigid, then
# depth evaluation on the held-out sequences), within an hour on a 2-core CPU:
#   bash scripts/train_small_synth.sh            # outputs under data/synth40, runs/small_rigid
# Environment overrides: STEPS (6000), MINUTES (50, a wall-clock cap on training), OUT (runs/small_rigid).
# --mask-out-of-view and --automask are documented deviations from the official loss (see docs/results.md).
set -euo pipefail
cd "$(dirname "$0")/.."
STEPS=${STEPS:-6000}
MINUTES=${MINUTES:-50}
OUT=${OUT:-runs/small_rigid}
PY=.venv/bin/python
[ -x "$PY" ] || { python3 -m venv .venv && .venv/bin/python -m pip install --quiet -e '.[train,dev]'; }
run() { echo "+ $*"; "$@"; }
run $PY -m training.synth --out data/synth40 --sequences 40 --frames 40 --seed 2026 --workers 2
run $PY -m training.prepare --kind synth --src data/synth40 --out data/synth40_prepared --heldout 4 --workers 2
run $PY -m training.train --stage rigid --arch small --data-dir data/synth40_prepared --out-dir "$OUT" \
    --max-steps "$STEPS" --max-minutes "$MINUTES" --bn-momentum 0.01 --mask-out-of-view --automask --num-workers 1 \
    --val-every 500 --save-every 500 --log-every 25
run $PY -m training.evaluate --checkpoint "$OUT/last.pt" --synth-dir data/synth40 \
    --prepared-dir data/synth40_prepared --task depth --out "$OUT/eval_depth.json"

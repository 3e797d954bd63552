#!/usr/bin/env bash
# The main job on a fresh machine with Python 3.11: set up, generate synthetic driving
# scenes, prepare them, train the small GeoNet (rigid stage), score it on the held-out
# sequences, and export ONNX graphs. `STEPS=5000 bash scripts/train_demo.sh` trains longer.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
STEPS=${STEPS:-300}
[ -x .venv/bin/python ] || "$PY" -m venv .venv
.venv/bin/python -m pip install --quiet --upgrade pip >/dev/null
.venv/bin/python -m pip install --quiet -e '.[train,dev]'
run() { echo "+ $*"; "$@"; }
run .venv/bin/python -m training.synth --out data/synth --sequences 8 --frames 24 --seed 0 --workers 2
run .venv/bin/python -m training.prepare --kind synth --src data/synth --out data/prepared --heldout 2 --workers 2
run .venv/bin/python -m training.train --stage rigid --arch small --data-dir data/prepared \
    --out-dir runs/demo_rigid --max-steps "$STEPS" --bn-momentum 0.01 --mask-out-of-view --automask --num-workers 1 \
    --val-every 100 --save-every 100
run .venv/bin/python -m training.evaluate --checkpoint runs/demo_rigid/last.pt --synth-dir data/synth \
    --prepared-dir data/prepared --task depth --out runs/demo_rigid/eval.json
run .venv/bin/python -m export --checkpoint runs/demo_rigid/last.pt --out models/demo_rigid --force \
    --graphs depthnet,posenet,rigidflow
echo "done: checkpoint runs/demo_rigid/last.pt, metrics runs/demo_rigid/eval.json, ONNX models/demo_rigid"

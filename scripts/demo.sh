#!/usr/bin/env bash
# The main job on a fresh machine with Python 3.11: install the runtime (onnxruntime, numpy,
# OpenCV, tqdm; no torch) into .venv and run `geonet-infer demo` on the bundled model and
# sample, then `geonet-infer predict` on the real KITTI extract if ../shared is beside the repo.
#   bash scripts/demo.sh            # outputs in geonet_demo/ (demo.png) and out/kitti/
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
[ -x .venv/bin/python ] || "$PY" -m venv .venv
.venv/bin/python -m pip install --quiet --upgrade pip >/dev/null
.venv/bin/python -m pip install --quiet -e .
run() { echo "+ $*"; "$@"; }
run .venv/bin/geonet-infer demo --out geonet_demo
KITTI=../shared/realdata/kitti_raw_2011_09_26_sfnd
if [ -d "$KITTI" ]; then
    run .venv/bin/geonet-infer predict "$KITTI" --out out/kitti
fi

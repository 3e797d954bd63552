#!/usr/bin/env bash
# The runtime alone, as users get it: a fresh venv with `pip install .` (no train extra, so
# no torch) and the runtime tests run against the INSTALLED package (bundled models and
# sample included as package data), not the source tree.
#   bash scripts/test_runtime.sh          # extra args go to pytest
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
VENV=${RUNTIME_VENV:-.venv-runtime}
rm -rf "$VENV" build
"$PY" -m venv "$VENV"
"$VENV/bin/python" -m pip install --quiet --upgrade pip >/dev/null
# onnx: the hostile-model tests write broken graphs with it, and it is the [convert] extra (INT8); hypothesis fuzzes
# the parsers. Test tools: the runtime imports neither.
"$VENV/bin/python" -m pip install --quiet . pytest pypng onnx hypothesis
rm -rf build
"$VENV/bin/python" -c "import importlib.util as u, sys; sys.exit(u.find_spec('torch') is not None)" \
    || { echo "torch is installed in the runtime venv: the runtime must not need it"; exit 1; }
# `pytest` (not `python -m pytest`) and an empty pythonpath keep the repo root off sys.path.
# tests/runtime mirrors geonet_infer/ (core, io, engines, output, batch, eval, bench, cli): every
# file there runs without torch (a test that needs the train extra skips itself).
exec env GEONET_RUNTIME_ONLY=1 "$VENV/bin/pytest" -q -o pythonpath= -p no:cacheprovider tests/runtime "$@"

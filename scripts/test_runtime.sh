#!/usr/bin/env bash
# The runtime alone, as users get it: a fresh venv with `pip install .` (no train extra, so
# no torch) and the runtime tests run against the INSTALLED package (bundled models and
# sample included as package data), not the source tree.
#   bash scripts/test_runtime.sh          # extra args go to one pytest run instead of the file-by-file run
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
VENV=${RUNTIME_VENV:-.venv-runtime}
rm -rf "$VENV" build
"$PY" -m venv "$VENV"
"$VENV/bin/python" -m pip install --quiet --upgrade pip >/dev/null
# onnx: the hostile-model tests write broken graphs with it, and it is the [convert] extra (INT8); hypothesis fuzzes
# the parsers; evo is the trajectory tests' yardstick. Test tools: the runtime imports none of them. The viz,
# openvino and ray extras: their tests run here (scripts/test.sh runs tests/runtime only here).
"$VENV/bin/python" -m pip install --quiet '.[viz,openvino,ray]' pytest pypng onnx hypothesis evo
rm -rf build
"$VENV/bin/python" -c "import importlib.util as u, sys; sys.exit(u.find_spec('torch') is not None)" \
    || { echo "torch is installed in the runtime venv: the runtime must not need it"; exit 1; }
# `pytest` (not `python -m pytest`) and an empty pythonpath keep the repo root off sys.path.
# tests/runtime mirrors geonet_infer/ (core, io, engines, output, batch, eval, bench, cli): every
# file there runs without torch (a test that needs the train extra skips itself).
if [ $# -gt 0 ]; then
    exec env GEONET_RUNTIME_ONLY=1 "$VENV/bin/pytest" -q -o pythonpath= -p no:cacheprovider "$@"
fi
# One process per file, two at a time, the slowest first (scripts/pytest_files.sh): CI's 20 minutes.
shopt -s globstar
slow=(tests/runtime/batch/test_batch.py tests/runtime/convert/test_convert.py tests/runtime/batch/test_hostile_batch.py
      tests/runtime/output/test_hostile_predict.py tests/runtime/cli/test_cli.py)
files=("${slow[@]}")
for f in tests/runtime/**/test_*.py; do
    [[ " ${slow[*]} " == *" $f "* ]] || files+=("$f")
done
export GEONET_RUNTIME_ONLY=1 PYTEST="$VENV/bin/pytest -q -o pythonpath= -p no:cacheprovider" NAME=scripts/test_runtime.sh
exec bash scripts/pytest_files.sh "${files[@]}"

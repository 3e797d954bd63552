#!/usr/bin/env bash
# Set up a virtual environment and run the whole test suite.
# Works on a fresh machine with Python 3.11: `bash scripts/test.sh` (extra args go to pytest).
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
[ -x .venv/bin/python ] || "$PY" -m venv .venv
.venv/bin/python -m pip install --quiet --upgrade pip >/dev/null
.venv/bin/python -m pip install --quiet -e '.[train,dev,ray,openvino,tf]'
# Lint and format first: cheap, and a failure names the file and line.
.venv/bin/ruff check .
.venv/bin/ruff format --check .
# The runtime's types ([tool.mypy] in pyproject.toml): geonet_infer/ ships py.typed, so users' checkers read them.
.venv/bin/mypy
# Every test, each once, the `slow` ones (> ~20 s on 2 cores) included (the quick run leaves them out:
# .venv/bin/python -m pytest -m "not slow"). Without arguments:
#   1. the tests outside tests/runtime (training, export, benchmarks, experiments, the README), one pytest
#      process per file, two at a time, the slowest first (scripts/pytest_files.sh), in .venv;
#   2. the few tests of tests/runtime that need torch or TensorFlow (marked train_extra), in .venv;
#   3. tests/runtime against the INSTALLED package in a venv without torch (scripts/test_runtime.sh).
# CI (.ci/run) must end within 20 minutes. The whole suite also runs in one process (issue 55:
# `python -X faulthandler -m pytest -q tests`; see docs/architecture.md).
if [ $# -eq 0 ]; then
    shopt -s globstar  # tests/ mirrors the package: tests/runtime/<layer>/, tests/training/, tests/export/ ...
    slow=(tests/export/test_from_tf.py tests/export/test_export.py tests/training/test_train.py
          tests/export/test_convert_templates.py tests/export/test_partial_models.py tests/training/test_adapt.py
          tests/test_readme.py)
    files=("${slow[@]}")
    for f in tests/**/test_*.py; do
        [[ " ${slow[*]} " == *" $f "* || $f == tests/runtime/* ]] || files+=("$f")
    done
    PYTEST=".venv/bin/python -m pytest -q -p no:cacheprovider" NAME=scripts/test.sh \
        bash scripts/pytest_files.sh "${files[@]}" || status=1
    .venv/bin/python -m pytest -q -p no:cacheprovider -m train_extra tests/runtime || status=1
    bash scripts/test_runtime.sh || status=1
    exit "${status:-0}"
fi
exec .venv/bin/python -m pytest -q "$@"

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
# Every test, the `slow` ones (> ~20 s on 2 cores) included. The quick run leaves them out:
#   .venv/bin/python -m pytest -m "not slow"
# Without arguments, one pytest process per test file: in one process (~720 tests) pytest died of SIGSEGV
# three times, each at a different, unrelated test late in the run (a native thread left by an earlier test,
# we think; cause not found), while each file passes on its own. Any failing file fails the run.
if [ $# -eq 0 ]; then
    shopt -s globstar  # tests/ mirrors the package: tests/runtime/<layer>/, tests/training/, tests/export/ ...
    failed=()
    files=(tests/**/test_*.py)
    for f in "${files[@]}"; do
        start=$SECONDS
        .venv/bin/python -m pytest -q -p no:cacheprovider "$f" || failed+=("$f")
        echo "scripts/test.sh: $f took $((SECONDS - start)) s"
    done
    n=${#files[@]}
    echo "scripts/test.sh: $((n - ${#failed[@]})) of $n test files passed${failed[*]:+; failed: ${failed[*]}}"
    [ ${#failed[@]} -eq 0 ]
    exit
fi
exec .venv/bin/python -m pytest -q "$@"

#!/usr/bin/env bash
# Run test files with one pytest process each, TEST_JOBS (default 2) at a time, in the order given (the
# slowest first: CI must end within 20 minutes, and much of a file's time is single-threaded). Each file's
# output is printed in one piece when it ends; any failing file (pytest exit 5, no tests, included) fails
# the run. Used by scripts/test.sh and scripts/test_runtime.sh:
#   PYTEST=".venv/bin/python -m pytest -q -p no:cacheprovider" NAME=scripts/test.sh bash scripts/pytest_files.sh FILE...
set -uo pipefail
: "${PYTEST:?the pytest command}" "${NAME:=pytest_files}"
run_file() {
    local log start=$SECONDS status=passed
    log=$(mktemp)
    $PYTEST "$1" >"$log" 2>&1 || status=FAILED
    printf '%s\n%s: %s %s in %d s\n' "$(cat "$log")" "$NAME" "$1" "$status" $((SECONDS - start))
    rm -f "$log"
}
export -f run_file
export PYTEST NAME
results=$(mktemp)
printf '%s\n' "$@" | xargs -P "${TEST_JOBS:-2}" -I{} bash -c 'run_file "$1"' _ {} | tee "$results"
failed=$(grep -E "^$NAME: .* FAILED in [0-9]+ s\$" "$results" | cut -d' ' -f2 | tr '\n' ' ' || true)
passed=$(grep -cE "^$NAME: .* passed in [0-9]+ s\$" "$results" || true)
rm -f "$results"
echo "$NAME: $passed of $# test files passed${failed:+; failed: $failed}"
[ "$passed" -eq "$#" ]

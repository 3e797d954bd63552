"""How long do `import geonet_infer` and `import geonet_infer.cli` take, and what do they load?

Each import runs in a fresh interpreter (the cost a user pays at every `geonet-infer` start and
every worker process), several rounds, the trees given interleaved within each round so that
they share the machine's conditions; the median is printed with the modules the import loaded.

    python experiments/import_time.py                               # this checkout
    git worktree add /tmp/before42 bcaec11                         # the tree before issue 42
    python experiments/import_time.py --root /tmp/before42 --root . # before and after, one run

docs/architecture.md quotes a run of the last command.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

MODULES = ("geonet_infer", "geonet_infer.cli")

# Prints (seconds, the package's modules loaded, all modules loaded) for one import.
PROBE = """
import sys, time
before = set(sys.modules)
t0 = time.perf_counter()
import {module}
seconds = time.perf_counter() - t0
new = set(sys.modules) - before
print(seconds, sum(m.split(".")[0] == "geonet_infer" for m in new), len(new))
"""


def probe(root: Path, module: str) -> tuple[float, int, int]:
    env = {**os.environ, "PYTHONPATH": str(root)}
    out = subprocess.run(
        [sys.executable, "-c", PROBE.format(module=module)], cwd=root, env=env, capture_output=True, text=True
    )
    if out.returncode != 0:
        raise SystemExit(f"import {module} failed in {root}: {out.stderr.strip().splitlines()[-1]}")
    seconds, package, loaded = out.stdout.split()
    return float(seconds), int(package), int(loaded)


def measure(roots: list[Path], rounds: int) -> dict[str, dict[str, dict]]:
    """{str(root): {module: {median_ms, package_modules, modules}}} over ``rounds`` interleaved rounds."""
    times: dict[tuple[Path, str], list[float]] = {(r, m): [] for r in roots for m in MODULES}
    counts: dict[tuple[Path, str], tuple[int, int]] = {}
    for _ in range(rounds):
        for root in roots:
            for module in MODULES:
                seconds, package, loaded = probe(root, module)
                times[root, module].append(seconds)
                counts[root, module] = (package, loaded)
    return {
        str(root): {
            module: {
                "median_ms": round(1e3 * statistics.median(times[root, module]), 1),
                "package_modules": counts[root, module][0],
                "modules": counts[root, module][1],
            }
            for module in MODULES
        }
        for root in roots
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--root", type=Path, action="append", help="a checkout (repeat to compare; default: this one)")
    parser.add_argument("--rounds", type=int, default=15, help="fresh interpreters per import and tree (default 15)")
    parser.add_argument("--json", type=Path, help="also write the numbers here")
    args = parser.parse_args(argv)
    roots = args.root or [Path(__file__).resolve().parents[1]]
    result = measure(roots, args.rounds)
    print(f"| tree | import | median ms ({args.rounds} fresh interpreters) | geonet_infer modules | all modules |")
    print("|---|---|---|---|---|")
    for root, rows in result.items():
        for module, row in rows.items():
            print(f"| {root} | `{module}` | {row['median_ms']} | {row['package_modules']} | {row['modules']} |")
    if args.json:
        args.json.write_text(json.dumps(result, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

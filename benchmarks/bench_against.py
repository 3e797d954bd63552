"""`geonet-infer bench --tasks sequence --modes e2e` of this checkout against an older revision, in
one interleaved run: issue 54's "best precision of the default engine" ratio.

Each round runs the bench of every (tree, settings) configuration once, in rotating order, as a
fresh process on the bundled model; a run's figure per precision is bench's p50 ms per frame of the
sequence task, end to end from uint8 frames at 1242x375. Settings: bench as it is (the old tree's
only mode), and each ``--after-args`` set for this checkout only (options the old revision lacks).

    python benchmarks/bench_against.py --against c56716d --rounds 3
    python benchmarks/bench_against.py --against c56716d --after-args "--mode throughput" \
        --after-args "--mode throughput --rigid-op numpy"

Prints a markdown table: the median over rounds per precision, the best precision's median, and
its ratio before / after (greater than 1: this checkout is faster); ``--json`` keeps every run.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import statistics
import sys
import tempfile
from pathlib import Path

from identical_outputs import REPO, revision_tree, run_cli

PRECISIONS = ("fp32", "int8")


def one_run(tree: Path, args: list[str], out: Path) -> dict[str, float]:
    """bench's p50 ms per frame of the e2e sequence task, per precision."""
    bench = ["bench", "--tasks", "sequence", "--modes", "e2e", "--precision", ",".join(PRECISIONS), "--quiet"]
    run_cli(tree, [*bench, "--json", str(out), *args])
    rows = json.loads(out.read_text())["results"]
    return {row["precision"]: row["per_item_p50_ms"] for row in rows}  # sequence rows: per frame


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--against", required=True, help="git revision to compare with")
    parser.add_argument("--rounds", type=int, default=3, help="runs of each configuration (default: 3)")
    parser.add_argument(
        "--after-args", action="append", default=[], help="bench options for one more setting of this checkout"
    )
    parser.add_argument("--json", type=Path, help="write every run here")
    args = parser.parse_args(argv)
    settings = {"as it is": []} | {text: shlex.split(text) for text in args.after_args}
    runs: list[dict] = []
    with tempfile.TemporaryDirectory(prefix="geonet_bench_") as tmp, revision_tree(args.against, Path(tmp)) as old:
        configs = [("before", old, "as it is", [])] + [("after", REPO, s, flags) for s, flags in settings.items()]
        for r in range(args.rounds):
            for i in range(len(configs)):
                label, tree, setting, flags = configs[(i + r) % len(configs)]  # rotate: no fixed first
                ms = one_run(tree, flags, Path(tmp) / f"bench_{len(runs)}.json")
                runs.append({"tree": label, "setting": setting, "args": flags, "ms_per_frame": ms})
                shown = ", ".join(f"{p} {v:.1f}" for p, v in ms.items())
                print(f"round {r + 1}: {label:6s} {setting:24s} {shown} ms/frame", file=sys.stderr)
    rows = [("before", "as it is")] + [("after", s) for s in settings]
    medians = {
        row: {
            p: statistics.median(r["ms_per_frame"][p] for r in runs if (r["tree"], r["setting"]) == row)
            for p in PRECISIONS
        }
        for row in rows
    }
    best_before = min(medians[rows[0]].values())
    print(
        f"`geonet-infer bench --tasks sequence --modes e2e` (ms per frame, p50, median of {args.rounds} rounds), "
        f"{os.cpu_count()} CPUs; before = {args.against}, after = this checkout"
    )
    print()
    print("| tree | settings | FP32 | INT8 | best | before / after (best) |")
    print("|---|---|---|---|---|---|")
    for row in rows:
        best = min(medians[row].values())
        fp32, int8 = (medians[row][p] for p in PRECISIONS)
        print(f"| {row[0]} | {row[1]} | {fp32:.1f} | {int8:.1f} | {best:.1f} | {best_before / best:.2f}x |")
    if args.json:
        args.json.write_text(json.dumps({"against": args.against, "runs": runs}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

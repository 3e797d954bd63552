"""Frames per second of `geonet-infer predict` on the 78-frame KITTI drive, this checkout against
an older revision, in one interleaved run.

Each round runs every (tree, outputs) configuration once, in rotating order, as a fresh
process (model load included in the wall time, as a user sees it); frames/s is the
``frames_per_s`` predict writes into ``summary.json`` (frames / wall time of the run, load
excluded). Two output settings: all default outputs, and ``--no-vis`` (no colour pictures).

    python benchmarks/predict_fps.py --against 3f60b25 --rounds 3
    python benchmarks/predict_fps.py --against 3f60b25 --after-args "--rigid-op numpy"

``--after-args`` go to this checkout's runs only (options the old revision may not have).
Prints a markdown table (median over rounds, and the ratio after / before) with the CPU time
each run's process used per frame (user + system, model load included: what bounds frames/s on
a busy machine); ``--json`` keeps every run.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shlex
import statistics
import sys
import tempfile
import time
from pathlib import Path

from identical_outputs import REPO, revision_tree, run_predict

OUTPUTS = {"all outputs": [], "--no-vis": ["--no-vis"]}


def one_run(tree: Path, args: list[str], out: Path) -> dict:
    """frames/s as predict reports it, and the whole process's wall and CPU time (user + system, load included)."""
    cpu_before = _children_cpu_s()
    started = time.perf_counter()
    run_predict(tree, args, out)
    process_s = time.perf_counter() - started
    cpu_s = _children_cpu_s() - cpu_before
    summary = json.loads((out / "summary.json").read_text())
    return {
        "frames_per_s": summary["frames_per_s"],
        "frames": summary["frames"],
        "process_s": process_s,
        "cpu_ms_per_frame": 1e3 * cpu_s / summary["frames"],
    }


def _children_cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)  # the finished, waited-for children
    return usage.ru_utime + usage.ru_stime


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--against", required=True, help="git revision to compare with")
    parser.add_argument("--rounds", type=int, default=3, help="runs of each configuration (default: 3)")
    parser.add_argument("--after-args", default="", help="extra predict options for this checkout only")
    parser.add_argument("--json", type=Path, help="write every run here")
    args = parser.parse_args(argv)
    extra = shlex.split(args.after_args)
    runs: list[dict] = []
    with tempfile.TemporaryDirectory(prefix="geonet_fps_") as tmp, revision_tree(args.against, Path(tmp)) as old:
        configs = [
            (label, tree, outputs, flags + (extra if label == "after" else []))
            for outputs, flags in OUTPUTS.items()
            for label, tree in (("before", old), ("after", REPO))
        ]
        for r in range(args.rounds):
            for i in range(len(configs)):
                label, tree, outputs, flags = configs[(i + r) % len(configs)]  # rotate: no fixed first
                out = Path(tmp) / f"out_{len(runs)}"
                runs.append({"tree": label, "outputs": outputs, "args": flags, **one_run(tree, flags, out)})
                print(
                    f"round {r + 1}: {label:6s} {outputs:12s} {runs[-1]['frames_per_s']:.1f} frames/s", file=sys.stderr
                )
    print(
        f"`geonet-infer predict` on the KITTI drive ({runs[0]['frames']} frames), median of {args.rounds} rounds, "
        f"{os.cpu_count()} CPUs; before = {args.against}, after = this checkout {' '.join(extra)}".rstrip()
    )
    print()
    print("| outputs | before frames/s | after frames/s | after / before | CPU ms per frame, before / after |")
    print("|---|---|---|---|---|")
    for outputs in OUTPUTS:
        fps, cpu = (
            {
                label: statistics.median(r[key] for r in runs if r["tree"] == label and r["outputs"] == outputs)
                for label in ("before", "after")
            }
            for key in ("frames_per_s", "cpu_ms_per_frame")
        )
        print(
            f"| {outputs} | {fps['before']:.1f} | {fps['after']:.1f} | {fps['after'] / fps['before']:.2f}x "
            f"| {cpu['before']:.0f} / {cpu['after']:.0f} |"
        )
    if args.json:
        args.json.write_text(json.dumps({"against": args.against, "after_args": extra, "runs": runs}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

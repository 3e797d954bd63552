"""Frames/s and peak memory of `geonet-infer predict` per mode and batch size (issue 54): does a smaller
default batch cost speed, and what does it save?

Each configuration runs as a fresh process on the 78-frame KITTI drive, all default outputs, in rotating
order over the rounds; frames/s is the ``frames_per_s`` of its summary.json, peak RSS the process's
``ru_maxrss`` (``os.wait4``, Linux). Prints a markdown table of medians over the rounds.

    python -m experiments.predict_batch_memory --rounds 2
    python -m experiments.predict_batch_memory --configs latency:1,latency:4 --extra "--output-size network"
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DRIVE = REPO / ".." / "shared" / "realdata" / "kitti_raw_2011_09_26_sfnd"
DEFAULT_CONFIGS = "latency:4,latency:2,latency:1,throughput:4,throughput:2,throughput:1"


def run_once(mode: str, batch: int, extra: list[str], out: Path) -> tuple[float, float]:
    """(frames/s, peak RSS MiB) of one predict process."""
    cmd = [sys.executable, "-m", "geonet_infer.cli", "predict", str(DRIVE), "--out", str(out), "--quiet"]
    cmd += ["--mode", mode, "--batch-size", str(batch), *extra]
    proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        raise SystemExit(f"predict failed ({proc.returncode}): {shlex.join(cmd)}")
    fps = json.loads((out / "summary.json").read_text())["frames_per_s"]
    return float(fps), usage.ru_maxrss / 1024


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--configs", default=DEFAULT_CONFIGS, help=f"MODE:BATCH,... (default {DEFAULT_CONFIGS})")
    parser.add_argument("--extra", default="", help="further predict options for every run")
    parser.add_argument("--json", type=Path, help="write every run here")
    args = parser.parse_args(argv)
    configs = [(m, int(b)) for m, b in (c.split(":") for c in args.configs.split(","))]
    runs: dict[str, list[tuple[float, float]]] = {f"{m}:{b}": [] for m, b in configs}
    with tempfile.TemporaryDirectory(prefix="geonet_batch_mem_") as tmp:
        for r in range(args.rounds):
            order = configs[r % len(configs) :] + configs[: r % len(configs)]
            for mode, batch in order:
                out = Path(tmp) / f"{mode}_{batch}_{r}"
                runs[f"{mode}:{batch}"].append(run_once(mode, batch, shlex.split(args.extra), out))
                print(f"round {r + 1} {mode}:{batch} -> {runs[f'{mode}:{batch}'][-1]}", file=sys.stderr)
    print(f"| mode | batch | frames/s (median of {args.rounds}) | peak RSS MiB (median) | runs |")
    print("|---|---|---|---|---|")
    for key, values in runs.items():
        mode, size = key.split(":")
        fps = statistics.median(v[0] for v in values)
        rss = statistics.median(v[1] for v in values)
        detail = ", ".join(f"{v[0]:.1f}/{v[1]:.0f}" for v in values)
        print(f"| {mode} | {size} | {fps:.1f} | {rss:.0f} | {detail} |")
    if args.json:
        args.json.write_text(json.dumps({"extra": args.extra, "runs": runs}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""What the new outputs cost (issues 54 and 59), one interleaved run of fresh `geonet-infer predict` processes:

* the KITTI drive (78 frames) with and without ``--rerun``: frames/s, the rerun stage's ms per frame,
  the recording's megabytes per frame;
* the 720p dashcam clip's compact set (``--outputs depth-png16,flow-png,poses``) at the input's size and at
  the network's (``--output-size network``): the writer threads' CPU ms and the bytes per frame.

    python experiments/output_costs.py --rounds 3 [--json out.json]

Prints a markdown table (medians over the rounds); the verdicts are in docs/performance.md.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared" / "realdata"
DRIVE = SHARED / "kitti_raw_2011_09_26_sfnd"
CLIP, CALIB = (
    SHARED / "udacity_dashcam" / "test_video.mp4",
    SHARED / "udacity_dashcam" / "calib_advanced_lane_lines.txt",
)
COMPACT = ["--outputs", "depth-png16,flow-png,poses", "--threads", "1"]
CONFIGS = {
    "drive, default outputs": [str(DRIVE)],
    "drive, default outputs, --rerun": [str(DRIVE), "--rerun", "{tmp}/drive.rrd"],
    "720p clip, compact set, input size": [str(CLIP), "--calib", str(CALIB), *COMPACT],
    "720p clip, compact set, network size": [str(CLIP), "--calib", str(CALIB), *COMPACT, "--output-size", "network"],
}


def run(args: list[str], tmp: Path) -> dict:
    out = tmp / "out"
    cmd = [sys.executable, "-m", "geonet_infer.cli", "predict", *[a.format(tmp=tmp) for a in args], "--out", str(out),
           "--no-progress", "--quiet"]  # fmt: skip
    subprocess.run(cmd, check=True, capture_output=True)
    s = json.loads((out / "summary.json").read_text())
    row = {
        "frames_per_s": s["frames_per_s"],
        "rerun_ms": s["timings_ms_per_frame"].get("rerun"),
        "write_cpu_ms": s["overlapped_ms_per_frame"]["write_cpu"],
        "bytes_per_frame": s["written"]["bytes_per_frame"],
    }
    if s.get("rerun"):
        row["rrd_mb_per_frame"] = s["rerun"]["bytes"] / 1e6 / s["rerun"]["frames"]
    return row


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--json", type=Path)
    args = p.parse_args(argv)
    runs: dict[str, list[dict]] = {name: [] for name in CONFIGS}
    names = list(CONFIGS)
    for r in range(args.rounds):
        for name in names[r % len(names) :] + names[: r % len(names)]:  # rotating order
            with tempfile.TemporaryDirectory() as tmp:
                runs[name].append(run(CONFIGS[name], Path(tmp)))
    keys = ("frames_per_s", "rerun_ms", "rrd_mb_per_frame", "write_cpu_ms", "bytes_per_frame")
    print("| configuration | " + " | ".join(keys) + " |\n|---|" + "---|" * len(keys))
    for name, rows in runs.items():
        cells = []
        for k in keys:
            values = [r[k] for r in rows if r.get(k) is not None]
            cells.append(f"{statistics.median(values):.3g}" if values else "–")
        print(f"| {name} | " + " | ".join(cells) + " |")
    if args.json:
        args.json.write_text(json.dumps(runs, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

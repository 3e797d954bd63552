"""Memory of `geonet-infer predict --video-out` over a long video: does it stay flat?

Runs predict on a dashcam video (600 frames by default) with the result video, sampling the
process's resident memory (``/proc/<pid>/status`` VmRSS, Linux) twice a second, and prints RSS
after the first 10 % of the run, at the end, and the peak.

    python experiments/video_memory.py --frames 600
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DASHCAM = REPO / ".." / "shared" / "realdata" / "udacity_dashcam"


def rss_mib(pid: int) -> float | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except OSError:
        return None
    return None


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--video", type=Path, default=DASHCAM / "solidYellowLeft.mp4")
    parser.add_argument("--calib", type=Path, default=DASHCAM / "intrinsics_960x540_GUESS_UNVERIFIED.txt")
    parser.add_argument("--frames", type=int, default=600)
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="geonet_video_mem_") as tmp:
        out = Path(tmp) / "out"
        cmd = [sys.executable, "-m", "geonet_infer.cli", "predict", str(args.video), "--out", str(out)]
        cmd += ["--calib", str(args.calib), "--max-frames", str(args.frames), "--video-out", str(out / "result.mp4")]
        cmd += ["--no-progress", "--quiet"]
        started = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        samples: list[tuple[float, float]] = []
        while proc.poll() is None:
            rss = rss_mib(proc.pid)
            if rss is not None:
                samples.append((time.perf_counter() - started, rss))
            time.sleep(0.5)
        if proc.returncode != 0:
            raise SystemExit(f"predict exited {proc.returncode}: {proc.stderr.read().decode() if proc.stderr else ''}")
        summary = json.loads((out / "summary.json").read_text())
    wall = samples[-1][0]
    early = [rss for t, rss in samples if t >= 0.1 * wall][0]
    result = {
        "video": args.video.name,
        "frames": summary["frames"],
        "video_frames": summary["video"]["frames"],
        "wall_s": round(wall, 1),
        "rss_at_10_percent_mib": round(early, 1),
        "rss_at_end_mib": round(samples[-1][1], 1),
        "rss_peak_mib": round(max(rss for _, rss in samples), 1),
    }
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())

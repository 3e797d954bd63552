"""Time the synthetic-data generator on one core; print one JSON line.

    .venv/bin/python experiments/bench_synth.py [--frames 40] [--height 128 --width 416]

Reports frames/s for rendering + ground truth in memory (``iter_frames``) and for
the full per-sequence writer (``write_sequence``: PNG encoding and atomic writes
included), after a 2-frame warm-up, with OpenCV and BLAS limited to one thread;
by wall clock and by this process's CPU time (the latter is what one free core
would give when other jobs share the machine; the 1-minute load average is printed).
"""

from __future__ import annotations

import os

# One core: must be set before numpy / OpenCV load their thread pools.
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from geonet_infer.bench.environment import cpu_model  # noqa: E402
from training import synth  # noqa: E402


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, default=40)
    p.add_argument("--height", type=int, default=128)
    p.add_argument("--width", type=int, default=416)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    cv2.setNumThreads(1)

    list(synth.iter_frames(args.seed, 99, 2, args.height, args.width))  # warm-up (imports, caches)
    # Wall time, and this process's CPU time (less sensitive to other jobs on a shared machine).
    t0, c0 = time.perf_counter(), time.process_time()
    n = sum(1 for _ in synth.iter_frames(args.seed, 0, args.frames, args.height, args.width))
    fps_gen, cpu_fps_gen = n / (time.perf_counter() - t0), n / (time.process_time() - c0)

    with tempfile.TemporaryDirectory() as tmp:
        t0, c0 = time.perf_counter(), time.process_time()
        synth.write_sequence(tmp, args.seed, 1, args.frames, args.height, args.width)
        fps_write = args.frames / (time.perf_counter() - t0)
        cpu_fps_write = args.frames / (time.process_time() - c0)
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else None

    print(
        json.dumps(
            {
                "benchmark": "synth",
                "frames": args.frames,
                "height": args.height,
                "width": args.width,
                "fps_generate": round(fps_gen, 2),
                "fps_generate_and_write": round(fps_write, 2),
                "cpu_time_fps_generate": round(cpu_fps_gen, 2),
                "cpu_time_fps_generate_and_write": round(cpu_fps_write, 2),
                "load_avg_1min": load,
                "threads": 1,
                "cpu": cpu_model(),
                "cpu_count": os.cpu_count(),
                "python": platform.python_version(),
                "numpy": np.__version__,
                "opencv": cv2.__version__,
                "platform": platform.platform(),
            }
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())

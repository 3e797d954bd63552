"""Throughput of `geonet-infer batch`: frames/s per workers x threads, local engine vs Ray engine.

Each configuration runs the real CLI in a fresh process (what a user gets), on the same
input, with the same --batch-size; configurations are interleaved (rotating order) and
repeated, and the median is reported. Two timings per run:

* ``job``: the whole command, from process start to exit (imports, worker processes or the
  local Ray cluster, model loading in every worker, all sequences, summary);
* ``dispatch``: ``summary.json``'s ``wall_s``, from handing out the first sequence to the last
  result (worker/actor start-up and model loading included, interpreter and Ray cluster
  start-up excluded);
* ``per worker``: frames / the seconds workers spent inside their sequences (summed), i.e. one
  worker's steady-state speed, start-up excluded: the engines should not differ here.

Engines: ``local``; ``ray`` (each run starts its own local Ray cluster, as the CLI does
without --ray-address); ``ray-joined`` (each run joins one cluster that this script starts
once, as on a standing cluster). Ray overhead = Ray's time / the local engine's time for the
same workers x threads (target <= 1.3x).

Input: the 78 real KITTI frames (1242x375) of ``../shared/realdata`` as 3 sequences of 26
(symlinks; the drive's calibration); ``--sequences 12`` cycles through them again
(312 frames); ``--input sample`` uses the bundled 416x128 sample frames instead.

    .venv/bin/python experiments/batch_throughput.py                       # ~5 min on 2 cores
    .venv/bin/python experiments/batch_throughput.py --sequences 12 --configs 2x1 --repeats 2  # 312 frames
    .venv/bin/python experiments/batch_throughput.py --repeats 1 --configs 2x1 --engines local  # quick look
    .venv/bin/python experiments/batch_throughput.py --json runs/bench/batch_throughput.json

Run it on a quiet machine: the load average is printed before and after, with a warning.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
KITTI = REPO.parent / "shared" / "realdata" / "kitti_raw_2011_09_26_sfnd"


def make_input(kind: str, root: Path, n_seq: int, per_seq: int) -> tuple[list[Path], Path, int]:
    """(sequence folders, calibration file, frames in all) under ``root``: ``n_seq`` folders of
    ``per_seq`` frames (symlinks), consecutive chunks of the source frames, cycling through them."""
    if kind == "kitti":
        if not KITTI.is_dir():
            sys.exit(f"{KITTI} not found; use --input sample")
        frames = sorted((KITTI / "image_02" / "data").glob("*.png"))
        calib = KITTI / "calib_cam_to_cam.txt"
    else:
        import geonet_infer

        sample = Path(geonet_infer.__file__).parent / "samples" / "synth_seq"
        frames = sorted((sample / "image").glob("*.png"))
        calib = sample / "calib.txt"
    chunks = max(1, len(frames) // per_seq)
    seqs = []
    for s in range(n_seq):
        folder = root / f"seq{s:03d}"
        folder.mkdir(parents=True)
        first = (s % chunks) * per_seq
        for i in range(per_seq):
            f = frames[(first + i) % len(frames)]
            (folder / f"{i:06d}{f.suffix}").symlink_to(f)
        seqs.append(folder)
    return seqs, calib, n_seq * per_seq


def run_once(
    seqs, calib, out: Path, engine: str, workers: int, threads: int, batch_size: int, ray_address: str | None = None
) -> dict:
    shutil.rmtree(out, ignore_errors=True)
    cmd = [
        str(REPO / ".venv" / "bin" / "geonet-infer"),
        "batch",
        *map(str, seqs),
        "--out",
        str(out),
        "--calib",
        str(calib),
        "--runner",
        engine,
        "--workers",
        str(workers),
        "--threads-per-worker",
        str(threads),
        "--batch-size",
        str(batch_size),
        "--no-progress",
    ]
    if ray_address:
        cmd += ["--ray-address", ray_address]
    if not Path(cmd[0]).exists():
        cmd[:1] = [sys.executable, "-m", "geonet_infer.cli"]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True)
    job_s = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} exited {proc.returncode}:\n{proc.stderr[-2000:]}")
    summary = json.loads((out / "summary.json").read_text())
    assert (summary["workers"], summary["threads_per_worker"]) == (workers, threads), summary
    busy = sum(r["wall_s"] for r in summary["per_sequence"])  # worker-side seconds, summed over sequences
    return {
        "job_s": job_s,
        "dispatch_s": summary["wall_s"],
        "frames": summary["frames"],
        "per_worker_fps": summary["frames"] / busy if busy else 0.0,
    }


def cpu_line() -> str:
    exe = REPO / ".venv" / "bin" / "geonet-infer"
    cmd = [str(exe), "info"] if exe.exists() else [sys.executable, "-m", "geonet_infer.cli", "info"]
    out = subprocess.run(cmd, capture_output=True, text=True).stdout
    return next((line.strip() for line in out.splitlines() if line.startswith("cpu:")), "cpu: ?")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--input", choices=("kitti", "sample"), default="kitti")
    ap.add_argument("--sequences", type=int, default=3)
    ap.add_argument("--frames-per-sequence", type=int, default=26, help="default 26: KITTI's 78 frames in 3")
    ap.add_argument("--configs", default="1x2,2x1", help="workers x threads per worker, comma list")
    ap.add_argument(
        "--engines",
        default="local,ray,ray-joined",
        help="local; ray = a local Ray cluster started by each run (no --ray-address); "
        "ray-joined = each run joins one cluster this script starts once (--ray-address)",
    )
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--batch-size", type=int, default=4)
    ap.add_argument("--json", type=Path, default=None, help="also write the results here")
    args = ap.parse_args()

    configs = [tuple(int(v) for v in c.split("x")) for c in args.configs.split(",")]
    engines = args.engines.split(",")
    ray_address = None
    if any(e.startswith("ray") for e in engines):
        try:
            import ray
        except ImportError:
            print("ray not installed: local engine only (pip install '.[ray]')", file=sys.stderr)
            engines = [e for e in engines if not e.startswith("ray")]
    if "ray-joined" in engines:
        from geonet_infer.engines import usable_cpus

        ray.init(address="local", num_cpus=usable_cpus(), include_dashboard=False, logging_level="ERROR")
        ray_address = ray.get_runtime_context().gcs_address
    load_before = os.getloadavg()
    if load_before[0] > (os.cpu_count() or 1) / 2:
        print(f"warning: load average {load_before[0]:.2f}: the machine is busy, numbers will be low", file=sys.stderr)
    runs: dict[tuple[str, int, int], list[dict]] = {(e, w, t): [] for e in engines for w, t in configs}
    keys = list(runs)
    with tempfile.TemporaryDirectory(prefix="geonet_batch_bench_") as tmp:
        seqs, calib, n_frames = make_input(args.input, Path(tmp) / "in", args.sequences, args.frames_per_sequence)
        for r in range(args.repeats):
            for key in keys[r % len(keys) :] + keys[: r % len(keys)]:  # rotate the order every repeat
                engine, w, t = key
                res = run_once(
                    seqs,
                    calib,
                    Path(tmp) / "out",
                    engine.split("-")[0],
                    w,
                    t,
                    args.batch_size,
                    ray_address if engine == "ray-joined" else None,
                )
                runs[key].append(res)
                print(
                    f"  {key[0]:5s} {key[1]}x{key[2]}  job {res['job_s']:6.2f} s  dispatch {res['dispatch_s']:6.2f} s",
                    file=sys.stderr,
                )
    load_after = os.getloadavg()
    if ray_address:
        ray.shutdown()

    rows = []
    for (engine, w, t), rs in runs.items():
        job = statistics.median(r["job_s"] for r in rs)
        disp = statistics.median(r["dispatch_s"] for r in rs)
        rows.append(
            {
                "engine": engine,
                "workers": w,
                "threads": t,
                "frames": rs[0]["frames"],
                "repeats": len(rs),
                "job_s": job,
                "dispatch_s": disp,
                "job_fps": rs[0]["frames"] / job,
                "dispatch_fps": rs[0]["frames"] / disp,
                "per_worker_fps": statistics.median(r["per_worker_fps"] for r in rs),
                "job_s_all": [r["job_s"] for r in rs],
            }
        )
    by = {(r["engine"], r["workers"], r["threads"]): r for r in rows}
    for r in rows:
        local = by.get(("local", r["workers"], r["threads"]))
        is_ray = r["engine"].startswith("ray")
        r["ray_overhead_job"] = r["job_s"] / local["job_s"] if is_ray and local else None
        r["ray_overhead_dispatch"] = r["dispatch_s"] / local["dispatch_s"] if is_ray and local else None

    machine = cpu_line()
    print(
        f"\n{machine}; input: {args.input}, {args.sequences} sequences, {n_frames} frames, "
        f"--batch-size {args.batch_size}; median of {args.repeats}; load average {load_before[0]:.2f} -> "
        f"{load_after[0]:.2f}\n"
    )
    print(
        "| engine | workers x threads | job s | job frames/s | dispatch s | dispatch frames/s | per worker frames/s "
        "| Ray / local (job) | Ray / local (dispatch) |"
    )
    print("|---|---|---|---|---|---|---|---|---|")

    def fmt(v):
        return f"{v:.2f}x" if v is not None else ""

    for r in rows:
        print(
            f"| {r['engine']} | {r['workers']}x{r['threads']} | {r['job_s']:.2f} | {r['job_fps']:.2f} | "
            f"{r['dispatch_s']:.2f} | {r['dispatch_fps']:.2f} | {r['per_worker_fps']:.2f} | "
            f"{fmt(r['ray_overhead_job'])} | "
            f"{fmt(r['ray_overhead_dispatch'])} |"
        )
    result = {
        "machine": machine,
        "platform": platform.platform(),
        "input": args.input,
        "sequences": args.sequences,
        "frames": n_frames,
        "batch_size": args.batch_size,
        "repeats": args.repeats,
        "load_average_before": load_before,
        "load_average_after": load_after,
        "results": rows,
    }
    print("\n" + json.dumps(result, indent=2))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""`--precision auto` against every fixed engine and precision, end to end, in ONE interleaved run.

    .venv/bin/python experiments/precision_auto.py --json docs/precision_auto.json

Issue 45: on a CPU where INT8 does not pay on an engine, the auto choice must be within 5 % of
the fastest accurate choice, timed in the same run. Every configuration is loaded once (auto
times its candidates at load, as users get it), then all are timed block-interleaved
(:func:`geonet_infer.engines.timing.time_interleaved`: every configuration sees the same background
load) on two jobs: ``predict_sequence`` over ``--frames`` KITTI-size frames (per frame: all
outputs, resize in and out) and ``depth`` of one frame. "Accurate" is
:func:`geonet_infer.core.int8_safety.int8_unsafe_reason` on this CPU: a fixed INT8 configuration
whose engine saturates here is timed but left out of the fastest accurate choice.
"""

from __future__ import annotations

import argparse
import json
import sys
from functools import partial

import geonet_infer
from geonet_infer.bench.cases import DEFAULT_INPUT_SIZE, bench_frames
from geonet_infer.core.int8_safety import int8_unsafe_reason
from geonet_infer.engines import ENGINES
from geonet_infer.engines.cpu import cpu_info, isa_line
from geonet_infer.engines.timing import Case, time_interleaved
from geonet_infer.io.atomic import atomic_write

JOBS = ("sequence", "depth")


def configurations(engines: list[str]) -> list[tuple[str, str]]:
    """(backend, precision): each engine at each precision, then auto at both."""
    fixed = [(e, p) for e in engines for p in ("fp32", "int8")]
    auto = [(b, "auto") for b in engines[:1]] + (
        [("auto", p) for p in ("fp32", "int8", "auto")] if len(engines) > 1 else []
    )
    return fixed + auto


def accurate(predictor: geonet_infer.Predictor) -> bool:
    """Whether every graph runs exactly on this CPU (no INT8 on an engine that saturates here)."""
    q = predictor.manifest.quantization
    return not any(
        run["precision"] == "int8" and int8_unsafe_reason(run["engine"], q.int8_kernels.get(name) if q else None)
        for name, run in predictor.graph_set.runs.items()
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", default=None, help="bundled name or model directory (default: the bundled one)")
    parser.add_argument("--threads", type=int, default=None, help="threads per graph (default: usable CPUs)")
    parser.add_argument("--frames", type=int, default=8, help="frames per predict_sequence call (default: 8)")
    parser.add_argument("--iters", type=int, default=12, help="timed calls per case (default: 12)")
    parser.add_argument("--json", default=None, help="write every number here")
    args = parser.parse_args(argv)

    engines = [e.name for e in ENGINES.values() if e.available()]
    predictors = {}
    for backend, precision in configurations(engines):
        label = f"{backend} {precision}"
        print(f"loading {label}", file=sys.stderr, flush=True)
        predictors[label] = geonet_infer.load(args.model, precision=precision, backend=backend, threads=args.threads)
    spec = next(iter(predictors.values())).spec
    frames, camera = bench_frames(DEFAULT_INPUT_SIZE, (spec.height, spec.width), args.frames)
    cases = {
        (label, job): Case(
            f"{label} {job}",
            partial(p.predict_sequence, frames, camera=camera) if job == "sequence" else partial(p.depth, frames[0]),
            items_per_call=len(frames) if job == "sequence" else 1,
        )
        for label, p in predictors.items()
        for job in JOBS
    }
    time_interleaved(list(cases.values()), warmup=2, iters=args.iters, block=2)

    rows = []
    for job in JOBS:
        frames_per_call = len(frames) if job == "sequence" else 1
        ms = {label: cases[label, job].stats().p50_ms / frames_per_call for label in predictors}
        fixed = {lb: v for lb, v in ms.items() if "auto" not in lb.split()}
        best_accurate = min((lb for lb in fixed if accurate(predictors[lb])), key=lambda lb: fixed[lb])
        for label, value in ms.items():
            # the fixed choices this configuration could have made: its engine's, or every engine's under auto
            engine = label.split()[0]
            own = [lb for lb in fixed if accurate(predictors[lb]) and (engine == "auto" or lb.split()[0] == engine)]
            best_own = min(own, key=lambda lb: fixed[lb])
            rows.append(
                {
                    "job": job,
                    "configuration": label,
                    "ms_per_frame": round(value, 2),
                    "accurate_here": accurate(predictors[label]),
                    "vs_fastest_accurate_fixed": round(value / fixed[best_accurate], 3),
                    "fastest_accurate_fixed": best_accurate,
                    "vs_fastest_accurate_fixed_same_engines": round(value / fixed[best_own], 3),
                    "fastest_accurate_fixed_same_engines": best_own,
                    "graphs": {
                        n: f"{r['engine']} {r['precision']}" for n, r in predictors[label].graph_set.runs.items()
                    },
                }
            )
    info = cpu_info()
    print(f"cpu: {info['model']}; isa: {isa_line(info)}; threads {next(iter(predictors.values())).threads}")
    print(f"per frame, p50 of {args.iters} block-interleaved calls; ratios to the fastest accurate fixed choice")
    print(
        "| job | configuration | ms / frame | ratio to the fastest | ratio to the fastest on its engines "
        "| graphs (depthnet, posenet, rigidflow, resflownet) |"
    )
    print("|---|---|---|---|---|---|")
    for r in rows:
        graphs = ", ".join(r["graphs"].values())
        mark = "" if r["accurate_here"] else " (inexact here)"
        ratio, own = r["vs_fastest_accurate_fixed"], r["vs_fastest_accurate_fixed_same_engines"]
        print(
            f"| {r['job']} | {r['configuration']}{mark} | {r['ms_per_frame']:.1f} | {ratio:.3f} "
            f"| {own:.3f} ({r['fastest_accurate_fixed_same_engines']}) | {graphs} |"
        )
    if args.json:
        record = {"cpu": info, "isa": isa_line(info), "frames": args.frames, "iters": args.iters, "rows": rows}
        with atomic_write(args.json) as tmp:
            tmp.write_text(json.dumps(record, indent=2) + "\n")
        print(f"JSON -> {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

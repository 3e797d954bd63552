"""``geonet-infer bench``: latency of each GeoNet stage, network only and end to end.

Tasks (``--tasks``):

=============  ==============================================================================
depth          DepthNet
pose           PoseNet on one snippet
rigid_flow     the rigid-flow op (depth + pose + K -> rigid flow, warped source, error)
resflow        ResFlowNet
flow           the cascade for one pair: DepthNet + PoseNet + rigid-flow op + ResFlowNet
sequence       per-frame cost of ``Predictor.iter_sequence`` (depth computed once per frame
               and reused by the pair it is the target of)
=============  ==============================================================================

Modes (``--modes``):

* ``graph``: the engines only (onnxruntime sessions or OpenVINO compiled models), on prepared
  inputs (normalised, graph size);
  the chained tasks (flow, sequence) pass each graph's outputs to the next one.
* ``e2e``: from uint8 frames at ``--input-size`` (default 1242x375, KITTI raw) to outputs
  at that size, through the runtime: ``Predictor.depth`` / ``pose`` / ``flow`` /
  ``iter_sequence``; for the two graphs without a public call of their own, rigid_flow =
  resize + normalise target and source, scale K, the op, rigid flow back to input size, and
  resflow = the net + flow and residual back to input size (its input is built inside the
  cascade). ``Predictor.pose`` and ``flow`` take one snippet, so their e2e rows exist for
  batch 1 only (batched pose/flow run inside ``sequence``).

Inputs are fixed: the bundled sample frames (``geonet_infer.samples``), resized to
``--input-size``, with their intrinsics scaled alike. Timing: ``geonet_infer.engines.timing``
(warm-up, GC off, block-interleaved over all cases of one precision and batch).
"""

from __future__ import annotations

import argparse
import gc
import json
import sys
import time
from pathlib import Path

from geonet_infer.bench.cases import BENCH_TASKS, DEFAULT_INPUT_SIZE, MODES, TASK_GRAPHS, bench_frames, build_cases
from geonet_infer.bench.environment import Environment, cpu_flags, git_commit, model_summary, thread_env
from geonet_infer.bench.report import format_table, paper_line, result_row
from geonet_infer.cli import COMMANDS
from geonet_infer.cli.common import add_model_args, backend_help
from geonet_infer.core.predictor import load
from geonet_infer.engines import BACKENDS, ENGINES, OrtEngine, check_threads
from geonet_infer.engines.timing import current_rss_mib, load_average, peak_rss_mib, time_interleaved
from geonet_infer.errors import BackendUnavailableError, InputError
from geonet_infer.io.atomic import atomic_write
from geonet_infer.io.images import check_pixels
from geonet_infer.limits import MAX_BATCH_SIZE, MAX_SEQUENCE_FRAMES, check_batch_size, check_count
from geonet_infer.models import resolve_model
from geonet_infer.models.manifest import AUTO, MANIFEST_NAME, PRECISION_CHOICES, PRECISIONS, load_manifest
from geonet_infer.samples import SAMPLE_FRAMES


def add_parser(sub) -> None:
    parser = sub.add_parser(
        "bench",
        help=COMMANDS["bench"],
        description="Time DepthNet, PoseNet, the rigid-flow op, ResFlowNet, the flow cascade for one pair and "
        "the per-frame cost of a sequence, each network-only ('graph') and end to end from uint8 "
        "frames ('e2e'), on the bundled sample frames. Reports p50/p90/p99, mean +- std (ms) and "
        "items/s after warm-up; cases of one precision and batch are timed block-interleaved.",
        epilog="e2e pose and flow exist for batch 1 only (Predictor.pose/flow take one snippet). "
        "sequence rows are per frame. Bad input (unknown task, precision, backend; a model without "
        "the needed graph; --iters < 1) -> one line on stderr, exit 2.",
        conflict_handler="resolve",
    )
    add_model_args(parser, mode="latency")
    group = parser.add_argument_group("benchmark")
    # Replaces add_model_args' single --precision (conflict_handler="resolve").
    group.add_argument(
        "--precision",
        default=None,
        metavar="LIST",
        help=f"comma list of {', '.join(PRECISION_CHOICES)} ({AUTO}: per graph, the fastest exact precision, "
        "chosen at load) (default: every precision the model has)",
    )
    group.add_argument(
        "--batch",
        default="1",
        metavar="LIST",
        help=f"comma list of batch sizes, each at most {MAX_BATCH_SIZE} (default: 1)",
    )
    group.add_argument(
        "--tasks",
        default=None,
        metavar="LIST",
        help=f"comma list of {', '.join(BENCH_TASKS)} (default: all the model's graphs allow)",
    )
    group.add_argument(
        "--modes",
        default=",".join(MODES),
        metavar="LIST",
        help="graph (network only), e2e (with pre/post-processing) or both (default)",
    )
    group.add_argument(
        "--backend",
        default=BACKENDS[0],
        metavar="LIST",
        help=f"comma list of inference backends: {', '.join(BACKENDS)} ({backend_help()})",
    )
    group.add_argument("--warmup", type=int, default=3, help="untimed calls per case before timing (default: 3)")
    group.add_argument("--iters", type=int, default=20, help="timed calls per case (default: 20)")
    group.add_argument(
        "--block", type=int, default=4, help="timed back-to-back calls per case per interleaving round (default: 4)"
    )
    group.add_argument(
        "--rewarm-ms",
        type=float,
        default=50.0,
        help="untimed re-warm calls before each block, for at least this long (default: 50; 0 = none)",
    )
    group.add_argument(
        "--input-size",
        default=f"{DEFAULT_INPUT_SIZE[0]}x{DEFAULT_INPUT_SIZE[1]}",
        metavar="WxH",
        help="frame size for e2e, or 'graph' for the graphs' own size (default: 1242x375)",
    )
    group.add_argument(
        "--seq-frames",
        type=int,
        default=8,
        help=f"frames per timed sequence call, at most {MAX_SEQUENCE_FRAMES} (default: 8; the last has no flow)",
    )
    out = parser.add_argument_group("output")
    out.add_argument("--json", type=Path, default=None, metavar="FILE", help="write the results as JSON")
    out.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    parser.set_defaults(run=run)


# ----------------------------------------------------------------------------- arguments
def _parse_list(text: str, allowed: tuple, what: str) -> list[str]:
    items = [t.strip() for t in str(text).split(",") if t.strip()]
    bad = [t for t in items if t not in allowed]
    if bad or not items:
        raise InputError(
            None, f"unknown {what} {', '.join(bad) if bad else repr(text)}", f"choose from {', '.join(allowed)}"
        )
    return list(dict.fromkeys(items))


def _parse_batches(text: str) -> list[int]:
    out = []
    for item in [t.strip() for t in str(text).split(",") if t.strip()] or [str(text)]:
        try:
            value = int(item)
        except ValueError:
            value = 0
        if value < 1:
            raise InputError(None, f"--batch {text!r}: batch sizes must be positive integers", "e.g. --batch 1,4")
        out.append(check_batch_size(value, "--batch"))
    return list(dict.fromkeys(out))


def _parse_size(text: str) -> tuple[int, int] | None:
    if str(text).lower() == "graph":
        return None
    try:
        w, h = (int(v) for v in str(text).lower().split("x"))
    except ValueError:
        raise InputError(None, f"--input-size {text!r} is not WxH", "e.g. --input-size 1242x375, or 'graph'") from None
    if w < 8 or h < 8:
        raise InputError(None, f"--input-size {text!r} is too small", "frames need at least 8x8 pixels")
    check_pixels("--input-size", w, h)
    return w, h


def _check_args(args) -> dict:
    if args.iters < 1:
        raise InputError(None, f"--iters must be >= 1, got {args.iters}")
    if args.warmup < 0:
        raise InputError(None, f"--warmup must be >= 0, got {args.warmup}")
    if args.block < 1:
        raise InputError(None, f"--block must be >= 1, got {args.block}")
    if args.rewarm_ms < 0:
        raise InputError(None, f"--rewarm-ms must be >= 0, got {args.rewarm_ms}")
    if args.seq_frames < 2:
        raise InputError(None, f"--seq-frames must be >= 2, got {args.seq_frames}", "a sequence needs a pair")
    check_count(args.seq_frames, "--seq-frames", MAX_SEQUENCE_FRAMES)
    if args.threads is not None:
        check_threads(args.threads, "--threads")
    backends = _parse_list(args.backend, BACKENDS, "backend")
    for name in backends:
        engine = ENGINES.get(name)
        if engine is not None and not engine.available():
            raise BackendUnavailableError(
                None, f"--backend {name} needs {engine.requires}, which is not installed", engine.install_hint
            )
    model_dir = resolve_model(args.model)
    manifest = load_manifest(model_dir)
    where = Path(manifest.root or model_dir) / MANIFEST_NAME
    if args.precision is None:
        precisions = [p for p in PRECISIONS if p in manifest.graphs]
    else:
        precisions = _parse_list(args.precision, PRECISION_CHOICES, "precision")
        for p in precisions:
            if p not in manifest.graphs and p != AUTO:
                raise InputError(
                    where,
                    f"no {p} graphs in this model directory",
                    f"precisions present: {', '.join(manifest.graphs)}; export with --precision fp32,int8",
                )
    explicit_tasks = args.tasks is not None
    tasks = _parse_list(args.tasks, BENCH_TASKS, "task") if explicit_tasks else list(BENCH_TASKS)
    tasks = [t for t in BENCH_TASKS if t in tasks]  # canonical order
    skipped = []
    for task in list(tasks):
        for p in precisions:
            missing = [g for g in TASK_GRAPHS[task] if g not in manifest.graph_names(p)]
            if not missing:
                continue
            if explicit_tasks:
                hint = (
                    "resflownet needs a stage 'flow' checkpoint at export time"
                    if "resflownet" in missing
                    else f"graphs present: {', '.join(manifest.graph_names(p))}"
                )
                raise InputError(
                    where,
                    f"task {task} needs the {', '.join(missing)} graph, which the {p} set of this model lacks",
                    hint,
                )
            tasks.remove(task)
            skipped.append({"task": task, "precision": p, "reason": f"model has no {', '.join(missing)} graph"})
            break
    return {
        "model_dir": model_dir,
        "manifest": manifest,
        "precisions": precisions,
        "tasks": tasks,
        "modes": _parse_list(args.modes, MODES, "mode"),
        "batches": _parse_batches(args.batch),
        "backends": backends,
        "input_size": _parse_size(args.input_size),
        "skipped": skipped,
    }


# ----------------------------------------------------------------------------- inputs
# ----------------------------------------------------------------------------- run
def run(args: argparse.Namespace) -> int:
    started = time.perf_counter()
    plan = _check_args(args)
    manifest = plan["manifest"]
    log = (lambda msg: None) if args.quiet else (lambda msg: print(f"bench: {msg}", file=sys.stderr, flush=True))
    env = Environment.current().as_dict()
    load_start = load_average()
    env.update(
        {
            "cpu_flags": cpu_flags(),
            "load_average_start": load_start,
            "git_commit": git_commit(),
            "thread_env": thread_env(),
            "command": ["geonet-infer", *sys.argv[1:]],
            "model": model_summary(plan["model_dir"]),
            "input_size": list(plan["input_size"]) if plan["input_size"] else [manifest.width, manifest.height],
            "sample_frames": str(SAMPLE_FRAMES),
            "timing": {
                "warmup": args.warmup,
                "iters": args.iters,
                "block": args.block,
                "rewarm_ms": args.rewarm_ms,
                "quiet_wait": True,
                "gc_disabled": True,
                "clock": "perf_counter_ns",
                "interleaved": "all cases of one (precision, backend, batch), rotating order",
                "seq_frames": args.seq_frames,
            },
            "rss_at_start_mib": current_rss_mib(),
            "memory": {},
        }
    )
    cpus = env["usable_cpus"]
    if load_start and load_start[0] > 0.5 * cpus:
        env["busy_warning"] = f"1-min load average {load_start[0]} on {cpus} usable CPUs: other work was running"
        log(f"warning: {env['busy_warning']}; the numbers will not be representative")
    if manifest.random_init:
        log("model has RANDOM WEIGHTS (timing only)")
    need = max(args.seq_frames, manifest.seq_length + max(plan["batches"]))
    frames, camera = bench_frames(plan["input_size"], (manifest.height, manifest.width), need)
    results, skipped = [], list(plan["skipped"])
    for backend in plan["backends"]:
        for precision in plan["precisions"]:
            gc.collect()
            rss_before = current_rss_mib()
            t0 = time.perf_counter()
            predictor = load(
                plan["model_dir"],
                precision=precision,
                threads=args.threads,
                backend=backend,
                rigid_op=args.rigid_op,
                mode=args.mode,
            )
            load_s = time.perf_counter() - t0
            rss_loaded = current_rss_mib()
            graphs_mib = manifest.files_mib(precision)
            env.setdefault("threads", predictor.threads)
            env.setdefault("mode", {"name": predictor.mode, "workers": predictor.workers})
            ort_engines = [predictor.graph_set.engine(n) for n, e in predictor.engines.items() if e == OrtEngine.name]
            if ort_engines:
                env.setdefault("session_options", ort_engines[0].describe())
            for batch in plan["batches"]:
                cases, skip = build_cases(
                    predictor, plan["tasks"], plan["modes"], batch, frames, camera, args.seq_frames
                )
                skipped += [{**s, "precision": precision, "backend": backend} for s in skip]
                log(
                    f"{backend} {precision} batch {batch}: {len(cases)} cases x ({args.warmup} warm-up + "
                    f"{args.iters} timed calls)"
                )
                time_interleaved(
                    [c for _, _, c, _ in cases],
                    warmup=args.warmup,
                    iters=args.iters,
                    block=args.block,
                    rewarm_ms=args.rewarm_ms,
                )
                results += [result_row(t, m, precision, backend, batch, c, x) for t, m, c, x in cases]
            env.setdefault("engines", {})[f"{backend}/{precision}"] = {
                name: {
                    **predictor.graph_set.engine(name).describe(),
                    **({"auto": predictor.backend_choice[name]} if name in predictor.backend_choice else {}),
                    "run": predictor.graph_set.runs.get(name),  # engine, precision and why
                }
                for name in predictor.graphs
            }
            peak = peak_rss_mib()
            env["memory"][f"{backend}/{precision}"] = {
                "load_s": round(load_s, 3),
                "graph_files_mib": round(graphs_mib, 2),
                "rss_before_load_mib": rss_before,
                "rss_after_load_mib": rss_loaded,
                "rss_load_delta_mib": (rss_loaded - rss_before) if rss_loaded and rss_before else None,
                "peak_rss_mib": peak,
                "peak_rss_over_graph_files": round(peak / graphs_mib, 2) if peak and graphs_mib else None,
                "first_in_process": not env["memory"],
                "note": "process figures (getrusage peak is monotonic, freed memory is reused, not returned): "
                "only the first predictor of a process has clean numbers; run one precision per process",
            }
            del predictor, cases  # the cases' closures hold the sessions
    env["peak_rss_mib"] = peak_rss_mib()
    env["load_average_end"] = load_average()
    env["wall_s"] = round(time.perf_counter() - started, 2)
    model = env["model"]
    print(
        f"geonet-infer bench: {model['dir']} (arch {model['arch']}, graphs {manifest.height}x{manifest.width}"
        f"{', RANDOM WEIGHTS' if manifest.random_init else ''}); e2e input {env['input_size'][0]}x"
        f"{env['input_size'][1]}; {env.get('threads')} threads, {args.mode} mode; {env['cpu']} ({cpus} usable CPUs)"
    )
    print(f"isa: {env['isa']['line']}")
    print(
        f"{args.iters} timed calls per case after {args.warmup} warm-up, block-interleaved; "
        f"sequence rows per frame ({args.seq_frames} frames per call)"
    )
    print(format_table(results))
    for backend in plan["backends"]:
        for precision in plan["precisions"]:
            line = paper_line(results, precision, backend)
            if line:
                print(line)
    for key, mem in env["memory"].items():
        nan = float("nan")
        print(
            f"memory {key}: graph files {mem['graph_files_mib']:.1f} MiB, RSS after load "
            f"{mem['rss_after_load_mib'] or nan:.1f} MiB, process peak {mem['peak_rss_mib'] or nan:.1f} MiB"
            + ("" if mem["first_in_process"] else " (not the first predictor of this process)")
        )
    for s in skipped:
        print(
            f"skipped {s['task']}{'/' + s['mode'] if 'mode' in s else ''} {s.get('precision', '')} "
            f"batch {s.get('batch', '-')}: {s['reason']}"
        )
    if args.json is not None:
        record = {"environment": env, "results": results, "skipped": skipped}
        with atomic_write(args.json) as tmp:
            tmp.write_text(json.dumps(record, indent=2) + "\n")
        print(f"JSON -> {args.json}")
    return 0

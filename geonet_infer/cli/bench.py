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
``--input-size``, with their intrinsics scaled alike. Timing: ``geonet_infer.timing``
(warm-up, GC off, block-interleaved over all cases of one precision and batch).
"""

from __future__ import annotations

import argparse
import collections
import gc
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from geonet_infer.cascade import flow_to_input, graph_intrinsics, next_source_position, snippet_indices
from geonet_infer.cli.common import add_model_args
from geonet_infer.cli.info import environment, model_summary
from geonet_infer.conventions import scale_intrinsics
from geonet_infer.engines import BACKENDS, openvino_available
from geonet_infer.errors import InputError
from geonet_infer.io.atomic import atomic_write
from geonet_infer.io.calib import Camera, read_camera
from geonet_infer.io.images import list_images, read_image
from geonet_infer.manifest import MANIFEST_NAME, PRECISIONS, load_manifest
from geonet_infer.models import resolve_model
from geonet_infer.predictor import Predictor, load
from geonet_infer.samples import SAMPLE_CALIB, SAMPLE_FRAMES
from geonet_infer.timing import Case, current_rss_mib, load_average, peak_rss_mib, time_interleaved

TASKS = ("depth", "pose", "rigid_flow", "resflow", "flow", "sequence")
MODES = ("graph", "e2e")
DEFAULT_INPUT_SIZE = (1242, 375)  # (W, H) of KITTI raw frames
# Graphs each task needs; flow and sequence also use resflownet when the model has it.
TASK_GRAPHS = {
    "depth": ("depthnet",),
    "pose": ("posenet",),
    "rigid_flow": ("rigidflow",),
    "resflow": ("resflownet",),
    "flow": ("depthnet", "posenet", "rigidflow"),
    "sequence": ("depthnet", "posenet", "rigidflow"),
}
PER_SNIPPET_TASKS = ("pose", "flow")  # e2e: Predictor.pose/flow take one snippet (batch 1 only)
CPU_FLAGS = (
    "avx2",
    "fma",
    "avx512f",
    "avx512bw",
    "avx512_vnni",
    "avx_vnni",
    "avx512_bf16",
    "amx_tile",
    "amx_int8",
    "amx_bf16",
)
THREAD_ENV = (
    "ORT_INTRA_OP_NUM_THREADS",
    "ORT_INTER_OP_NUM_THREADS",
    "OMP_NUM_THREADS",
    "OMP_WAIT_POLICY",
    "MKL_NUM_THREADS",
    "OPENBLAS_NUM_THREADS",
)


def add_parser(sub) -> None:
    parser = sub.add_parser(
        "bench",
        help="latency of each stage (network only and end to end), table + JSON",
        description="Time DepthNet, PoseNet, the rigid-flow op, ResFlowNet, the flow cascade for one pair and "
        "the per-frame cost of a sequence, each network-only ('graph') and end to end from uint8 "
        "frames ('e2e'), on the bundled sample frames. Reports p50/p90/p99, mean +- std (ms) and "
        "items/s after warm-up; cases of one precision and batch are timed block-interleaved.",
        epilog="e2e pose and flow exist for batch 1 only (Predictor.pose/flow take one snippet). "
        "sequence rows are per frame. Bad input (unknown task, precision, backend; a model without "
        "the needed graph; --iters < 1) -> one line on stderr, exit 2.",
        conflict_handler="resolve",
    )
    add_model_args(parser)
    group = parser.add_argument_group("benchmark")
    # Replaces add_model_args' single --precision (conflict_handler="resolve").
    group.add_argument(
        "--precision",
        default=None,
        metavar="LIST",
        help=f"comma list of {', '.join(PRECISIONS)} (default: every precision the model has)",
    )
    group.add_argument("--batch", default="1", metavar="LIST", help="comma list of batch sizes (default: 1)")
    group.add_argument(
        "--tasks",
        default=None,
        metavar="LIST",
        help=f"comma list of {', '.join(TASKS)} (default: all the model's graphs allow)",
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
        help=f"comma list of inference backends: {', '.join(BACKENDS)} (default: {BACKENDS[0]}; "
        "openvino needs the [openvino] extra; auto keeps the faster engine per graph)",
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
        help="frames per timed sequence call (default: 8; the last frame has no flow)",
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
        out.append(value)
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
    backends = _parse_list(args.backend, BACKENDS, "backend")
    if "openvino" in backends and not openvino_available():
        raise InputError(
            None,
            "--backend openvino needs the OpenVINO runtime, which is not installed",
            "pip install 'geonet-infer[openvino]'",
        )
    model_dir = resolve_model(args.model)
    manifest = load_manifest(model_dir)
    where = Path(manifest.root or model_dir) / MANIFEST_NAME
    if args.precision is None:
        precisions = [p for p in PRECISIONS if p in manifest.graphs]
    else:
        precisions = _parse_list(args.precision, PRECISIONS, "precision")
        for p in precisions:
            if p not in manifest.graphs:
                raise InputError(
                    where,
                    f"no {p} graphs in this model directory",
                    f"precisions present: {', '.join(manifest.graphs)}; export with --precision fp32,int8",
                )
    explicit_tasks = args.tasks is not None
    tasks = _parse_list(args.tasks, TASKS, "task") if explicit_tasks else list(TASKS)
    tasks = [t for t in TASKS if t in tasks]  # canonical order
    skipped = []
    for task in list(tasks):
        for p in precisions:
            missing = [g for g in TASK_GRAPHS[task] if g not in manifest.graphs[p]]
            if not missing:
                continue
            if explicit_tasks:
                hint = (
                    "resflownet needs a stage 'flow' checkpoint at export time"
                    if "resflownet" in missing
                    else f"graphs present: {', '.join(manifest.graphs[p])}"
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
def _pingpong(n: int, count: int) -> list[int]:
    """``count`` indices into n frames that run forward then back (no jump between neighbours)."""
    if n == 1:
        return [0] * count
    cycle = list(range(n)) + list(range(n - 2, 0, -1))
    return [cycle[i % len(cycle)] for i in range(count)]


def bench_frames(
    input_size: tuple[int, int] | None, graph_size: tuple[int, int], count: int
) -> tuple[list[np.ndarray], Camera]:
    """``count`` consecutive uint8 RGB frames of the bundled sample at ``input_size`` (W, H) and their camera.

    ``input_size`` None = the graphs' size (H, W given as ``graph_size``): no resize at all.
    """
    base = [read_image(f) for f in list_images(SAMPLE_FRAMES)]
    h0, w0 = base[0].shape[:2]
    width, height = input_size if input_size is not None else (graph_size[1], graph_size[0])
    if (height, width) != (h0, w0):
        base = [cv2.resize(f, (width, height), interpolation=cv2.INTER_LINEAR) for f in base]
    K = scale_intrinsics(read_camera(SAMPLE_CALIB).K, width / w0, height / h0)
    camera = Camera(K, None, (width, height), f"bundled sample calib.txt scaled to {width}x{height}")
    return [base[i] for i in _pingpong(len(base), count)], camera


# ----------------------------------------------------------------------------- graphs
class Graphs:
    """Calls the predictor's engines directly: feeds must be C-contiguous float32."""

    def __init__(self, predictor: Predictor):
        self.engines = {n: predictor.graph_set.engine(n) for n in predictor.graphs}

    def __contains__(self, name: str) -> bool:
        return name in self.engines

    def __call__(self, name: str, **feeds: np.ndarray) -> dict[str, np.ndarray]:
        return self.engines[name].run(feeds)


def _c(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.float32)


def snippet_feeds(x: np.ndarray, targets: list[int], n: int, L: int) -> dict[str, np.ndarray]:
    """Prepared network inputs for the pairs target t -> t+1 (frames x: (n, 3, h, w) normalised)."""
    orders = [snippet_indices(t, n, L) for t in targets]
    src = next_source_position(L)
    return {
        "target": _c(x[[o[0] for o in orders]]),
        "source": _c(x[[o[1 + src] for o in orders]]),
        "snippet": _c(np.stack([np.concatenate([x[i] for i in o]) for o in orders])),
    }


def net_cascade(
    g: Graphs, feeds: dict, K_graph: np.ndarray, src_pos: int, disparity: np.ndarray | None = None
) -> dict[str, np.ndarray]:
    """depth -> pose -> rigid-flow op -> ResFlowNet on prepared feeds; returns every intermediate."""
    if disparity is None:
        disparity = g("depthnet", image=feeds["target"])["disparity"]
    pose = _c(g("posenet", snippet=feeds["snippet"])["pose"][:, src_pos])
    rigid = g(
        "rigidflow",
        depth=1.0 / disparity,
        pose=pose,
        intrinsics=K_graph,
        target=feeds["target"],
        source=feeds["source"],
    )
    flow_input = np.concatenate(
        [feeds["target"], feeds["source"], rigid["warped"], rigid["rigid_flow"], rigid["error"]], axis=1
    )
    out = {"disparity": disparity, "pose": pose, "flow_input": flow_input, **rigid}
    if "resflownet" in g:
        out.update(g("resflownet", flow_input=flow_input))
    return out


# ----------------------------------------------------------------------------- cases
def build_cases(
    predictor: Predictor,
    tasks: list[str],
    modes: list[str],
    batch: int,
    frames: list[np.ndarray],
    camera: Camera,
    seq_frames: int,
) -> tuple[list[tuple[str, str, Case, dict]], list[dict]]:
    """The timed callables for one predictor and batch -> ([(task, mode, case, extra)], skipped)."""
    g = Graphs(predictor)
    spec = predictor.spec
    L, k = spec.seq_length, spec.seq_length // 2
    src_pos = next_source_position(L)
    size = frames[0].shape[:2]
    n = len(frames)
    x = np.stack([spec.to_network(f) for f in frames])  # (n, 3, h, w) prepared once
    targets = [k + b for b in range(batch)]  # full snippets for every pair
    feeds = snippet_feeds(x, targets, n, L)
    K_graph = _c(np.repeat(graph_intrinsics(camera.K, size, spec)[None], batch, axis=0))
    ref = net_cascade(g, feeds, K_graph, src_pos)  # realistic inputs of the single-graph cases
    rigid_feeds = {
        "depth": _c(1.0 / ref["disparity"]),
        "pose": ref["pose"],
        "intrinsics": K_graph,
        "target": feeds["target"],
        "source": feeds["source"],
    }
    flow_input = _c(ref["flow_input"])
    tgt_frames = [frames[snippet_indices(t, n, L)[0]] for t in targets]
    src_frames = [frames[snippet_indices(t, n, L)[1 + src_pos]] for t in targets]
    snippet = frames[0:L]
    seq = frames[:seq_frames]

    # sequence, network only: the graph calls iter_sequence makes, on prepared frames
    seq_chunks = []
    for t0 in range(0, seq_frames, batch):
        chunk = list(range(t0, min(t0 + batch, seq_frames)))
        paired = [t for t in chunk if t + 1 < seq_frames]
        sf = snippet_feeds(x[:seq_frames], paired, seq_frames, L) if paired else None
        kg = _c(np.repeat(K_graph[:1], len(paired), axis=0)) if paired else None
        seq_chunks.append((_c(x[chunk]), len(paired), sf, kg))

    def sequence_graph():
        for images, n_paired, sf, kg in seq_chunks:
            disparity = g("depthnet", image=images)["disparity"]
            if n_paired:
                net_cascade(g, sf, kg, src_pos, disparity=_c(disparity[:n_paired]))

    def rigid_e2e():
        t = np.stack([spec.to_network(f) for f in tgt_frames])
        s = np.stack([spec.to_network(f) for f in src_frames])
        kg = _c(np.repeat(graph_intrinsics(camera.K, size, spec)[None], batch, axis=0))
        out = g("rigidflow", depth=rigid_feeds["depth"], pose=rigid_feeds["pose"], intrinsics=kg, target=t, source=s)
        return [flow_to_input(f, size) for f in out["rigid_flow"]]

    def resflow_e2e():
        out = g("resflownet", flow_input=flow_input)
        return [(flow_to_input(f, size), flow_to_input(r, size)) for f, r in zip(out["flow"], out["residual_flow"])]

    def depth_e2e():
        return predictor.depth(frames[0]) if batch == 1 else predictor.depth(frames[:batch])

    flow_graphs = ["depthnet", "posenet", "rigidflow"] + (["resflownet"] if "resflownet" in g else [])
    calls = {
        ("depth", "graph"): lambda: g("depthnet", image=feeds["target"]),
        ("depth", "e2e"): depth_e2e,
        ("pose", "graph"): lambda: g("posenet", snippet=feeds["snippet"]),
        ("pose", "e2e"): lambda: predictor.pose(snippet, camera),
        ("rigid_flow", "graph"): lambda: g("rigidflow", **rigid_feeds),
        ("rigid_flow", "e2e"): rigid_e2e,
        ("resflow", "graph"): lambda: g("resflownet", flow_input=flow_input),
        ("resflow", "e2e"): resflow_e2e,
        ("flow", "graph"): lambda: net_cascade(g, feeds, K_graph, src_pos),
        ("flow", "e2e"): lambda: predictor.flow(snippet, camera),
        ("sequence", "graph"): sequence_graph,
        ("sequence", "e2e"): lambda: collections.deque(
            predictor.iter_sequence(seq, camera, batch_size=batch), maxlen=0
        ),
    }
    graphs_of = {
        "depth": ["depthnet"],
        "pose": ["posenet"],
        "rigid_flow": ["rigidflow"],
        "resflow": ["resflownet"],
        "flow": flow_graphs,
        "sequence": flow_graphs,
    }
    cases, skipped = [], []
    for task in tasks:
        for mode in modes:
            if mode == "e2e" and task in PER_SNIPPET_TASKS and batch > 1:
                skipped.append(
                    {
                        "task": task,
                        "mode": mode,
                        "batch": batch,
                        "reason": f"Predictor.{task}() takes one snippet (batch 1); batched {task} "
                        "runs inside the sequence task",
                    }
                )
                continue
            items = seq_frames if task == "sequence" else batch
            extra = {
                "graphs": graphs_of[task],
                "items_per_call": items,
                "unit": "frame" if task == "sequence" else "call",
            }
            if task == "sequence":
                extra.update(frames=seq_frames, pairs=seq_frames - 1)
            cases.append((task, mode, Case(f"{task}/{mode}", calls[(task, mode)], items), extra))
    return cases, skipped


# ----------------------------------------------------------------------------- environment
def cpu_flags() -> list[str]:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("flags"):
                have = set(line.split(":", 1)[1].split())
                return [f for f in CPU_FLAGS if f in have]
    except OSError:
        pass
    return []


def _git_commit() -> str | None:
    root = Path(__file__).resolve().parents[2]
    if not (root / ".git").exists():
        return None
    try:
        out = subprocess.run(
            ["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True, timeout=5, check=False
        )
        return out.stdout.strip() or None
    except (OSError, subprocess.SubprocessError):
        return None


# ----------------------------------------------------------------------------- output
def _row(task: str, mode: str, precision: str, backend: str, batch: int, case: Case, extra: dict) -> dict:
    stats = case.stats()
    if task == "sequence":
        per_frame = stats.scaled(1.0 / extra["frames"])
        row = per_frame.as_dict()
        row["per_pair_p50_ms"] = stats.p50_ms / extra["pairs"]
        row["per_item_p50_ms"] = per_frame.p50_ms
    else:
        row = stats.as_dict()
        row["per_item_p50_ms"] = stats.p50_ms / batch
    row["first_call_ms"] = case.first_call_ms
    return {"task": task, "mode": mode, "precision": precision, "backend": backend, "batch": batch, **row, **extra}


def format_table(results: list[dict]) -> str:
    head = (
        f"{'task':<11} {'mode':<5} {'prec':<4} {'backend':<11} {'batch':>5} {'p50 ms':>9} {'p90 ms':>9} "
        f"{'p99 ms':>9} {'mean +- std ms':>17} {'ms/item':>9} {'items/s':>8}"
    )
    lines = [head, "-" * len(head)]
    for r in results:
        unit = "/frame" if r["unit"] == "frame" else ""
        lines.append(
            f"{r['task']:<11} {r['mode']:<5} {r['precision']:<4} {r['backend']:<11} {r['batch']:>5} "
            f"{r['p50_ms']:>9.2f} {r['p90_ms']:>9.2f} {r['p99_ms']:>9.2f} "
            f"{r['mean_ms']:>8.2f} +- {r['std_ms']:<6.2f} {r['per_item_p50_ms']:>9.2f} {r['fps']:>8.1f}"
            + (f"  ({unit})" if unit else "")
        )
    return "\n".join(lines)


def paper_line(results: list[dict], precision: str, backend: str) -> str | None:
    """'per example' like the paper (batch 1, p50): depth, flow per pair in a sequence, pose."""
    pick = {
        (r["task"], r["mode"]): r
        for r in results
        if r["precision"] == precision and r["backend"] == backend and r["batch"] == 1
    }
    parts = []
    for label, key, field in (
        ("depth", ("depth", "e2e"), "p50_ms"),
        ("flow/pair (sequence)", ("sequence", "e2e"), "per_pair_p50_ms"),
        ("flow (one pair)", ("flow", "e2e"), "p50_ms"),
        ("pose", ("pose", "e2e"), "p50_ms"),
    ):
        if key in pick:
            parts.append(f"{label} {pick[key][field]:.1f} ms")
    return f"per example, {precision}, {backend}, batch 1, e2e p50: " + ", ".join(parts) if parts else None


# ----------------------------------------------------------------------------- run
def run(args: argparse.Namespace) -> int:
    started = time.perf_counter()
    plan = _check_args(args)
    manifest = plan["manifest"]
    log = (lambda msg: None) if args.quiet else (lambda msg: print(f"bench: {msg}", file=sys.stderr, flush=True))
    env = environment()
    load_start = load_average()
    env.update(
        {
            "cpu_flags": cpu_flags(),
            "load_average_start": load_start,
            "git_commit": _git_commit(),
            "thread_env": {k: os.environ.get(k) for k in THREAD_ENV},
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
            predictor = load(plan["model_dir"], precision=precision, threads=args.threads, backend=backend)
            load_s = time.perf_counter() - t0
            rss_loaded = current_rss_mib()
            graphs_mib = manifest.files_mib(precision)
            env.setdefault("threads", predictor.threads)
            ort_engines = [predictor.graph_set.engine(n) for n, e in predictor.engines.items() if e == "onnxruntime"]
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
                results += [_row(t, m, precision, backend, batch, c, x) for t, m, c, x in cases]
            env.setdefault("engines", {})[f"{backend}/{precision}"] = {
                name: {
                    **predictor.graph_set.engine(name).describe(),
                    **({"auto": predictor.backend_choice[name]} if name in predictor.backend_choice else {}),
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
        f"{env['input_size'][1]}; {env.get('threads')} threads; {env['cpu']} ({cpus} usable CPUs)"
    )
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
        with atomic_write(args.json) as tmp:
            tmp.write_text(json.dumps({"environment": env, "results": results, "skipped": skipped}, indent=2) + "\n")
        print(f"JSON -> {args.json}")
    return 0

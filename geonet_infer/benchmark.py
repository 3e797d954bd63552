"""The benchmark library behind ``geonet-infer bench``: its cases, the rows it reports and the
record of the machine (:class:`Environment`). The CLI (:mod:`geonet_infer.cli.bench`) parses
arguments and prints; ``benchmarks/peers.py`` builds on the same pieces.

"""

from __future__ import annotations

import collections
import os
import platform
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np

from geonet_infer import __version__
from geonet_infer.cascade import flow_to_input, graph_intrinsics, run_cascade
from geonet_infer.conventions import scale_intrinsics
from geonet_infer.cpu import cpu_info, isa_line
from geonet_infer.engines import ENGINES, check_graphs, usable_cpus
from geonet_infer.io.calib import Camera, read_camera
from geonet_infer.io.images import list_images, read_image
from geonet_infer.manifest import ModelCard, load_manifest
from geonet_infer.models import bundled_models, resolve_model
from geonet_infer.predictor import TASK_GRAPHS as MODEL_TASK_GRAPHS  # depth, pose, flow (bench has its own tasks)
from geonet_infer.predictor import Predictor, missing_graphs
from geonet_infer.samples import SAMPLE_CALIB, SAMPLE_FRAMES
from geonet_infer.timing import Case

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


# ----------------------------------------------------------------------------- cases
def cascade_feeds(
    predictor: Predictor, x: np.ndarray, camera: Camera, size: tuple[int, int], batch: int
) -> dict[str, dict[str, np.ndarray]]:
    """Each graph's inputs as the cascade feeds it, for ``batch`` pairs of the prepared frames
    ``x`` (n, 3, h, w) (input size ``size``, n >= seq_length + batch - 1): realistic inputs for
    timing one graph alone (graph -> {input name: float32 array})."""
    L, k = predictor.seq_length, predictor.seq_length // 2
    feeds: dict[str, dict[str, np.ndarray]] = {}
    snippets = _snippets(x, [k + b for b in range(batch)], L)
    names = predictor.graphs
    if "posenet" in names:  # a partial model runs as far as its graphs go
        flow = "depthnet" in names and "rigidflow" in names
        run_cascade(
            predictor.graph_set, predictor.spec, snippets, [k] * batch, camera.K, size, with_flow=flow, feeds=feeds
        )
    if "depthnet" in names:
        feeds.setdefault("depthnet", {"image": np.ascontiguousarray(snippets[:, k])})  # the targets, as the cascade
    return feeds


def _snippets(x: np.ndarray, targets: list[int], L: int) -> np.ndarray:
    """(len(targets), L, 3, h, w) snippets in temporal order centred on each target (ends clipped)."""
    n, k = len(x), L // 2
    return np.stack([x[[min(max(i, 0), n - 1) for i in range(t - k, t + k + 1)]] for t in targets])


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
    graphs = predictor.graph_set
    spec = predictor.spec
    L, k = spec.seq_length, spec.seq_length // 2
    size = frames[0].shape[:2]
    x = np.stack([spec.to_network(f) for f in frames])  # (n, 3, h, w) prepared once
    targets = [k + b for b in range(batch)]  # full snippets for every pair
    snippets = _snippets(x, targets, L)
    feeds = cascade_feeds(predictor, x, camera, size, batch)
    tgt_frames = [frames[t] for t in targets]
    src_frames = [frames[t + 1] for t in targets]
    snippet = frames[0:L]
    seq = frames[:seq_frames]

    # sequence, network only: the graph calls iter_sequence makes, on prepared frames
    seq_chunks = []
    for t0 in range(0, seq_frames, batch):
        chunk = list(range(t0, min(t0 + batch, seq_frames)))
        paired = [t for t in chunk if t + 1 < seq_frames]
        seq_chunks.append((x[chunk], len(paired), _snippets(x[:seq_frames], paired, L) if paired else None))

    def sequence_graph():
        for images, n_paired, chunk_snippets in seq_chunks:
            disparity = graphs.run("depthnet", image=images)["disparity"][:, 0]
            if n_paired:
                run_cascade(
                    graphs, spec, chunk_snippets, [k] * n_paired, camera.K, size, disparity=disparity[:n_paired]
                )

    def rigid_e2e():
        t = np.stack([spec.to_network(f) for f in tgt_frames])
        s = np.stack([spec.to_network(f) for f in src_frames])
        kg = np.repeat(graph_intrinsics(camera.K, size, spec)[None], batch, axis=0)
        rigid = feeds["rigidflow"]
        out = graphs.run("rigidflow", depth=rigid["depth"], pose=rigid["pose"], intrinsics=kg, target=t, source=s)
        return [flow_to_input(f, size) for f in out["rigid_flow"]]

    def resflow_e2e():
        out = graphs.run("resflownet", **feeds["resflownet"])
        return [(flow_to_input(f, size), flow_to_input(r, size)) for f, r in zip(out["flow"], out["residual_flow"])]

    def depth_e2e():
        return predictor.depth(frames[0]) if batch == 1 else predictor.depth(frames[:batch])

    flow_graphs = ["depthnet", "posenet", "rigidflow"] + (["resflownet"] if "resflownet" in graphs else [])
    engines = {name: graphs.engine(name) for name in graphs.names}  # graph mode: the engines alone
    calls = {
        ("depth", "graph"): lambda: engines["depthnet"].run(feeds["depthnet"]),
        ("depth", "e2e"): depth_e2e,
        ("pose", "graph"): lambda: engines["posenet"].run(feeds["posenet"]),
        ("pose", "e2e"): lambda: predictor.pose(snippet, camera),
        ("rigid_flow", "graph"): lambda: engines["rigidflow"].run(feeds["rigidflow"]),
        ("rigid_flow", "e2e"): rigid_e2e,
        ("resflow", "graph"): lambda: engines["resflownet"].run(feeds["resflownet"]),
        ("resflow", "e2e"): resflow_e2e,
        ("flow", "graph"): lambda: run_cascade(graphs, spec, snippets, [k] * batch, camera.K, size),
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


# ----------------------------------------------------------------------------- speed targets
# The project's speed targets (issue 30) that one bench run measures, batch 1, p50, the e2e ones at
# KITTI size (DEFAULT_INPUT_SIZE): key -> (what, goal, "max" = at most / "min" = at least). 1-4 are
# for the small cascade, 7 for the resnet50 (paper) networks. benchmarks/speed_targets.py adds
# predict's frames/s and memory, and measures an older revision in the same run.
SPEED_TARGETS: dict[str, tuple[str, float, str]] = {
    "1a_best_engine_ms": ("small cascade, sequence, per frame, e2e 1242x375, best engine (ms)", 8, "max"),
    "1b_onnxruntime_ms": ("same, onnxruntime only (ms)", 12, "max"),
    "2_pre_post_ms": ("pre- and post-processing per frame, e2e - graph (ms)", 1.5, "max"),
    "3_rigid_op_ms": ("rigid-flow op on onnxruntime's host, fastest form (ms)", 1.0, "max"),
    "4_int8_speedup_onnxruntime": ("INT8 cascade vs FP32 on onnxruntime (x faster)", 1.5, "min"),
    "7a_resnet50_int8_depth_ms": ("resnet50, INT8, best engine: DepthNet graph (ms)", 19, "max"),
    "7b_resnet50_int8_flow_pair_ms": ("resnet50, INT8, best engine: flow per pair in a sequence, e2e (ms)", 45, "max"),
}


def target_distance(value: float, goal: float, sense: str) -> float:
    """value / goal for an upper bound, goal / value for a lower one: 1 or less is met."""
    return value / goal if sense == "max" else goal / value


def speed_target_values(results: list[dict], arch: str, kitti_size: bool = True) -> dict[str, float]:
    """This run's value for each target it measured (``results``: bench rows). ``kitti_size``: the
    e2e rows were measured at 1242x375 (otherwise only the graph-only targets are given)."""
    rows = {(r["task"], r["mode"], r["precision"], r["backend"]): r for r in results if r["batch"] == 1}
    engines = sorted({key[3] for key in rows})
    both = ("fp32", "int8")

    def best(task: str, mode: str, precisions: tuple[str, ...], backends: list[str], field: str = "p50_ms"):
        found = [rows[(task, mode, p, b)][field] for p in precisions for b in backends if (task, mode, p, b) in rows]
        return min(found) if found else None

    values: dict[str, float | None] = {}
    if arch == "resnet50":
        values["7a_resnet50_int8_depth_ms"] = best("depth", "graph", ("int8",), engines)
        if kitti_size:
            values["7b_resnet50_int8_flow_pair_ms"] = best("sequence", "e2e", ("int8",), engines, "per_pair_p50_ms")
    else:
        values["3_rigid_op_ms"] = best("rigid_flow", "graph", ("fp32",), ["onnxruntime"])
        if kitti_size:
            values["1a_best_engine_ms"] = best("sequence", "e2e", both, engines)
            values["1b_onnxruntime_ms"] = best("sequence", "e2e", both, ["onnxruntime"])
            pre_post = [
                rows[("sequence", "e2e", p, b)]["p50_ms"] - rows[("sequence", "graph", p, b)]["p50_ms"]
                for p in both
                for b in engines
                if ("sequence", "e2e", p, b) in rows and ("sequence", "graph", p, b) in rows
            ]
            values["2_pre_post_ms"] = min(pre_post) if pre_post else None
            fp32, int8 = (best("sequence", "e2e", (p,), ["onnxruntime"]) for p in both)
            values["4_int8_speedup_onnxruntime"] = fp32 / int8 if fp32 and int8 else None
    return {key: value for key, value in values.items() if value is not None}


def speed_targets(results: list[dict], arch: str, kitti_size: bool = True) -> dict[str, dict]:
    """{key: {what, goal, sense, value, distance}} for each target this run measured (bench --json)."""
    out = {}
    for key, value in speed_target_values(results, arch, kitti_size).items():
        what, goal, sense = SPEED_TARGETS[key]
        out[key] = {
            "what": what,
            "goal": goal,
            "sense": sense,
            "value": value,
            "distance": target_distance(value, goal, sense),
        }
    return out


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


# ----------------------------------------------------------------------------- output
def result_row(task: str, mode: str, precision: str, backend: str, batch: int, case: Case, extra: dict) -> dict:
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


# ----------------------------------------------------------------------------- environment
def cpu_model() -> str:
    return cpu_info()["model"] or platform.machine()


@dataclass(frozen=True)
class Environment:
    """The software and machine a measurement ran on (``geonet-infer info``, every bench JSON)."""

    geonet_infer: str
    python: str
    engines: dict[str, str | None]  # engine name -> its package's version (None: not installed)
    numpy: str
    opencv: str
    providers: list[str]  # onnxruntime execution providers
    platform: str
    cpu: str
    isa: dict  # geonet_infer.cpu.cpu_info(): the x86 features INT8 depends on, and the INT8 kernel
    usable_cpus: int  # affinity mask and cgroup quota (geonet_infer.engines.usable_cpus)
    default_threads: int  # threads per graph when none are given
    bundled_models: list[str]

    @classmethod
    def current(cls) -> Environment:
        import onnxruntime as ort

        cpus = usable_cpus()
        return cls(
            geonet_infer=__version__,
            python=platform.python_version(),
            engines={name: engine.version() for name, engine in ENGINES.items()},
            numpy=np.__version__,
            opencv=cv2.__version__,
            providers=ort.get_available_providers(),
            platform=platform.platform(),
            cpu=cpu_model(),
            isa={**cpu_info(), "line": isa_line()},
            usable_cpus=cpus,
            default_threads=cpus,
            bundled_models=list(bundled_models()),
        )

    def as_dict(self) -> dict:
        """The JSON record: the engines' versions as top-level keys, after "python"."""
        record = asdict(self)
        engines = record.pop("engines")
        keys = list(record)
        at = keys.index("python") + 1
        return {**{k: record[k] for k in keys[:at]}, **engines, **{k: record[k] for k in keys[at:]}}


def thread_env() -> dict[str, str | None]:
    """The environment variables that change thread counts behind our back."""
    return {k: os.environ.get(k) for k in THREAD_ENV}


# ----------------------------------------------------------------------------- model
def model_summary(model) -> dict:
    manifest = load_manifest(resolve_model(model))
    check_graphs(manifest)  # what the Predictor would refuse at load, info refuses too
    graphs = {
        p: {
            name: {
                "file": g.file,
                "sha256": g.sha256[:16],
                "opset": g.opset,
                "mib": round((manifest.root / g.file).stat().st_size / 2**20, 2),
            }
            for name, g in manifest.graphs[p].items()
        }
        for p in manifest.graphs
    }
    prov = manifest.provenance
    present = manifest.graph_names("fp32")
    tasks = {}
    for task, needed in MODEL_TASK_GRAPHS.items():
        missing = missing_graphs(task, present)
        tasks[task] = {"available": not missing, "graphs": list(needed), "missing": list(missing)}
    return {
        "dir": str(manifest.root),
        "arch": manifest.arch,
        "size": [manifest.height, manifest.width],
        "seq_length": manifest.seq_length,
        "random_init": manifest.random_init,
        "precisions": list(manifest.graphs),
        "graphs": graphs,
        "tasks": tasks,
        "provenance": {
            "checkpoint_stage": prov.checkpoint_stage,
            "checkpoint_step": prov.checkpoint_step,
            "training_command": prov.training_command,
            "data_dir": prov.data_dir,
            "git_commit": prov.git_commit,
            "export_date": prov.export_date,
        },
        "metrics": manifest.metrics,
        "model_card": card_summary(manifest.model_card),
        "int8_accuracy_delta": manifest.quantization.accuracy_delta if manifest.quantization else None,
    }


NOT_MEASURED = "not measured"


def card_summary(card: ModelCard | None) -> dict:
    """What the model was trained on and its measured scores (from the model card), or "not measured"."""
    if card is None:
        return {"trained_on": "not recorded", "real": NOT_MEASURED, "synthetic": NOT_MEASURED, "measured_in": None}
    scores = {
        key: [{**asdict(s), "verdict": s.verdict} for s in getattr(card, key)] or NOT_MEASURED
        for key in ("real", "synthetic")
    }
    return {
        "trained_on": card.trained_on,
        "synthetic_only": card.synthetic_only,
        **scores,
        "measured_in": card.measured_in,
    }

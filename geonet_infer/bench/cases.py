"""The cases of ``geonet-infer bench``: the frames it times and one timed call per (task, mode,
precision, backend, batch). The CLI (:mod:`geonet_infer.cli.bench`) parses arguments and prints;
``benchmarks/peers.py`` builds on the same pieces. Rows and tables: :mod:`geonet_infer.bench.report`;
the machine: :mod:`geonet_infer.bench.environment`.
"""

from __future__ import annotations

import collections

import cv2
import numpy as np

from geonet_infer.conventions import scale_intrinsics
from geonet_infer.core.cascade import flow_to_input, graph_intrinsics, run_cascade
from geonet_infer.core.predictor import Predictor
from geonet_infer.engines.timing import Case
from geonet_infer.io.calib import Camera, read_camera
from geonet_infer.io.images import list_images, read_image
from geonet_infer.samples import SAMPLE_CALIB, SAMPLE_FRAMES

BENCH_TASKS = ("depth", "pose", "rigid_flow", "resflow", "flow", "sequence")
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

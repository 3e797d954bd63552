"""What bounds each of issue 30's speed targets, measured: the parts of the work a target covers,
each timed alone, and how close the networks run to this machine's GEMM peak.

Used by ``experiments/speed_targets.py`` (one run, this checkout); each function measures one
thing and returns plain numbers:

* :func:`graph_macs`: multiply-accumulates of an ONNX graph's convolutions (shape inference).
* :func:`gemm_peaks`: GOP/s of large int8 and fp32 GEMMs (``torch._int_mm``, ``torch.mm``).
* :func:`pre_post_ms`: the cascade's own pre- and post-processing of one KITTI frame.
* :func:`rigid_op_parts_ms`: the numpy rigid-flow op's three steps at the network size.
* :func:`onnxruntime_int8_profile`: each graph fp32 vs int8 on onnxruntime, and where int8's time goes.
* :func:`int8_flow_sensitivity`: flow EPE with each network kept in fp32 (which one costs the accuracy).
"""

from __future__ import annotations

import json
import statistics
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

from geonet_infer.models import resolve_model
from geonet_infer.models.manifest import load_manifest

SMALL = "small_synth"


def median_ms(fn, calls: int = 15) -> float:
    """Median wall ms of ``fn()`` over ``calls`` calls after one warm-up call."""
    fn()
    times = []
    for _ in range(calls):
        started = time.perf_counter()
        fn()
        times.append((time.perf_counter() - started) * 1e3)
    return statistics.median(times)


def graph_macs(path: Path, skip_zero_taps: bool = False) -> int:
    """Multiply-accumulates of one run of the graph's Conv and ConvTranspose nodes (batch 1).

    ``skip_zero_taps``: a Conv whose weight is in the file counts only its non-zero taps. The zeros of a
    layer written in another form (DepthNet's finest level in :mod:`export.phase_form`: up to 4x the taps,
    the same function) are no work of the model, so a share of the peak must not count them; trained
    weights have no other exact zeros (random ones may: the peers' counts keep every tap)."""
    import onnx
    from onnx import numpy_helper

    model = onnx.shape_inference.infer_shapes(onnx.load(str(path)))
    shapes = {}
    for value in [*model.graph.value_info, *model.graph.input, *model.graph.output]:
        dims = value.type.tensor_type.shape.dim
        shapes[value.name] = [d.dim_value if d.HasField("dim_value") else 1 for d in dims]  # batch "B": 1
    shapes.update({init.name: list(init.dims) for init in model.graph.initializer})
    weights = {init.name: init for init in model.graph.initializer}
    macs = 0
    for node in model.graph.node:
        if node.op_type not in ("Conv", "ConvTranspose"):
            continue
        kernel = shapes[node.input[1]]  # Conv (Cout, Cin/g, kh, kw); ConvTranspose (Cin, Cout/g, kh, kw)
        if node.op_type == "Conv":
            taps = int(np.prod(kernel))  # of all output channels, at each output pixel
            if skip_zero_taps and node.input[1] in weights:
                taps = int(np.count_nonzero(numpy_helper.to_array(weights[node.input[1]])))
            macs += int(np.prod(shapes[node.output[0]])) // kernel[0] * taps
        else:
            macs += int(np.prod(shapes[node.input[0]])) * int(np.prod(kernel[1:]))
    return macs


def gemm_peaks(threads: int, n: int = 2048, reps: int = 5) -> dict[str, float]:
    """Best GOP/s of n^3 GEMMs on ``threads`` threads: int8 (s8 x s8 -> s32) and fp32."""
    import torch

    torch.set_num_threads(threads)
    rng = np.random.default_rng(0)
    fp32 = torch.from_numpy(rng.random((n, n), dtype=np.float32))
    int8 = torch.randint(-128, 127, (n, n), dtype=torch.int8)
    peaks = {}
    for name, fn in (("int8_gops", lambda: torch._int_mm(int8, int8)), ("fp32_gflops", lambda: torch.mm(fp32, fp32))):
        fn()
        best = min(_seconds(fn) for _ in range(reps))
        peaks[name] = 2.0 * n**3 / best / 1e9
    return peaks


def _seconds(fn) -> float:
    started = time.perf_counter()
    fn()
    return time.perf_counter() - started


def sequence_macs_per_frame(model_dir: Path) -> int:
    """Convolution MACs the cascade runs per frame of a long sequence: DepthNet once per frame,
    PoseNet and ResFlowNet once per pair."""
    manifest = load_manifest(model_dir)
    return sum(
        graph_macs(manifest.path(name, "fp32"), skip_zero_taps=True) for name in ("depthnet", "posenet", "resflownet")
    )


def pre_post_ms(frame: Path) -> dict[str, float]:
    """Single-thread ms of the sequence's per-frame work outside the graphs, on one KITTI frame:
    the input to the network (resize, normalise) and the outputs back to the input size."""
    import cv2

    from geonet_infer.core.cascade import InputSpec, disparity_to_input, flow_to_input
    from geonet_infer.io.images import read_image

    cv2.setNumThreads(1)
    spec = InputSpec.from_manifest(load_manifest(resolve_model(SMALL)))
    rgb = read_image(frame)
    size = rgb.shape[:2]
    rng = np.random.default_rng(0)
    disparity = rng.uniform(0.01, 0.5, (spec.height, spec.width)).astype(np.float32)
    flow = rng.normal(0, 3, (2, spec.height, spec.width)).astype(np.float32)
    return {
        "to_network_ms": median_ms(lambda: spec.to_network(rgb)),
        "depth_to_input_ms": median_ms(lambda: disparity_to_input(disparity, size)),
        "flow_to_input_ms": median_ms(lambda: flow_to_input(flow, size)),
    }


def rigid_op_parts_ms() -> dict[str, float]:
    """Single-thread ms of the numpy rigid-flow op's steps at the bundled model's size (a plane 5-50 m
    away, the camera moving 0.3 m forward and turning slightly)."""
    import cv2

    from geonet_infer.core import rigid

    cv2.setNumThreads(1)
    manifest = load_manifest(resolve_model(SMALL))
    height, width = manifest.height, manifest.width
    rng = np.random.default_rng(0)
    depth = np.linspace(5, 50, height, dtype=np.float32)[:, None].repeat(width, 1)
    K = np.array([[0.58 * width, 0, width / 2], [0, 1.9 * height, height / 2], [0, 0, 1]], np.float32)
    pose = np.array([0.0, 0.0, 0.3, 0.0, 0.01, 0.0], np.float32)
    T = rigid.pose_to_matrix(pose)
    source, target = (rng.uniform(-1, 1, (3, height, width)).astype(np.float32) for _ in range(2))
    ws = rigid.Workspace()
    flow = rigid.rigid_flow(depth, T, K, ws).copy()
    warped = rigid.warp_bilinear(source, flow, ws).copy()
    op = rigid.RigidFlowOp(0.85)
    feeds = {"depth": depth[None, None], "pose": pose[None], "intrinsics": K[None]}
    feeds.update(target=target[None], source=source[None])
    return {
        "rigid_flow_ms": median_ms(lambda: rigid.rigid_flow(depth, T, K, ws), 50),
        "warp_ms": median_ms(lambda: rigid.warp_bilinear(source, flow, ws), 50),
        "error_map_ms": median_ms(lambda: rigid.photometric_error_map(warped, target, 0.85, ws), 50),
        "whole_op_ms": median_ms(lambda: op.run(feeds), 50),
    }


def onnxruntime_int8_profile(model_dir: Path, threads: int = 1, runs: int = 20) -> dict:
    """Each ConvNet graph on onnxruntime at fp32 and int8 (median ms, one frame), and onnxruntime's own
    profile of the int8 graphs: ms per run by op type, summed over the three graphs."""
    import onnxruntime as ort

    from geonet_infer.engines.onnxruntime import make_session_options

    manifest = load_manifest(model_dir)
    rng = np.random.default_rng(0)
    per_graph: dict[str, dict[str, float]] = {}
    int8_ops: dict[str, float] = defaultdict(float)
    with tempfile.TemporaryDirectory(prefix="geonet_ort_profile_") as tmp:
        for name in ("depthnet", "posenet", "resflownet"):
            for precision in ("fp32", "int8"):
                options = make_session_options(threads=threads)
                if precision == "int8":
                    options.enable_profiling = True
                    options.profile_file_prefix = str(Path(tmp) / name)
                session = ort.InferenceSession(str(manifest.path(name, precision)), options)
                feeds = {
                    i.name: rng.normal(0, 0.5, [d if isinstance(d, int) else 1 for d in i.shape]).astype(np.float32)
                    for i in session.get_inputs()
                }
                per_graph.setdefault(name, {})[precision] = median_ms(lambda s=session, f=feeds: s.run(None, f), runs)
                if precision == "int8":
                    trace = json.loads(Path(session.end_profiling()).read_text())
                    for event in trace:
                        if event.get("cat") == "Node" and event["name"].endswith("_kernel_time"):
                            int8_ops[event["args"]["op_name"]] += event["dur"] / 1e3 / (runs + 1)
    total = sum(int8_ops.values())
    ops = dict(sorted(int8_ops.items(), key=lambda kv: -kv[1]))
    return {"threads": threads, "graphs_ms": per_graph, "int8_op_ms": ops, "int8_op_total_ms": total}


def int8_flow_sensitivity(repo: Path) -> dict | None:
    """Flow EPE-noc on the held-out synthetic sequences (the manifest's accuracy set) of the bundled
    int8 cascade with one group of networks swapped back to fp32; None without that data here."""
    manifest = load_manifest(resolve_model(SMALL))
    delta = (manifest.quantization.accuracy_delta if manifest.quantization else None) or {}
    synth = repo / str(delta.get("synth_dir", ""))
    prepared = synth.with_name(synth.name + "_prepared")
    if not delta or not (prepared / "heldout.txt").is_file():
        return None
    from geonet_infer.core.predictor import Predictor

    if str(repo) not in sys.path:  # run as a script, only benchmarks/ is on the path
        sys.path.insert(0, str(repo))
    from training.evaluate import evaluate_flow, heldout_sequences, onnx_flow_fn

    sequences = heldout_sequences(prepared)
    root = resolve_model(SMALL)
    fp32 = Predictor(root, "fp32")
    epe = {}
    for kept in ((), ("resflownet",), ("depthnet", "posenet"), ("depthnet", "posenet", "resflownet")):
        predictor = Predictor(root, "int8")
        for name in kept:  # an experiment, not an API: the fp32 predictor's session in the int8 cascade
            predictor.graph_set._engines[name] = fp32.graph_set.engine(name)
        result = evaluate_flow(onnx_flow_fn(predictor), synth, sequences, delta.get("stride", 1))
        epe["+".join(kept) or "none"] = result["noc"]["epe"]
    return {"fp32_kept": epe, "sequences": sequences, "pairs": result["pairs"]}

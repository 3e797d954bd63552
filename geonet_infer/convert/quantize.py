"""INT8 (QDQ) copies of the exported graphs with onnxruntime's static quantiser.

Recipe (onnx_notes.md section 2): ``quant_pre_process`` (shape inference +
ORT basic optimisation), then ``quantize_static`` in QDQ format, per-channel
int8 weights, uint8 activations (x86 recommendation of the 1.32 docstring),
``reduce_range=False`` (right for CPUs with VNNI; pass ``--reduce-range`` for
older AVX2/AVX-512 CPUs without VNNI, where u8*s8 products can saturate),
MinMax calibration by default.

Calibration inputs come from a folder of real or synthetic frames resized to
H x W with ``cv2.INTER_AREA``:

* depthnet: every frame;
* posenet: snippets of ``seq_length`` consecutive frames [target, sources];
* resflownet: 12-channel inputs made by running the *fp32* depthnet, posenet
  and rigidflow graphs on consecutive frames (target -> every source), i.e. the
  distribution ResFlowNet sees at inference.

``rigidflow`` is never quantised: it is geometry (projection, grid sampling),
not convolutions, and its output is measured in pixels. ``PLANS`` keeps parts of
the other graphs fp32 (PoseNet's matrix tail; ResFlowNet's output layer, its two finest decoder
levels and, for the small arch, its input layer: :func:`plan_for`) and
rescales ResFlowNet's fed-back flow before its Concats; the manifest records it
(``quantization.graph_notes``).
"""

from __future__ import annotations

import dataclasses
import re
import shutil
import tempfile
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import onnx

from geonet_infer.convert.frames import (  # noqa: F401  (the calibration inputs, used here and as qz.*)
    calibration_intrinsics,
    depth_feeds,
    load_frames,
    pose_feeds,
    resflow_feeds,
    snippets,
)
from geonet_infer.errors import InputError

CALIBRATION_METHODS = ("minmax", "entropy", "percentile")  # onnxruntime CalibrationMethod MinMax/Entropy/Percentile


@dataclass(frozen=True)
class GraphPlan:
    """What stays fp32 in one int8 graph, and what is rescaled before quantising."""

    float_after: tuple[str, ...] = ()  # nodes consuming these tensors stay fp32
    float_output_layer: bool = False  # output_layer_nodes stay fp32
    float_input_layer: bool = False  # input_layer_nodes stay fp32
    float_finest_levels: int = 0  # decoder_level_nodes of this many finest levels stay fp32
    equalize_concats: bool = False  # equalize_concat_inputs first


PLANS = {
    # PoseNet's 4x4 matrices are built from the pose vector with Sin/Cos/Concat; quantised,
    # they collapsed to ~identity (no motion).
    "posenet": GraphPlan(float_after=("pose",)),
    # ResFlowNet's flow is in pixels and its decoder feeds the coarser flow back beside wide
    # features; both lost ~1 px of agreement with fp32 flow. Its 12-channel input puts images
    # (+-1) beside the rigid flow (+-80 px) under one uint8 scale, and its two finest decoder
    # levels carry the sub-pixel detail: fp32 too (docs/export.md, "INT8 and flow").
    "resflownet": GraphPlan(
        float_output_layer=True, float_input_layer=True, float_finest_levels=2, equalize_concats=True
    ),
}
# Where the plan was measured: the fp32 input layer helped the small arch's trained ResFlowNet, and
# made a random-weight resnet50 ResFlowNet drift far from the official forward (tests/export/test_from_tf.py);
# no trained resnet50 weights are here to judge, so that arch keeps its input layer quantised.
INPUT_LAYER_ARCHS = ("small",)


def plan_for(graph: str, arch: str) -> GraphPlan:
    """The plan of ``graph`` (:data:`PLANS`) for a model of architecture ``arch``."""
    plan = PLANS.get(graph, GraphPlan())
    if plan.float_input_layer and arch not in INPUT_LAYER_ARCHS:
        plan = dataclasses.replace(plan, float_input_layer=False)
    return plan


@dataclass(frozen=True)
class QuantSettings:
    per_channel: bool = True
    reduce_range: bool = False
    calibrate_method: str = "minmax"  # one of CALIBRATION_METHODS
    max_frames: int = 24  # calibration frames read from the folder
    # Operator types quantised; () = every type onnxruntime quantises (Conv, Add, Concat, Resize,
    # MaxPool, ...). ("Conv",) leaves the glue between convolutions in fp32.
    op_types: tuple[str, ...] = ()

    def describe(self) -> dict:
        return {
            "method": "onnxruntime quantize_static, QDQ",
            "activation_type": "uint8",
            "weight_type": "int8",
            "per_channel": self.per_channel,
            "reduce_range": self.reduce_range,
            "calibrate_method": self.calibrate_method,
            **({"op_types": list(self.op_types)} if self.op_types else {}),
        }


def quantisable_op_types() -> tuple[str, ...]:
    """The operator types onnxruntime's quantize_static can quantise (QDQ and QLinear registries)."""
    from onnxruntime.quantization.registry import QDQRegistry, QLinearOpsRegistry

    return tuple(sorted(set(QDQRegistry) | set(QLinearOpsRegistry)))


class _ListReader:
    """CalibrationDataReader over a list of feed dicts (duck-typed: get_next / rewind)."""

    def __init__(self, feeds: Iterable[dict]):
        self.feeds = list(feeds)
        self._it = iter(self.feeds)

    def get_next(self):
        return next(self._it, None)

    def rewind(self):
        self._it = iter(self.feeds)


# ----------------------------------------------------------------------------- quantise
def output_layer_nodes(model: onnx.ModelProto) -> list[str]:
    """The layer that writes each graph output, as node names: that node, the layer it reads
    (its Conv and activation) when it is a Conv, and the Slices it takes graph inputs through.

    Kept fp32 because the outputs are in pixels: quantised, ResFlowNet's flow (about +-80 px)
    would be rounded to 0.6 px steps, and the 8-channel full-resolution features its head reads
    carry the flow's fine detail (one uint8 step of them is a fraction of a pixel at the output).
    """
    inputs = {i.name for i in model.graph.input}
    producer = {out: node for node in model.graph.node for out in node.output}
    names = []
    for output in model.graph.output:
        node = producer.get(output.name)
        if node is None:
            continue
        names.append(node.name)
        step = producer.get(node.input[0]) if node.op_type == "Conv" else None
        while step is not None:
            names.append(step.name)
            step = None if step.op_type == "Conv" else producer.get(step.input[0])
        names += [
            producer[i].name
            for i in node.input
            if i in producer and producer[i].op_type == "Slice" and producer[i].input[0] in inputs
        ]
    return names


def activation_max_abs(model: onnx.ModelProto, feeds: Sequence[dict], tensors: Sequence[str]) -> dict[str, float]:
    """max |x| of each named intermediate tensor of an fp32 graph over the feeds."""
    import onnxruntime as ort

    from geonet_infer.engines.onnxruntime import make_session_options

    probe = onnx.ModelProto()
    probe.CopyFrom(model)
    del probe.graph.output[:]
    probe.graph.output.extend(onnx.helper.make_empty_tensor_value_info(t) for t in tensors)
    session = ort.InferenceSession(
        probe.SerializeToString(), sess_options=make_session_options(), providers=["CPUExecutionProvider"]
    )
    peak = dict.fromkeys(tensors, 0.0)
    for feed in feeds:
        for name, value in zip(tensors, session.run(list(tensors), feed)):
            peak[name] = max(peak[name], float(np.abs(value).max()))
    return peak


def equalize_concat_inputs(model: onnx.ModelProto, feeds: Sequence[dict], ratio: float = 8.0) -> list[str]:
    """Scale up concat inputs whose range is far below their neighbours'; fold 1/k into the next conv.

    A Concat gets one uint8 scale for all its channels. GeoNet's decoders concatenate the
    upsampled coarser prediction (ResFlowNet: flow normalised by the image size, |x| < 0.3) with
    features of range ~10, so quantised, the prediction fed back keeps only a few levels. For
    each such input (max |x| below 1/``ratio`` of the largest input, over ``feeds``), a
    ``Mul(k)`` with k a power of two (exact in fp32) is inserted before the Concat and the
    matching input channels of every consuming Conv's weight are divided by k, so the fp32
    graph computes the same function. Edits ``model`` in place; returns "tensor x k" lines.
    """
    model.CopyFrom(onnx.shape_inference.infer_shapes(model))
    channels = {
        v.name: v.type.tensor_type.shape.dim[1].dim_value
        for v in list(model.graph.value_info) + list(model.graph.input)
        if len(v.type.tensor_type.shape.dim) == 4
    }
    weights = {init.name: init for init in model.graph.initializer}
    users: dict[str, list] = {}
    for node in model.graph.node:
        for i in node.input:
            users.setdefault(i, []).append(node)

    def axis(node):
        return next((a.i for a in node.attribute if a.name == "axis"), None)

    def plain_conv(node):
        groups = next((a.i for a in node.attribute if a.name == "group"), 1)
        return node.op_type == "Conv" and groups == 1 and node.input[1] in weights and len(users[node.input[1]]) == 1

    concats = [
        n
        for n in model.graph.node
        if n.op_type == "Concat"
        and axis(n) in (1, -3)
        and all(i in channels and channels[i] > 0 for i in n.input)
        and users.get(n.output[0])
        and all(plain_conv(c) for c in users[n.output[0]])
    ]
    if not concats:
        return []
    peak = activation_max_abs(model, feeds, sorted({i for n in concats for i in n.input}))
    done: list[str] = []
    new_nodes: dict = {}
    for concat in concats:
        top = max(peak[i] for i in concat.input)
        start = 0
        for slot, tensor in enumerate(list(concat.input)):
            width = channels[tensor]
            if 0 < peak[tensor] * ratio < top:
                k = float(2 ** np.floor(np.log2(top / peak[tensor])))
                scaled = f"{tensor}_x{k:g}"
                factor = onnx.numpy_helper.from_array(np.array(k, np.float32), f"{scaled}_k")
                model.graph.initializer.append(factor)
                new_nodes[concat.name] = new_nodes.get(concat.name, []) + [
                    onnx.helper.make_node("Mul", [tensor, factor.name], [scaled], name=f"{scaled}_mul")
                ]
                concat.input[slot] = scaled
                for conv in users[concat.output[0]]:
                    w = onnx.numpy_helper.to_array(weights[conv.input[1]]).copy()
                    w[:, start : start + width] /= k
                    weights[conv.input[1]].CopyFrom(onnx.numpy_helper.from_array(w, conv.input[1]))
                done.append(f"{tensor} x {k:g} (max |x| {peak[tensor]:.3g} next to {top:.3g})")
            start += width
    ordered = []
    for node in model.graph.node:  # keep the graph topologically sorted: each Mul just before its Concat
        ordered += new_nodes.get(node.name, []) + [node]
    del model.graph.node[:]
    model.graph.node.extend(ordered)
    return done


def downstream_nodes(model: onnx.ModelProto, tensors: Sequence[str]) -> list[str]:
    """Names of every node that (transitively) consumes one of ``tensors``."""
    reached, names = set(tensors), []
    for node in model.graph.node:  # ONNX graphs are topologically sorted
        if reached.intersection(node.input):
            names.append(node.name)
            reached.update(node.output)
    return names


def input_layer_nodes(model: onnx.ModelProto) -> list[str]:
    """Nodes from a graph input up to and including the first convolutions: ResFlowNet's first conv over
    the 12-channel stack, and for a direct ResFlowNet (issue 53) also what builds its input from that
    stack (slices, the photometric error: quantised, its sums and square roots lost 10 % of the KITTI
    2015 flow). Nodes past a Conv are not followed."""
    consumers: dict[str, list[onnx.NodeProto]] = {}
    for node in model.graph.node:
        for name in node.input:
            consumers.setdefault(name, []).append(node)
    reached: dict[str, None] = {}
    frontier = [node for i in model.graph.input for node in consumers.get(i.name, [])]
    while frontier:
        node = frontier.pop(0)
        if node.name in reached:
            continue
        reached[node.name] = None
        if node.op_type != "Conv":
            frontier += [nxt for out in node.output for nxt in consumers.get(out, [])]
    return list(reached)


_DECODER_LEVEL = re.compile(r"decoder\.(?:upconvs|iconvs)\.(\d+)\.")  # training/networks/blocks.py's names


def decoder_level_nodes(model: onnx.ModelProto, levels: int) -> list[str]:
    """The Conv nodes of the ``levels`` finest decoder levels (each level's up-convolution and the
    convolution after it), found by their kernels' parameter names; level numbers grow finer."""
    by_level: dict[int, list[str]] = {}
    for node in model.graph.node:
        match = _DECODER_LEVEL.search(node.input[1]) if node.op_type == "Conv" and len(node.input) > 1 else None
        if match:
            by_level.setdefault(int(match.group(1)), []).append(node.name)
    return [name for level in sorted(by_level)[-levels:] for name in by_level[level]] if levels else []


def quantize_graph(
    fp32_path: str | Path,
    out_path: str | Path,
    feeds: Sequence[dict],
    settings: QuantSettings = QuantSettings(),
    plan: GraphPlan = GraphPlan(),
) -> list[str]:
    """Pre-process + quantize_static (QDQ) one graph; keeps the fp32 file's metadata_props.

    ``plan`` says which parts stay fp32 and whether concat inputs are rescaled first. Returns
    what the plan did, one line each (for the log and the manifest).
    """
    from onnxruntime.quantization import (
        CalibrationDataReader,
        CalibrationMethod,
        QuantFormat,
        QuantType,
        quantize_static,
    )
    from onnxruntime.quantization.shape_inference import quant_pre_process

    if not feeds:
        raise InputError(
            None,
            f"no calibration inputs for {Path(fp32_path).name}",
            "the calibration folder needs at least seq_length consecutive frames",
        )
    methods = dict(
        zip(CALIBRATION_METHODS, (CalibrationMethod.MinMax, CalibrationMethod.Entropy, CalibrationMethod.Percentile))
    )
    if settings.calibrate_method not in methods:
        raise InputError(
            None, f"unknown calibration method {settings.calibrate_method!r}", f"choose one of {', '.join(methods)}"
        )
    fp32_path, out_path = Path(fp32_path), Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)

    class Reader(_ListReader, CalibrationDataReader):
        pass

    work = Path(tempfile.mkdtemp(prefix="quant-", dir=out_path.parent))
    try:
        pre = work / "pre.onnx"
        # ONNX shape inference + ORT optimisation only. ORT's *symbolic* shape inference (meant for
        # transformers) does not complete on these graphs, and on failure it dumps
        # sym_shape_infer_temp.onnx plus external-data files into the current directory.
        quant_pre_process(str(fp32_path), str(pre), skip_symbolic_shape=True)
        graph = onnx.load(str(pre))
        notes = [f"rescaled {line}" for line in equalize_concat_inputs(graph, feeds)] if plan.equalize_concats else []
        if notes:
            onnx.save_model(graph, str(pre))
        exclude = downstream_nodes(graph, plan.float_after) if plan.float_after else []
        if plan.float_after and not exclude:
            raise InputError(fp32_path, f"no nodes consume {list(plan.float_after)}", "re-export the fp32 graph")
        if plan.float_output_layer:
            exclude += output_layer_nodes(graph)
        if plan.float_input_layer:
            exclude += input_layer_nodes(graph)
        if plan.float_finest_levels:
            finest = decoder_level_nodes(graph, plan.float_finest_levels)
            if not finest:
                raise InputError(
                    fp32_path,
                    "no decoder levels found (kernels named decoder.upconvs.N)",
                    "the plan is for GeoNet's ResFlowNet",
                )
            exclude += finest
        exclude = list(dict.fromkeys(exclude))  # a node two rules keep fp32 is named once
        if exclude:
            notes.append(f"fp32 nodes: {', '.join(exclude)}")
        quantize_static(
            str(pre),
            str(work / "q.onnx"),
            Reader(feeds),
            quant_format=QuantFormat.QDQ,
            per_channel=settings.per_channel,
            reduce_range=settings.reduce_range,
            activation_type=QuantType.QUInt8,
            weight_type=QuantType.QInt8,
            calibrate_method=methods[settings.calibrate_method],
            nodes_to_exclude=exclude,
            op_types_to_quantize=list(settings.op_types) or None,
            extra_options={"CalibTensorRangeSymmetric": False},
        )
        model = onnx.load(str(work / "q.onnx"))
        source_meta = {p.key: p.value for p in onnx.load(str(fp32_path), load_external_data=False).metadata_props}
        del model.metadata_props[:]
        for key in sorted(source_meta):
            entry = model.metadata_props.add()
            entry.key = key
            entry.value = "int8" if key == "geonet.precision" else source_meta[key]
        onnx.save_model(model, str(out_path), save_as_external_data=False)
        return notes
    finally:
        shutil.rmtree(work, ignore_errors=True)

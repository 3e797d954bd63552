"""geonet_infer.models.onnx_graph on small graphs built here with onnx's helpers (a second writer of the
format): the channels a graph reads, and a graph cut down to some outputs, checked by running it."""

from __future__ import annotations

import numpy as np
import onnxruntime as ort
import pytest

onnx = pytest.importorskip("onnx")  # the [convert] extra; the runtime-only run skips this file
from onnx import TensorProto, helper, numpy_helper  # noqa: E402

from geonet_infer.models.onnx_graph import channels_read, keep_outputs  # noqa: E402

X = helper.make_tensor_value_info("x", TensorProto.FLOAT, ["B", 6, 4, 5])


def model_bytes(nodes, outputs, initializers=(), inputs=(X,)) -> bytes:
    graph = helper.make_graph(nodes, "g", list(inputs), outputs, initializer=list(initializers))
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)])
    model.ir_version = 9
    onnx.checker.check_model(model)
    return model.SerializeToString()


def ints(name: str, values) -> onnx.TensorProto:
    return numpy_helper.from_array(np.array(values, np.int64), name)


def out(name: str, channels) -> onnx.ValueInfoProto:
    return helper.make_tensor_value_info(name, TensorProto.FLOAT, ["B", channels, 4, 5])


def slice_node(name: str, start: str, end: str, axes: str = "axis", steps: str | None = None):
    return helper.make_node("Slice", ["x", start, end, axes] + ([steps] if steps else []), [name])


def test_slices_by_initializers_and_by_constant_nodes_name_their_channels():
    nodes = [
        slice_node("a", "s0", "e0"),
        helper.make_node("Constant", [], ["s1"], value=ints("v1", [4])),
        helper.make_node("Constant", [], ["e1"], value=ints("v2", [6])),
        slice_node("b", "s1", "e1"),
        helper.make_node("Concat", ["a", "b"], ["y"], axis=1),
    ]
    buf = model_bytes(nodes, [out("y", 4)], [ints("s0", [0]), ints("e0", [2]), ints("axis", [1])])
    assert channels_read(buf, "x") == frozenset({0, 1, 4, 5})


@pytest.mark.parametrize(
    "start, end, axis, steps",
    [(-2, 6, 1, None), (0, 2**62, 1, None), (0, 4, 1, 2), (0, 2, 2, None)],
    ids=["from the end", "to the end", "every second channel", "not the channel axis"],
)
def test_a_slice_that_is_not_a_plain_channel_range_reads_everything(start, end, axis, steps):
    inits = [ints("s", [start]), ints("e", [end]), ints("axis", [axis])] + ([ints("st", [steps])] if steps else [])
    nodes = [slice_node("y", "s", "e", "axis", "st" if steps else None)]
    buf = model_bytes(nodes, [helper.make_tensor_value_info("y", TensorProto.FLOAT, ["B", "C", "H", "W"])], inits)
    assert channels_read(buf, "x") is None


def test_any_other_reader_of_the_input_reads_everything():
    nodes = [slice_node("a", "s", "e"), helper.make_node("Relu", ["x"], ["b"])]
    buf = model_bytes(nodes, [out("a", 2), out("b", 6)], [ints("s", [0]), ints("e", [2]), ints("axis", [1])])
    assert channels_read(buf, "x") is None


def test_a_cut_graph_keeps_what_its_output_needs_and_computes_the_same():
    w = numpy_helper.from_array(np.arange(6, dtype=np.float32).reshape(1, 6, 1, 1) / 10, "w")
    unused_after = numpy_helper.from_array(np.full((1, 6, 1, 1), 3.0, np.float32), "k")
    nodes = [
        helper.make_node("Conv", ["x", "w"], ["c"]),
        helper.make_node("Relu", ["c"], ["kept"]),
        helper.make_node("Mul", ["x", "k"], ["m"]),
        helper.make_node("Sqrt", ["m"], ["dropped"]),
    ]
    buf = model_bytes(nodes, [out("kept", 1), out("dropped", 6)], [w, unused_after])
    cut = keep_outputs(buf, ["kept"])
    assert cut is not None
    graph = onnx.load_from_string(cut).graph
    onnx.checker.check_model(onnx.load_from_string(cut))
    assert [n.op_type for n in graph.node] == ["Conv", "Relu"]
    assert [o.name for o in graph.output] == ["kept"] and [i.name for i in graph.initializer] == ["w"]
    x = np.random.default_rng(0).normal(size=(2, 6, 4, 5)).astype(np.float32)
    whole = ort.InferenceSession(buf, providers=["CPUExecutionProvider"]).run(["kept"], {"x": x})[0]
    small = ort.InferenceSession(cut, providers=["CPUExecutionProvider"]).run(None, {"x": x})[0]
    np.testing.assert_array_equal(small, whole)


def test_a_needed_node_with_a_subgraph_is_not_cut():
    then = helper.make_graph([helper.make_node("Identity", ["x"], ["t"])], "then", [], [out("t", 6)])
    other = helper.make_graph([helper.make_node("Neg", ["x"], ["f"])], "else", [], [out("f", 6)])
    cond = helper.make_tensor_value_info("cond", TensorProto.BOOL, [])
    nodes = [
        helper.make_node("If", ["cond"], ["y"], then_branch=then, else_branch=other),
        helper.make_node("Abs", ["x"], ["z"]),
    ]
    buf = model_bytes(nodes, [out("y", 6), out("z", 6)], inputs=(X, cond))
    assert keep_outputs(buf, ["y"]) is None
    assert keep_outputs(buf, ["z"]) is not None  # the If is not needed for z
    assert keep_outputs(buf, ["nothing"]) is None

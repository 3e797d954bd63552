"""INT8 graph plans (geonet_infer/convert/quantize.py) on a hand-built decoder level.

The graph mimics one level of GeoNet's decoder: wide features (range ~10) concatenated with a
2-channel prediction of range ~0.05 fed back from a coarser head, a conv over the concat, and an
output head. The fp32 ORT run of the unmodified graph is the reference.
"""

from __future__ import annotations

import numpy as np
import onnx
import onnxruntime as ort
import pytest
from onnx import TensorProto, helper, numpy_helper

from geonet_infer.convert import quantize as qz
from geonet_infer.errors import GeoNetError

C, HW = 8, 16


def decoder_level(path) -> onnx.ModelProto:
    rng = np.random.default_rng(0)
    weights = {
        "w_feat": rng.normal(0, 0.5, (C, 3, 3, 3)),
        "w_pred": rng.normal(0, 0.002, (2, C, 3, 3)),
        "w_mix": np.concatenate([rng.normal(0, 0.05, (C, C, 3, 3)), rng.normal(0, 5.0, (C, 2, 3, 3))], axis=1),
        "w_head": rng.normal(0, 0.3, (2, C, 3, 3)),
    }
    same = {"pads": [1, 1, 1, 1]}
    nodes = [
        helper.make_node("Conv", ["image", "w_feat"], ["feat_pre"], name="feat_conv", **same),
        helper.make_node("Relu", ["feat_pre"], ["feat"], name="feat_relu"),
        helper.make_node("Conv", ["feat", "w_pred"], ["pred"], name="pred_conv", **same),
        helper.make_node("Concat", ["feat", "pred"], ["cat"], name="cat", axis=1),
        helper.make_node("Conv", ["cat", "w_mix"], ["mix_pre"], name="mix_conv", **same),
        helper.make_node("Relu", ["mix_pre"], ["mix"], name="mix_relu"),
        helper.make_node("Conv", ["mix", "w_head"], ["out"], name="head_conv", **same),
    ]
    graph = helper.make_graph(
        nodes,
        "decoder_level",
        [helper.make_tensor_value_info("image", TensorProto.FLOAT, [1, 3, HW, HW])],
        [helper.make_tensor_value_info("out", TensorProto.FLOAT, [1, 2, HW, HW])],
        [numpy_helper.from_array(v.astype(np.float32), k) for k, v in weights.items()],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    onnx.checker.check_model(model)
    onnx.save_model(model, str(path))
    return model


def feeds(n: int, seed: int) -> list[dict]:
    rng = np.random.default_rng(seed)
    return [{"image": rng.uniform(-1, 1, (1, 3, HW, HW)).astype(np.float32)} for _ in range(n)]


def run(model_or_path, feed: dict) -> np.ndarray:
    source = model_or_path.SerializeToString() if isinstance(model_or_path, onnx.ModelProto) else str(model_or_path)
    return ort.InferenceSession(source, providers=["CPUExecutionProvider"]).run(None, feed)[0]


def test_equalized_concat_computes_the_same_function(tmp_path):
    model = decoder_level(tmp_path / "level.onnx")
    calib = feeds(4, seed=1)
    peak = qz.activation_max_abs(model, calib, ["feat", "pred"])
    assert peak["pred"] * 8 < peak["feat"]  # the case the rewrite is for
    edited = onnx.ModelProto()
    edited.CopyFrom(model)
    lines = qz.equalize_concat_inputs(edited, calib)
    assert len(lines) == 1 and lines[0].startswith("pred x ")
    k = float(lines[0].split()[2])
    assert np.log2(k) == int(np.log2(k))  # a power of two: exact in fp32
    assert peak["feat"] / 2 < k * peak["pred"] <= peak["feat"]
    onnx.checker.check_model(edited)
    for feed in feeds(3, seed=2):
        np.testing.assert_allclose(run(edited, feed), run(model, feed), rtol=1e-5, atol=1e-5)


def test_equalized_concat_quantizes_the_fed_back_prediction_better(tmp_path):
    decoder_level(tmp_path / "level.onnx")
    calib, test = feeds(16, seed=1), feeds(4, seed=3)
    settings = qz.QuantSettings(calibrate_method="minmax")
    qz.quantize_graph(tmp_path / "level.onnx", tmp_path / "plain.onnx", calib, settings)
    notes = qz.quantize_graph(
        tmp_path / "level.onnx", tmp_path / "eq.onnx", calib, settings, qz.GraphPlan(equalize_concats=True)
    )
    assert any(line.startswith("rescaled pred x ") for line in notes)
    reference = [run(tmp_path / "level.onnx", f) for f in test]

    def error(path):
        return np.mean([np.abs(run(path, f) - r).mean() for f, r in zip(test, reference)])

    assert error(tmp_path / "eq.onnx") < 0.5 * error(tmp_path / "plain.onnx")


def test_output_layer_nodes_are_the_head_and_the_layer_it_reads(tmp_path):
    model = decoder_level(tmp_path / "level.onnx")
    assert qz.output_layer_nodes(model) == ["head_conv", "mix_relu", "mix_conv"]
    qz.quantize_graph(
        tmp_path / "level.onnx",
        tmp_path / "q.onnx",
        feeds(8, seed=1),
        qz.QuantSettings(),
        qz.GraphPlan(float_output_layer=True),
    )
    quantized = onnx.load(str(tmp_path / "q.onnx"))
    float_weights = {i.name for i in quantized.graph.initializer if i.data_type == TensorProto.FLOAT}
    convs = {n.name: n for n in quantized.graph.node if n.op_type == "Conv"}
    assert {"w_head", "w_mix"} <= float_weights  # fp32 kernels, read directly
    assert convs["head_conv"].input[1] == "w_head" and convs["mix_conv"].input[1] == "w_mix"
    assert convs["feat_conv"].input[1] != "w_feat"  # the rest is still quantised (through a DequantizeLinear)


def test_float_after_an_unknown_tensor_is_an_error(tmp_path):
    decoder_level(tmp_path / "level.onnx")
    with pytest.raises(GeoNetError, match="no nodes consume"):
        qz.quantize_graph(
            tmp_path / "level.onnx", tmp_path / "q.onnx", feeds(2, seed=1), plan=qz.GraphPlan(float_after=("missing",))
        )


def test_op_types_leave_every_other_operator_in_fp32(tmp_path):
    """QuantSettings(op_types=("Conv",)): the two Relus stay fp32 nodes, while the default quantises
    them (folded into their convolution's uint8 output); the kernels are int8 either way."""
    decoder_level(tmp_path / "level.onnx")
    calib = feeds(8, seed=1)
    qz.quantize_graph(tmp_path / "level.onnx", tmp_path / "all.onnx", calib, qz.QuantSettings())
    conv_only = qz.QuantSettings(op_types=("Conv",))
    qz.quantize_graph(tmp_path / "level.onnx", tmp_path / "conv.onnx", calib, conv_only)
    assert conv_only.describe()["op_types"] == ["Conv"] and "op_types" not in qz.QuantSettings().describe()
    for path, relus in ((tmp_path / "all.onnx", 0), (tmp_path / "conv.onnx", 2)):
        model = onnx.load(str(path))
        assert [n.op_type for n in model.graph.node].count("Relu") == relus
        kernels = {i.name: i.data_type for i in model.graph.initializer if i.name.endswith("_quantized")}
        assert len(kernels) == 4 and set(kernels.values()) == {TensorProto.INT8}
    assert "Resize" in qz.quantisable_op_types() and "Conv" in qz.quantisable_op_types()


def test_input_layer_nodes_are_the_nodes_reading_a_graph_input(tmp_path):
    model = decoder_level(tmp_path / "level.onnx")
    assert qz.input_layer_nodes(model) == ["feat_conv"]
    qz.quantize_graph(
        tmp_path / "level.onnx", tmp_path / "q.onnx", feeds(8, seed=1), plan=qz.GraphPlan(float_input_layer=True)
    )
    convs = {n.name: n for n in onnx.load(str(tmp_path / "q.onnx")).graph.node if n.op_type == "Conv"}
    assert convs["feat_conv"].input[1] == "w_feat"  # fp32 kernel, read directly
    assert convs["mix_conv"].input[1] != "w_mix"


def test_decoder_level_nodes_are_the_finest_levels_up_and_integrating_convs():
    """Kernels named like training/networks/blocks.py's decoder: level 1 is finer than level 0."""
    names = ["upconvs.0.conv", "iconvs.0", "heads.0", "upconvs.1.conv", "iconvs.1", "heads.1"]
    nodes = [
        helper.make_node("Conv", ["x", f"flow_net.decoder.{n}.weight"], [f"y{i}"], name=n) for i, n in enumerate(names)
    ]
    nodes.append(helper.make_node("Conv", ["x", "flow_net.encoder.conv1.conv.weight"], ["e"], name="encoder"))
    graph = helper.make_graph(nodes, "names", [], [])
    assert qz.decoder_level_nodes(helper.make_model(graph), 1) == ["upconvs.1.conv", "iconvs.1"]
    assert qz.decoder_level_nodes(helper.make_model(graph), 2) == [
        "upconvs.0.conv",
        "iconvs.0",
        "upconvs.1.conv",
        "iconvs.1",
    ]
    assert qz.decoder_level_nodes(helper.make_model(graph), 0) == []


def test_finest_levels_of_a_graph_without_a_decoder_is_an_error(tmp_path):
    decoder_level(tmp_path / "level.onnx")
    with pytest.raises(GeoNetError, match="no decoder levels"):
        qz.quantize_graph(
            tmp_path / "level.onnx", tmp_path / "q.onnx", feeds(2, seed=1), plan=qz.GraphPlan(float_finest_levels=2)
        )


def test_resnet50_keeps_resflownets_input_layer_quantised():
    """The fp32 input layer was measured on the small arch only (convert/quantize.py INPUT_LAYER_ARCHS)."""
    assert qz.plan_for("resflownet", "small") == qz.PLANS["resflownet"]
    resnet50 = qz.plan_for("resflownet", "resnet50")
    assert not resnet50.float_input_layer
    assert resnet50.float_finest_levels == 2 and resnet50.float_output_layer and resnet50.equalize_concats
    assert qz.plan_for("depthnet", "resnet50") == qz.GraphPlan()


def test_input_layer_nodes_follow_the_graph_input_to_the_first_convolution():
    """A direct ResFlowNet (issue 53) slices its input and builds a photometric error before its first conv:
    all of that is its input layer; nothing past a Conv is."""
    nodes = [
        helper.make_node("Slice", ["x", "s0", "e0"], ["a"], name="slice_a"),
        helper.make_node("Slice", ["x", "s1", "e1"], ["b"], name="slice_b"),
        helper.make_node("Sub", ["a", "b"], ["d"], name="diff"),
        helper.make_node("Abs", ["d"], ["err"], name="error"),
        helper.make_node("Concat", ["a", "b", "err"], ["stack"], name="stack", axis=1),
        helper.make_node("Conv", ["stack", "w1"], ["f1"], name="first_conv"),
        helper.make_node("Relu", ["f1"], ["r1"], name="relu"),
        helper.make_node("Conv", ["r1", "w2"], ["y"], name="second_conv"),
    ]
    x = helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 6, 8, 8])
    model = helper.make_model(helper.make_graph(nodes, "direct", [x], []))
    assert sorted(qz.input_layer_nodes(model)) == sorted(["slice_a", "slice_b", "diff", "error", "stack", "first_conv"])

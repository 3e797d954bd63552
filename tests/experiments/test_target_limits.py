"""experiments/target_limits.py and the speed-targets page's "what bounds it" rows, on hand-made inputs."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

onnx = pytest.importorskip("onnx")
from onnx import TensorProto, helper, numpy_helper  # noqa: E402

from experiments.target_limits import graph_macs  # noqa: E402

EXPERIMENTS = Path(__file__).resolve().parents[2] / "experiments"  # speed_targets imports its siblings by name


def _conv_graph(path: Path, conv_weight: np.ndarray | None = None) -> None:
    """Conv 3 -> 4 channels, 3x3, pad 1, on B x 3 x 8 x 10; then ConvTranspose 4 -> 2, 2x2, stride 2; a ReLU."""
    weight = np.ones((4, 3, 3, 3), np.float32) if conv_weight is None else conv_weight
    conv_w = numpy_helper.from_array(weight, "conv_w")
    deconv_w = numpy_helper.from_array(np.zeros((4, 2, 2, 2), np.float32), "deconv_w")
    nodes = [
        helper.make_node("Conv", ["x", "conv_w"], ["a"], pads=[1, 1, 1, 1]),
        helper.make_node("Relu", ["a"], ["b"]),
        helper.make_node("ConvTranspose", ["b", "deconv_w"], ["y"], strides=[2, 2]),
    ]
    graph = helper.make_graph(
        nodes,
        "macs",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, ["B", 3, 8, 10])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, ["B", 2, 16, 20])],
        [conv_w, deconv_w],
    )
    onnx.save(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)]), str(path))


def test_graph_macs_counts_each_convolution_once_per_output_or_input_pixel(tmp_path):
    _conv_graph(tmp_path / "g.onnx")
    conv = (4 * 8 * 10) * (3 * 3 * 3)  # every output value: Cin x kh x kw multiply-adds
    deconv = (4 * 8 * 10) * (2 * 2 * 2)  # every input value spreads to Cout x kh x kw outputs
    assert graph_macs(tmp_path / "g.onnx") == conv + deconv


def test_graph_macs_leave_out_the_taps_whose_weight_is_zero(tmp_path):
    weight = np.ones((4, 3, 3, 3), np.float32)
    weight[:, :, 0, :] = 0  # the top row of every kernel: 6 of 9 taps left
    weight[3] = 0  # and one output channel with none
    _conv_graph(tmp_path / "g.onnx", weight)
    conv = (8 * 10) * (3 * 3 * 6)  # per output pixel: three channels' 3 x 6 taps
    deconv = (4 * 8 * 10) * (2 * 2 * 2)
    assert graph_macs(tmp_path / "g.onnx", skip_zero_taps=True) == conv + deconv
    assert graph_macs(tmp_path / "g.onnx") == (4 * 8 * 10) * (3 * 3 * 3) + deconv  # by default, every tap


def _result(after: dict) -> dict:
    limits = {
        "gemm_peaks": {"int8_gops": 1000.0, "fp32_gflops": 200.0},
        "small_gmacs_per_frame": 1.0,
        "resnet50_depth_gmacs": 10.0,  # 20 GOP: 20 ms at the peak, more than the 19 ms goal
        "resnet50_gmacs_per_frame": 20.0,
    }
    return {"after": after, "limits": limits, "after_cpu_ms_per_frame": {"all outputs": 100, "--no-vis": 80}, "cpus": 2}


def test_bounds_rows_only_for_unmet_targets_and_say_when_the_peak_is_slower_than_the_goal(monkeypatch):
    monkeypatch.syspath_prepend(str(EXPERIMENTS))
    from experiments.speed_targets import limit_rows

    after = {"1a_best_engine_ms": 7.0, "networks_best_ms": 5.0, "7a_resnet50_int8_depth_ms": 25.0}
    rows = dict(limit_rows(_result(after)))
    assert set(rows) == {"7a"}  # 1a (7 ms <= 8) is met
    assert "20.0 ms at the int8 GEMM peak, more than the 19 ms goal" in rows["7a"]
    assert "measured 25.0 ms = 800 GOP/s, 80% of the peak" in rows["7a"]

    after = {"1a_best_engine_ms": 9.0, "networks_best_ms": 6.0, "7a_resnet50_int8_depth_ms": 18.0}
    rows = dict(limit_rows(_result(after)))
    assert set(rows) == {"1a"}
    assert "2.00 GOP of convolutions: 2.0 ms at the int8 GEMM peak; measured 6.0 ms = 333 GOP/s, 33%" in rows["1a"]
    assert "more than" not in rows["1a"]

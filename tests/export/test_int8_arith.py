"""INT8 arithmetic of x86 CPUs without VNNI, emulated so that any CPU can check it (issue 45).

On AVX2-only CPUs onnxruntime's uint8 x int8 kernels add pairs of products in int16 with
saturation (``geonet_infer/convert/int8_arith.py``); the bundled INT8 graphs have 8-bit weights that overflow
there unless the session turns on onnxruntime's exact path, as the runtime's sessions do.
"""

from __future__ import annotations

import numpy as np
import onnx
import pytest
from onnx import helper, numpy_helper

from geonet_infer.convert.int8_arith import (
    conv_weights,
    dot_as_onnxruntime_runs_it,
    dot_avx2_u8s8,
    dot_exact,
    int8_kernels,
)
from geonet_infer.engines import onnxruntime as ort_engine
from geonet_infer.engines.cpu import cpu_info
from geonet_infer.engines.onnxruntime import X64_QUANT_PRECISION, make_session_options
from geonet_infer.io import list_images, read_image
from geonet_infer.models import resolve_model
from geonet_infer.models.manifest import load_manifest
from geonet_infer.samples import SAMPLE_FRAMES


def test_avx2_pairs_saturate_in_int16():
    """Hand-computed: 255*127 + 255*127 = 64770 is stored as 32767; 255*64 + 255*64 = 32640 fits.
    VNNI sums all four exactly: 255 * (127 + 127 + 64 + 64) = 97410."""
    a = np.array([[255, 255, 255, 255]], np.uint8)
    w = np.array([[127], [127], [64], [64]], np.int8)
    assert dot_avx2_u8s8(a, w)[0, 0] == 32767 + 32640
    assert dot_exact(a, w)[0, 0] == 97410
    # a negative pair saturates at -32768; an odd K is padded with a zero product
    assert dot_avx2_u8s8(np.array([[255, 255, 7]], np.uint8), np.array([[-128], [-128], [3]], np.int8))[0, 0] == (
        -32768 + 21
    )


def test_emulation_is_what_this_cpus_onnxruntime_computes():
    """A plain onnxruntime MatMulInteger (uint8 x int8, no remedy) gives the emulation of this CPU's
    kernel: exact with VNNI/AMX, the saturating sums without (checked by the suite on AVX2-only CPUs)."""
    import onnxruntime as ort

    kernel = cpu_info()["int8_kernel"]
    if kernel == "none":
        pytest.skip("not an x86 CPU")
    rng = np.random.default_rng(45)
    a = rng.integers(0, 256, (16, 147)).astype(np.uint8)  # odd K, like a 7x7x3 kernel
    w = rng.integers(-127, 128, (147, 24)).astype(np.int8)
    graph = helper.make_graph(
        [helper.make_node("MatMulInteger", ["a", "w"], ["y"])],
        "g",
        [helper.make_tensor_value_info("a", onnx.TensorProto.UINT8, list(a.shape))],
        [helper.make_tensor_value_info("y", onnx.TensorProto.INT32, None)],
        [numpy_helper.from_array(w, "w")],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)])
    session = ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
    got = session.run(None, {"a": a})[0]
    assert np.array_equal(got, dot_as_onnxruntime_runs_it(a, w, kernel, precision_mode=False)), kernel
    assert not np.array_equal(dot_avx2_u8s8(a, w), dot_exact(a, w))  # the case can tell the two apart


def _first_conv_inputs(model: onnx.ModelProto, image: np.ndarray, kernel: tuple[int, int]) -> np.ndarray:
    """uint8 im2col rows (c, kh, kw order) of a frame as the graph's input QuantizeLinear stores it."""
    inits = {i.name: numpy_helper.to_array(i) for i in model.graph.initializer}
    quant = next(n for n in model.graph.node if n.op_type == "QuantizeLinear" and n.input[0] == "image")
    scale, zero = float(inits[quant.input[1]]), int(inits[quant.input[2]])
    x = image.astype(np.float32).transpose(2, 0, 1) / 255 * 2 - 1  # the network range (cascade.InputSpec)
    q = np.clip(np.round(x / scale) + zero, 0, 255).astype(np.uint8)
    windows = np.lib.stride_tricks.sliding_window_view(q, kernel, axis=(1, 2))[:, ::4, ::4]  # (C, h, w, kh, kw)
    return windows.transpose(1, 2, 0, 3, 4).reshape(-1, q.shape[0] * kernel[0] * kernel[1])


def test_bundled_int8_convs_exact_on_avx2_as_the_runtime_runs_them(monkeypatch):
    """The bundled INT8 DepthNet's first convolution on a real sample frame: AVX2's saturating sums
    differ from the exact ones (8-bit weights overflow int16 pairs); with the runtime's session options
    onnxruntime computes it exactly on AVX2 too (it fails without X64_QUANT_PRECISION in them)."""
    manifest = load_manifest(resolve_model())
    model = onnx.load(str(manifest.path("depthnet", "int8")))
    name, w = next(iter(conv_weights(model).items()))
    frame = read_image(list_images(SAMPLE_FRAMES)[0])
    h, w_ = manifest.height, manifest.width
    import cv2

    a = _first_conv_inputs(model, cv2.resize(frame, (w_, h), interpolation=cv2.INTER_AREA), w.shape[2:])
    weights = w.reshape(w.shape[0], -1).T  # (K, out channels)
    exact = dot_exact(a, weights)
    assert not np.array_equal(dot_avx2_u8s8(a, weights), exact), f"{name}: no saturation on this frame"
    # the session options the runtime makes on an AVX2-only CPU
    monkeypatch.setattr(ort_engine, "cpu_info", lambda: {"int8_kernel": "avx2"})
    try:
        precision_mode = make_session_options().get_session_config_entry(X64_QUANT_PRECISION) == "1"
    except RuntimeError:  # onnxruntime raises for a key never set
        precision_mode = False
    assert np.array_equal(dot_as_onnxruntime_runs_it(a, weights, "avx2", precision_mode), exact)


def _shared_weight_graph(path):
    """A QDQ graph whose one int8 weight (beyond +-64) feeds two MatMuls (as a norm shared by several
    layers does): onnxruntime refuses its AVX2 remedy for such a graph."""
    rng = np.random.default_rng(3)
    inits = [
        numpy_helper.from_array(rng.integers(-127, 128, (8, 8)).astype(np.int8), "w"),
        numpy_helper.from_array(np.array(0.01, np.float32), "ws"),
        numpy_helper.from_array(np.array(0, np.int8), "wz"),
        numpy_helper.from_array(np.array(0.02, np.float32), "xs"),
        numpy_helper.from_array(np.array(128, np.uint8), "xz"),
    ]
    nodes = [
        helper.make_node("QuantizeLinear", ["x", "xs", "xz"], ["xq"]),
        helper.make_node("DequantizeLinear", ["xq", "xs", "xz"], ["xd"]),
        helper.make_node("DequantizeLinear", ["w", "ws", "wz"], ["wd"]),
        helper.make_node("MatMul", ["xd", "wd"], ["h"]),
        helper.make_node("Relu", ["h"], ["r"]),
        helper.make_node("QuantizeLinear", ["r", "xs", "xz"], ["rq"]),
        helper.make_node("DequantizeLinear", ["rq", "xs", "xz"], ["rd"]),
        helper.make_node("MatMul", ["rd", "wd"], ["y"]),
    ]
    graph = helper.make_graph(
        nodes,
        "g",
        [helper.make_tensor_value_info("x", onnx.TensorProto.FLOAT, [4, 8])],
        [helper.make_tensor_value_info("y", onnx.TensorProto.FLOAT, None)],
        inits,
    )
    onnx.save(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)]), str(path))


def test_the_avx2_remedy_is_set_only_where_it_matters_and_a_graph_it_refuses_still_loads(monkeypatch, tmp_path, capsys):
    path = tmp_path / "shared.onnx"
    _shared_weight_graph(path)
    x = {"x": np.linspace(-1, 1, 32, dtype=np.float32).reshape(4, 8)}
    monkeypatch.setattr(ort_engine, "cpu_info", lambda: {"int8_kernel": "avx512_vnni"})
    with pytest.raises(RuntimeError):  # exact kernels: nothing to remedy, the entry is not set
        make_session_options().get_session_config_entry(X64_QUANT_PRECISION)
    reference = ort_engine.make_session(path, make_session_options(threads=1)).run(None, x)[0]
    assert capsys.readouterr().err == ""

    monkeypatch.setattr(ort_engine, "cpu_info", lambda: {"int8_kernel": "avx2"})
    options = make_session_options(threads=1)
    assert options.get_session_config_entry(X64_QUANT_PRECISION) == "1"
    session = ort_engine.make_session(path, options)  # onnxruntime refuses the remedy for this graph
    np.testing.assert_array_equal(session.run(None, x)[0], reference)  # this CPU: exact kernels either way
    err = capsys.readouterr().err
    assert f"{path}: onnxruntime cannot run this graph's INT8 exactly on a CPU without VNNI" in err


@pytest.mark.parametrize("graph", ["depthnet", "posenet", "resflownet"])
def test_manifest_records_the_kernels_each_int8_graph_is_exact_on(graph):
    """quantization.int8_kernels of the bundled manifest is what the graph's weights give."""
    manifest = load_manifest(resolve_model())
    model = onnx.load(str(manifest.path(graph, "int8")))
    assert manifest.quantization.int8_kernels[graph] == int8_kernels(model)


def test_which_engine_is_exact_on_which_cpu():
    from geonet_infer.core.int8_safety import int8_unsafe_reason

    over, within = {"avx2_u8s8": False}, {"avx2_u8s8": True}
    assert "beyond +-64" in int8_unsafe_reason("openvino", over, "avx2")
    assert "does not record" in int8_unsafe_reason("openvino", None, "avx2")
    assert int8_unsafe_reason("openvino", within, "avx2") is None
    assert int8_unsafe_reason("onnxruntime", over, "avx2") is None  # its sessions set the remedy
    for kernel in ("avx512_vnni", "avx_vnni", "amx_int8"):
        assert int8_unsafe_reason("openvino", over, kernel) is None


def test_auto_skips_an_engine_inexact_on_an_avx2_cpu(monkeypatch, capsys):
    """On a CPU without VNNI (stubbed), auto keeps OpenVINO off the bundled INT8 graphs (their
    weights pass +-64; OpenVINO's INT8 under qemu Haswell: DepthNet correlation 0.70 -> 0.47) and says
    why in summary.json's per-graph record; --backend openvino runs them after one warning line."""
    from geonet_infer.core import int8_safety
    from geonet_infer.core.cascade import GraphSet
    from geonet_infer.engines import OpenVinoEngine

    monkeypatch.setattr(int8_safety, "cpu_info", lambda: {"int8_kernel": "avx2"})
    manifest = load_manifest(resolve_model())
    graphs = GraphSet(manifest, "int8", "auto", 1)
    # the INT8 graphs; rigidflow runs FP32 (quantization.fp32_graphs), where auto may time OpenVINO faster
    int8_graphs = [name for name in graphs.runs if name not in manifest.quantization.fp32_graphs]
    assert int8_graphs and {graphs.runs[name]["engine"] for name in int8_graphs} == {"onnxruntime"}
    if not OpenVinoEngine.available():
        return
    assert "skipped openvino: openvino INT8 without VNNI" in graphs.runs["depthnet"]["why"]
    capsys.readouterr()
    GraphSet(manifest, "int8", "openvino", 1)
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 3 and all(line.startswith("geonet-infer: warning: ") for line in err), err


# /proc/cpuinfo excerpts (flags abridged to the ones that matter, plus neighbours)
ZEN3 = "model name\t: AMD EPYC 7763 64-Core Processor\nflags\t\t: fpu sse4_2 avx f16c avx2 bmi2 sha_ni vaes\n"
SPR = (
    "model name\t: Intel(R) Xeon(R) Platinum 8480+\n"
    "flags\t\t: avx2 avx512f avx512bw avx512_vnni avx_vnni amx_tile amx_int8\n"
)


def test_isa_from_proc_cpuinfo():
    from geonet_infer.engines.cpu import _from_proc, int8_kernel, isa_line

    model, isa = _from_proc(ZEN3)
    assert model == "AMD EPYC 7763 64-Core Processor" and int8_kernel(isa) == "avx2"
    assert isa_line({"isa": isa, "int8_kernel": "avx2"}) == "avx2 (INT8 kernel avx2: int16 pairs, saturating)"
    _, isa = _from_proc(SPR)
    assert [f for f, present in isa.items() if present] == ["avx2", "avx512f", "avx512_vnni", "avx_vnni", "amx_int8"]
    assert int8_kernel(isa) == "amx_int8"
    assert _from_proc("processor\t: 0\nBogoMIPS\t: 50.00\n") is None  # no flags line (not x86): numpy's detection


def test_isa_follows_cpuid_where_proc_cpuinfo_describes_another_cpu():
    """Under QEMU's user-mode emulation of a Haswell, /proc/cpuinfo is the host's (AMX, VNNI) while
    CPUID says AVX2 only: the INT8 kernel is then the saturating one, and the source says why."""
    from geonet_infer.engines.cpu import _from_proc, int8_kernel, reconcile

    _, host = _from_proc(SPR)
    haswell = {"avx2": True, "avx512f": False, "avx512_vnni": False, "avx_vnni": None, "amx_int8": None}
    isa, disagree = reconcile(host, haswell)
    assert disagree == ["avx512f", "avx512_vnni"] and int8_kernel(isa) == "avx2"
    assert isa["amx_int8"] is None and isa["avx_vnni"] is None  # CPUID bits numpy cannot read: unknown
    same = {"avx2": True, "avx512f": True, "avx512_vnni": True, "avx_vnni": None, "amx_int8": None}
    assert reconcile(host, same) == (host, [])  # agreeing: /proc/cpuinfo's fuller list holds

"""What ResFlowNet does not read is not computed: the channels a graph reads (models.onnx_graph), a graph
cut down to some of its outputs, and the rigid-flow op of the bundled model (a direct ResFlowNet) giving
the same outputs without the warped frame and the error."""

from __future__ import annotations

import numpy as np
import onnxruntime as ort
import pytest

import geonet_infer
from geonet_infer.core.graphs import GraphSet
from geonet_infer.core.rigid import RigidFlowOp
from geonet_infer.engines import make_engine, timing_feeds
from geonet_infer.io import list_images, read_camera
from geonet_infer.models import resolve_model
from geonet_infer.models.manifest import load_manifest
from geonet_infer.models.onnx_graph import channels_read, keep_outputs

MANIFEST = load_manifest(resolve_model(None))
SAMPLES = resolve_model(None).parents[1] / "samples" / "synth_seq"
FRAMES_AND_RIGID_FLOW = frozenset({0, 1, 2, 3, 4, 5, 9, 10})  # target, source, rigid flow of RESFLOW_INPUT


def session(graph) -> ort.InferenceSession:
    """A one-thread session of a graph file (a path) or of a graph's bytes."""
    options = ort.SessionOptions()
    options.intra_op_num_threads = 1
    model = graph if isinstance(graph, bytes) else str(graph)
    return ort.InferenceSession(model, options, providers=["CPUExecutionProvider"])


@pytest.mark.parametrize("precision", ["fp32", "int8"])
def test_the_bundled_resflownet_reads_the_frames_and_the_rigid_flow_and_nothing_else(precision):
    path = MANIFEST.path("resflownet", precision)
    assert channels_read(path.read_bytes(), "flow_input") == FRAMES_AND_RIGID_FLOW
    # what the graph does, independent of the parser: the other channels change nothing, a read one does
    graph = session(path)
    rng = np.random.default_rng(0)
    x = rng.normal(0, 0.5, (1, 12, MANIFEST.height, MANIFEST.width)).astype(np.float32)
    unread = x.copy()
    unread[:, [6, 7, 8, 11]] = rng.normal(3, 2, (1, 4, MANIFEST.height, MANIFEST.width))
    read = x.copy()
    read[:, 9] += 5.0
    before, after_unread, after_read = (np.stack(graph.run(None, {"flow_input": v})) for v in (x, unread, read))
    np.testing.assert_array_equal(after_unread, before)  # residual and flow
    assert not np.array_equal(after_read, before)  # the residual is the flow minus the rigid flow given


def test_a_graph_that_convolves_its_input_reads_all_of_it():
    assert channels_read(MANIFEST.path("depthnet", "fp32").read_bytes(), "image") is None


def test_the_rigid_flow_alone_comes_from_a_smaller_graph_with_the_same_values():
    path = MANIFEST.path("rigidflow", "fp32")
    whole = path.read_bytes()
    cut = keep_outputs(whole, ["rigid_flow"])
    assert cut is not None and len(cut) < len(whole)
    small, full = session(cut), session(path)
    assert [o.name for o in small.get_outputs()] == ["rigid_flow"]
    feeds = timing_feeds(make_engine(path, "onnxruntime", 1))
    feeds["pose"] = np.array([[0.05, -0.01, 0.4, 0.01, 0.02, -0.01]], np.float32)  # a real motion, not zero
    np.testing.assert_array_equal(small.run(None, feeds)[0], full.run(["rigid_flow"], feeds)[0])
    assert keep_outputs(whole, ["no_such_output"]) is None


def test_the_numpy_op_computes_only_what_it_is_asked_for():
    rng = np.random.default_rng(1)
    H, W = 24, 40
    feeds = {
        "depth": rng.uniform(2, 30, (2, 1, H, W)).astype(np.float32),
        "pose": rng.normal(0, 0.05, (2, 6)).astype(np.float32),
        "intrinsics": np.repeat(np.array([[[30.0, 0, 20], [0, 30, 12], [0, 0, 1]]], np.float32), 2, axis=0),
        "target": rng.normal(0, 0.5, (2, 3, H, W)).astype(np.float32),
        "source": rng.normal(0, 0.5, (2, 3, H, W)).astype(np.float32),
    }
    whole = RigidFlowOp(0.85)
    part = whole.only(["rigid_flow"])
    assert part.output_names == ["rigid_flow"] and sorted(whole.run(feeds)) == ["error", "rigid_flow", "warped"]
    out = part.run(feeds)
    assert list(out) == ["rigid_flow"]
    np.testing.assert_array_equal(out["rigid_flow"], whole.run(feeds)["rigid_flow"])


@pytest.mark.parametrize(
    "settings",
    [
        {},
        {"rigid_op": "numpy"},
        {"precision": "int8"},
        {"mode": "throughput"},
    ],
)
def test_the_bundled_model_skips_the_warp_and_gives_the_same_outputs(monkeypatch, settings):
    frames = list_images(SAMPLES / "image")[:4]
    camera = read_camera(SAMPLES / "calib.txt")
    lean = geonet_infer.load(**settings)
    assert lean.graph_set.engine("rigidflow").output_names == ["rigid_flow"]
    assert "warped and error not computed" in lean.graph_set.runs["rigidflow"]["why"]
    monkeypatch.setattr(GraphSet, "_skip_unread_rigid_outputs", lambda self: None)
    whole = geonet_infer.load(**settings)
    assert sorted(whole.graph_set.engine("rigidflow").output_names) == ["error", "rigid_flow", "warped"]
    for a, b in zip(lean.iter_sequence(frames, camera), whole.iter_sequence(frames, camera), strict=True):
        for field in ("depth", "flow", "rigid_flow", "camera_to_world"):
            x, y = getattr(a, field), getattr(b, field)
            assert (x is None) == (y is None)
            if x is not None:
                np.testing.assert_array_equal(x, y, err_msg=f"{a.name} {field}")
        assert (a.check is None) == (b.check is None) and (a.check is None or a.check == b.check)


def test_a_graph_the_reader_cannot_follow_keeps_the_whole_op(monkeypatch):
    import geonet_infer.core.graphs as graphs

    def unreadable(*_args):
        raise ValueError("wire type 3")

    monkeypatch.setattr(graphs, "channels_read", unreadable)
    predictor = geonet_infer.load()
    assert sorted(predictor.graph_set.engine("rigidflow").output_names) == ["error", "rigid_flow", "warped"]
    monkeypatch.setattr("geonet_infer.engines.onnxruntime.keep_outputs", unreadable)
    engine = make_engine(MANIFEST.path("rigidflow", "fp32"), "onnxruntime", 1).only(["rigid_flow"])
    assert sorted(engine.output_names) == ["error", "rigid_flow", "warped"]  # the whole graph, still right

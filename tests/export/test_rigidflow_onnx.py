"""rigidflow.onnx against closed forms computed by hand, and its structure.

The graph is exported once (48 x 64, from a batch-1 example) and checked:
no matrix-inverse op, GridSample spelled for opset 18, identity pose -> zero
flow, pure translation at constant depth -> (fx tx / Z, fy ty / Z), a general
pose against an independent float64 numpy projection, and parity with torch
on real KITTI frames (the ``kitti_raw`` fixture: skipped without the sample data, failed on CI).
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import onnx
import pytest
import torch

from export.to_onnx import OPSET, check_graph, export_graph, op_types
from export.verify import compare_graph
from export.wrappers import RigidFlowExport, example_inputs, io_spec
from geonet_infer import conventions
from geonet_infer.core.cascade import InputSpec
from geonet_infer.engines.onnxruntime import make_session
from geonet_infer.io import list_images, read_calib_K, read_image

H, W = 48, 64
FX, FY, CX, CY = 50.0, 40.0, 31.5, 23.5


@pytest.fixture(scope="module")
def graph(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("rigid") / "rigidflow.onnx"
    export_graph(
        RigidFlowExport(),
        example_inputs("rigidflow", H, W, 3, batch=1),
        io_spec("rigidflow", H, W, 3),
        path,
        {"geonet.graph": "rigidflow"},
    )
    return path


def K_matrix(batch: int = 1) -> np.ndarray:
    return np.tile(np.array([[FX, 0, CX], [0, FY, CY], [0, 0, 1]], np.float32), (batch, 1, 1))


def run(graph: Path, depth, pose, K, target, source) -> dict[str, np.ndarray]:
    session = make_session(graph)
    feed = dict(
        zip(
            ["depth", "pose", "intrinsics", "target", "source"],
            [np.ascontiguousarray(x, dtype=np.float32) for x in (depth, pose, K, target, source)],
        )
    )
    return dict(zip(["rigid_flow", "warped", "error"], session.run(None, feed)))


def random_image(rng, batch: int = 1) -> np.ndarray:
    return rng.uniform(-1, 1, (batch, 3, H, W)).astype(np.float32)


# ------------------------------------------------------------------------- structure
def test_structure_no_inverse_and_gridsample_spelling(graph):
    check_graph(graph, io_spec("rigidflow", H, W, 3), opset=OPSET)  # checker(full) + strict shapes
    ops = op_types(graph)
    assert "Inverse" not in ops and "GridSample" in ops
    model = onnx.load(str(graph))
    assert {o.domain for o in model.opset_import} <= {"", "ai.onnx"}  # no contrib (com.microsoft) ops
    grid = [n for n in model.graph.node if n.op_type == "GridSample"]
    assert len(grid) == 1
    attrs = {a.name: onnx.helper.get_attribute_value(a) for a in grid[0].attribute}
    assert OPSET < 20 and attrs["mode"] == b"bilinear"  # opset 16-19 spelling; 20+ would be b"linear"
    assert attrs["align_corners"] == int(conventions.SAMPLER.align_corners)
    assert attrs.get("padding_mode", b"zeros") == conventions.SAMPLER.padding.encode()
    for vi in [*model.graph.input, *model.graph.output]:
        assert vi.type.tensor_type.shape.dim[0].dim_param == "B"


def test_pixel_grid_is_computed_not_stored(graph):
    """u, v, 1 come from Range/Expand on the input shapes (``dynamic_spatial`` trace), not from
    H x W initializers (36 KB here, 0.64 MB at 128x416), yet the file declares static H, W."""
    model = onnx.load(str(graph))
    largest = max((onnx.numpy_helper.to_array(t).nbytes for t in model.graph.initializer), default=0)
    assert largest < 4096, f"an initializer of {largest} bytes: a folded pixel grid?"
    assert "Range" in op_types(graph)
    assert graph.stat().st_size < 100_000
    assert [d.dim_value for d in model.graph.input[0].type.tensor_type.shape.dim[2:]] == [H, W]
    dim_params = {d.dim_param for vi in model.graph.value_info for d in vi.type.tensor_type.shape.dim}
    assert dim_params <= {"", "B"}  # H, W and H*W pinned everywhere


# ------------------------------------------------------------------------- closed forms
def test_identity_pose_gives_zero_flow_and_identity_warp(graph):
    rng = np.random.default_rng(0)
    depth = rng.uniform(2.0, 40.0, (1, 1, H, W))
    image = random_image(rng)
    out = run(graph, depth, np.zeros((1, 6)), K_matrix(), image, image)
    assert np.abs(out["rigid_flow"]).max() <= 1e-4
    interior = (slice(None), slice(None), slice(1, -1), slice(1, -1))
    assert np.abs(out["warped"][interior] - image[interior]).max() <= 1e-4
    assert np.abs(out["error"][interior]).max() <= 1e-4  # DSSIM and L1 of identical images vanish


def test_pure_translation_at_constant_depth(graph):
    """X = Z K^-1 [u, v, 1]; X + t projects to u + fx tx / Z, v + fy ty / Z (tz = 0)."""
    Z, tx, ty = 10.0, 0.4, -0.25
    expected_u, expected_v = FX * tx / Z, FY * ty / Z  # = 2.0 px, -1.0 px, by hand
    assert (expected_u, expected_v) == (2.0, -1.0)
    rng = np.random.default_rng(1)
    source = random_image(rng)
    target = random_image(rng)
    out = run(graph, np.full((1, 1, H, W), Z), [[tx, ty, 0, 0, 0, 0]], K_matrix(), target, source)
    flow = out["rigid_flow"][0]
    assert np.abs(flow[0] - expected_u).max() <= 1e-4
    assert np.abs(flow[1] - expected_v).max() <= 1e-4
    # integer flow (2, -1): warped(u, v) = source(u + 2, v - 1) wherever that pixel exists
    warped = out["warped"][0]
    assert np.abs(warped[:, 1:, : W - 2] - source[0, :, : H - 1, 2:]).max() <= 1e-4
    # outside the source (zero padding): last two columns and first row read zeros
    assert np.abs(warped[:, :, W - 1]).max() <= 1e-4 and np.abs(warped[:, 0, :]).max() <= 1e-4


def _numpy_rigid_flow(depth: np.ndarray, pose: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Independent float64 reference: R = Rx Ry Rz, X_src = R X + t, pinhole projection."""
    tx, ty, tz, rx, ry, rz = pose
    Rx = np.array([[1, 0, 0], [0, math.cos(rx), -math.sin(rx)], [0, math.sin(rx), math.cos(rx)]])
    Ry = np.array([[math.cos(ry), 0, math.sin(ry)], [0, 1, 0], [-math.sin(ry), 0, math.cos(ry)]])
    Rz = np.array([[math.cos(rz), -math.sin(rz), 0], [math.sin(rz), math.cos(rz), 0], [0, 0, 1]])
    R = Rx @ Ry @ Rz
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    pix = np.stack([u, v, np.ones_like(u)]).reshape(3, -1)
    X = np.linalg.inv(K.astype(np.float64)) @ pix * depth.reshape(1, -1)
    p = K @ (R @ X + np.array([[tx], [ty], [tz]]))
    return (p[:2] / p[2:] - pix[:2]).reshape(2, H, W)


def test_general_pose_batch_matches_numpy_projection(graph):
    """Two different poses in one batch of 2 (the graph was exported from batch 1)."""
    rng = np.random.default_rng(2)
    depth = rng.uniform(3.0, 30.0, (2, 1, H, W))
    poses = np.array([[0.3, -0.1, 0.8, 0.02, -0.05, 0.03], [-0.2, 0.05, -0.4, -0.03, 0.04, -0.02]])
    out = run(graph, depth, poses, K_matrix(2), random_image(rng, 2), random_image(rng, 2))
    for b in range(2):
        expected = _numpy_rigid_flow(depth[b, 0], poses[b], K_matrix()[0].astype(np.float64))
        assert np.abs(out["rigid_flow"][b] - expected).max() <= 1e-3


def test_parity_with_torch_on_real_frames(graph, kitti_raw):
    files = list_images(kitti_raw / "image_02" / "data")[:2]
    frames = [cv2.resize(read_image(f), (W, H), interpolation=cv2.INTER_AREA) for f in files]
    K = read_calib_K(kitti_raw / "calib_cam_to_cam.txt", "P_rect_02")
    K = conventions.scale_intrinsics(K, W / 1242, H / 375).astype(np.float32)[None]
    v = np.linspace(0, 1, H)[:, None]
    depth = (4.0 + 40.0 * (1 - v) * np.ones((1, W)))[None, None].astype(np.float32)  # far at the top
    pose = np.array([[0.01, -0.005, 0.9, 0.002, -0.004, 0.001]], np.float32)
    spec = InputSpec.from_conventions(H, W)
    inputs = [depth, pose, K, spec.to_network(frames[1])[None], spec.to_network(frames[0])[None]]
    diffs = compare_graph(RigidFlowExport().eval(), graph, inputs)
    assert diffs["rigid_flow"]["max_abs"] <= 1e-3
    assert diffs["warped"]["relative"] <= 1e-3 and diffs["error"]["relative"] <= 1e-3
    with torch.no_grad():
        flow = RigidFlowExport()(*[torch.from_numpy(x) for x in inputs])[0]
    assert flow.abs().max() > 1.0  # a real motion was compared

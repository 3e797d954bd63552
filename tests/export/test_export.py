"""Export: torch vs onnxruntime parity on real frames, the manifest, INT8 and the CLI.

One module-scoped export (``small`` arch at 128x416, seeded random weights with
perturbed BN statistics, stage-flow checkpoint, fp32 + int8 with the accuracy
delta on a tiny synthetic held-out set) is shared by most tests. Parity tests
need the KITTI frames in ``../shared/realdata`` (the ``kitti_raw`` fixture: skipped
without them, failed on CI).
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import onnx
import pytest
import torch

from export.__main__ import main as export_main
from export.to_onnx import ExportCheckError, check_graph, op_types
from export.verify import compare_graph
from export.wrappers import GRAPH_NAMES, build_wrapper, io_spec
from geonet_infer import conventions
from geonet_infer.core.cascade import InputSpec
from geonet_infer.core.predictor import Predictor
from geonet_infer.engines.onnxruntime import make_session
from geonet_infer.errors import GeoNetError
from geonet_infer.io import list_images, read_calib_K, read_image
from geonet_infer.models.manifest import MANIFEST_NAME, Manifest, load_manifest, write_manifest
from tests.conftest import KITTI_RAW, REALDATA
from training.evaluate import onnx_depth_fn
from training.losses import LossWeights

REPO = Path(__file__).resolve().parents[2]
H, W = 128, 416

# Tolerances of the acceptance criteria.
DEPTH_REL_TOL = 1e-4  # max |ORT - torch| / range(torch)
FLOW_PX_TOL = 1e-3
POSE_TOL = 1e-5
# Derived rigid-op channels (warped image, DSSIM error): SSIM's ratio of tiny local variances
# turns ~1e-4 differences of the warped image into ~2e-4 of the error map in flat regions.
DERIVED_REL_TOL = 1e-3


def conventions_json() -> dict:
    """conventions.as_dict() as it reads back from JSON (tuples become lists)."""
    return json.loads(json.dumps(conventions.as_dict()))


# --------------------------------------------------------------------------- helpers
def perturb_model(model: torch.nn.Module, seed: int = 0) -> None:
    """Move BN running stats away from (0, 1) and give biases random values, so BN matters."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, buf in model.named_buffers():
            if name.endswith("running_mean"):
                buf.copy_(0.2 * torch.randn(buf.shape, generator=g))
            elif name.endswith("running_var"):
                buf.copy_(0.5 + 1.5 * torch.rand(buf.shape, generator=g))
        for name, p in model.named_parameters():
            if name.endswith("bias"):
                p.copy_(0.05 * torch.randn(p.shape, generator=g))


def save_small_checkpoint(path: Path, stage: str, height: int = H, width: int = W) -> None:
    from training.checkpoint import save_checkpoint
    from training.config import TrainConfig
    from training.model import GeoNet

    torch.manual_seed(1234)
    model = GeoNet("small", 2, with_flow=stage == "flow")
    perturb_model(model)
    cfg = TrainConfig(
        stage=stage, arch="small", height=height, width=width, data_dir="data/prepared-test", out_dir=str(path.parent)
    )
    save_checkpoint(
        path,
        model.eval(),
        torch.optim.Adam(model.parameters()),
        42,
        cfg,
        {"val_total": 0.5, "best_val_total": 0.5, "best_step": 42},
    )


def kitti_frames(kitti: Path, n: int = 3, start: int = 0) -> list[np.ndarray]:
    files = list_images(kitti / "image_02" / "data")[start : start + n]
    return [cv2.resize(read_image(f), (W, H), interpolation=cv2.INTER_AREA) for f in files]


def kitti_K(kitti: Path) -> np.ndarray:
    K = read_calib_K(kitti / "calib_cam_to_cam.txt", "P_rect_02")
    return conventions.scale_intrinsics(K, W / 1242, H / 375).astype(np.float32)


def to01(rgb: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(rgb).permute(2, 0, 1).float().div(255.0).unsqueeze(0)


def no_leftovers(out: Path) -> bool:
    return not out.exists() and not list(out.parent.glob(f"{out.name}.tmp-*"))


# --------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def work(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("export")


@pytest.fixture(scope="module")
def flow_ckpt(work) -> Path:
    path = work / "flow.pt"
    save_small_checkpoint(path, "flow")
    return path


@pytest.fixture(scope="module")
def synth(work) -> tuple[Path, Path]:
    """A tiny synthetic set (2 sequences x 5 frames, 1 held out) at H x W, via the real tools."""
    from training import prepare
    from training import synth as synth_mod

    synth_dir, prepared = work / "synth", work / "prepared"
    synth_mod.main(
        ["--out", str(synth_dir), "--sequences", "2", "--frames", "5", "--height", str(H), "--width", str(W)]
    )
    prepare.main(
        [
            "--kind",
            "synth",
            "--src",
            str(synth_dir),
            "--out",
            str(prepared),
            "--height",
            str(H),
            "--width",
            str(W),
            "--heldout",
            "1",
            "--workers",
            "1",
        ]
    )
    assert (prepared / "heldout.txt").is_file() and (synth_dir / "seq_0001" / "calib.txt").is_file()
    return synth_dir, prepared


@pytest.fixture(scope="module")
def model_dir(work, flow_ckpt, synth) -> Path:
    """fp32 + int8 export of the flow checkpoint through the CLI (batch-1 example inputs)."""
    synth_dir, prepared = synth
    calib = REALDATA / KITTI_RAW / "image_02" / "data"  # real frames where present, else synthetic ones
    if not calib.is_dir():
        calib = synth_dir / "seq_0000" / "image"
    out = work / "model"
    code = export_main(
        [
            "--checkpoint",
            str(flow_ckpt),
            "--out",
            str(out),
            "--precision",
            "fp32,int8",
            "--calib-data",
            str(calib),
            "--calib-frames",
            "6",
            "--eval-synth-dir",
            str(synth_dir),
            "--eval-prepared-dir",
            str(prepared),
            "--quiet",
        ]
    )
    assert code == 0
    return out


@pytest.fixture(scope="module")
def torch_model(flow_ckpt):
    from training.checkpoint import load_checkpoint, model_from_checkpoint

    return model_from_checkpoint(load_checkpoint(flow_ckpt))


# --------------------------------------------------------------------------- graph checks
def test_graphs_pass_checker_and_strict_shape_inference(model_dir):
    manifest = load_manifest(model_dir)
    for name in GRAPH_NAMES:
        entry = manifest.graph(name)
        model = check_graph(model_dir / entry.file, io_spec(name, H, W, 3), opset=18)  # raises on failure
        meta = {p.key: p.value for p in model.metadata_props}
        assert meta["geonet.graph"] == name
        assert json.loads(meta["geonet.conventions"]) == conventions_json()
        assert json.loads(meta["geonet.image_norm"]) == conventions_json()["image_norm"]
        assert "Inverse" not in op_types(model_dir / entry.file)


def test_streamed_save_is_read_as_the_same_model(tmp_path):
    """save_streamed writes each initializer in a graph record of its own (the export's memory peak);
    onnx parses it to exactly the message onnx.save_model writes, and onnxruntime gives the same output."""
    from onnx import TensorProto, helper, numpy_helper

    from export.to_onnx import save_streamed, set_metadata

    rng = np.random.default_rng(0)
    inits = [
        numpy_helper.from_array(rng.normal(size=shape).astype(np.float32), name)
        for name, shape in (("w1", (4, 3, 3, 3)), ("b1", (4,)), ("w2", (2, 4, 1, 1)))
    ]
    nodes = [
        helper.make_node("Conv", ["x", "w1", "b1"], ["h"], pads=[1, 1, 1, 1]),
        helper.make_node("Relu", ["h"], ["r"]),
        helper.make_node("Conv", ["r", "w2"], ["y"]),
    ]
    x = helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 3, 8, 8])
    y = helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, 2, 8, 8])
    model = helper.make_model(
        helper.make_graph(nodes, "g", [x], [y], inits, doc_string="graph doc"),
        opset_imports=[helper.make_opsetid("", 18)],
        producer_name="geonet export",
    )
    set_metadata(model, {"graph": "test", "arch": "none"})
    onnx.save_model(model, str(tmp_path / "save_model.onnx"))
    save_streamed(model, tmp_path / "streamed.onnx")
    files = (tmp_path / "save_model.onnx", tmp_path / "streamed.onnx")
    assert files[0].read_bytes() != files[1].read_bytes()  # another layout ...
    assert onnx.load(str(files[1])).SerializeToString() == onnx.load(str(files[0])).SerializeToString()  # same model
    onnx.checker.check_model(str(files[1]), full_check=True)
    image = rng.uniform(-1, 1, (1, 3, 8, 8)).astype(np.float32)
    want, got = (make_session(f).run(None, {"x": image})[0] for f in files)
    np.testing.assert_array_equal(got, want)


def test_rigidflow_stores_no_pixel_grid(model_dir):
    """At 128x416 a folded u, v or ones grid is a 213 KB initializer (0.64 MB of a 0.66 MB file);
    the graph builds the grid from the input shapes instead (RigidFlowExport.dynamic_spatial)."""
    path = model_dir / "rigidflow.onnx"
    model = onnx.load(str(path))
    largest = max((onnx.numpy_helper.to_array(t).nbytes for t in model.graph.initializer), default=0)
    assert largest < 4096, f"an initializer of {largest} bytes: a folded pixel grid?"
    assert path.stat().st_size < 100_000


def test_check_graph_rejects_wrong_io_names(model_dir, tmp_path):
    model = onnx.load(str(model_dir / "depthnet.onnx"))
    model.graph.output[1].name = "depth_renamed"
    for node in model.graph.node:
        node.output[:] = ["depth_renamed" if o == "depth" else o for o in node.output]
    onnx.save(model, str(tmp_path / "bad.onnx"))
    with pytest.raises(ExportCheckError, match="outputs"):
        check_graph(tmp_path / "bad.onnx", io_spec("depthnet", H, W, 3), opset=18)


# --------------------------------------------------------------------------- parity
def test_per_graph_parity_on_real_frames(model_dir, torch_model, kitti_raw):
    frames = kitti_frames(kitti_raw, 3)
    K = kitti_K(kitti_raw)
    report = {}
    # depthnet: a batch of 3 real frames (the graph was exported from a batch-1 example)
    spec = InputSpec.from_conventions(H, W, 3)
    norm = [spec.to_network(f)[None] for f in frames]
    images = np.concatenate(norm)
    d = compare_graph(build_wrapper("depthnet", torch_model), model_dir / "depthnet.onnx", [images])
    report["depth_rel"], report["disp_rel"] = d["depth"]["relative"], d["disparity"]["relative"]
    assert d["depth"]["relative"] <= DEPTH_REL_TOL and d["disparity"]["relative"] <= DEPTH_REL_TOL

    snippet = np.concatenate([norm[1], norm[0], norm[2]], axis=1)
    p = compare_graph(build_wrapper("posenet", torch_model), model_dir / "posenet.onnx", [snippet])
    report["pose_abs"], report["pose_matrix_abs"] = p["pose"]["max_abs"], p["pose_matrix"]["max_abs"]
    assert p["pose"]["max_abs"] <= POSE_TOL and p["pose_matrix"]["max_abs"] <= POSE_TOL

    # rigidflow + resflownet on the torch model's own depth and pose (t -> t+1)
    with torch.no_grad():
        depth = (1.0 / torch_model.depth_net(torch.from_numpy(norm[1]))[0]).numpy()
        pose = torch_model.pose_net(torch.from_numpy(snippet))[:, 1].numpy()
    rigid_in = [depth, pose, K[None], norm[1], norm[2]]
    r = compare_graph(build_wrapper("rigidflow", torch_model), model_dir / "rigidflow.onnx", rigid_in)
    report["rigid_flow_px"], report["warped_rel"], report["error_rel"] = (
        r["rigid_flow"]["max_abs"],
        r["warped"]["relative"],
        r["error"]["relative"],
    )
    assert r["rigid_flow"]["max_abs"] <= FLOW_PX_TOL
    assert r["warped"]["relative"] <= DERIVED_REL_TOL and r["error"]["relative"] <= DERIVED_REL_TOL

    rigid = build_wrapper("rigidflow", torch_model)
    with torch.no_grad():
        flow, warped, error = rigid(*[torch.from_numpy(np.asarray(x)) for x in rigid_in])
    flow_in = np.concatenate([norm[1], norm[2], warped.numpy(), flow.numpy(), error.numpy()], axis=1)
    f = compare_graph(build_wrapper("resflownet", torch_model), model_dir / "resflownet.onnx", [flow_in])
    report["flow_px"], report["residual_px"] = f["flow"]["max_abs"], f["residual_flow"]["max_abs"]
    assert f["flow"]["max_abs"] <= FLOW_PX_TOL and f["residual_flow"]["max_abs"] <= FLOW_PX_TOL
    print("\nper-graph parity (ORT vs torch):", json.dumps({k: float(f"{v:.3g}") for k, v in report.items()}))


def test_cascade_matches_torch_flow_forward(model_dir, torch_model, kitti_raw):
    """depth -> pose -> rigid op -> ResFlowNet in ORT vs GeoNet.flow_forward, scale 0, t -> t+1."""
    frames = kitti_frames(kitti_raw, 3, start=10)
    K = kitti_K(kitti_raw)
    predictor = Predictor(model_dir)
    flow = predictor.flow(frames, K)
    out = {
        "flow": flow.flow,
        "rigid_flow": flow.rigid_flow,
        "depth": flow.depth,
        "pose": predictor.pose(frames).vectors[1],
    }
    target = to01(frames[1])
    sources = torch.stack([to01(frames[0])[0], to01(frames[2])[0]]).unsqueeze(0)
    with torch.no_grad():
        fwd_full, _, _, _ = torch_model.flow_forward(target, sources, torch.from_numpy(K)[None])
        rigid, _, _ = torch_model.rigid_forward(target, sources, torch.from_numpy(K)[None])
    ref_flow = fwd_full[0][1].permute(1, 2, 0).numpy()  # rows i-major: row 1 = source t+1
    ref_rigid = rigid.fwd_flow[0][1].permute(1, 2, 0).numpy()
    ref_depth = (1.0 / rigid.disp[0][0, 0]).numpy()
    numbers = {
        "flow_px": float(np.abs(out["flow"] - ref_flow).max()),
        "rigid_flow_px": float(np.abs(out["rigid_flow"] - ref_rigid).max()),
        "depth_rel": float(np.abs(out["depth"] - ref_depth).max() / np.ptp(ref_depth)),
        "pose_abs": float(np.abs(out["pose"] - rigid.poses[0, 1].numpy()).max()),
    }
    print(
        "\ncascade parity (ORT vs GeoNet.flow_forward):", json.dumps({k: float(f"{v:.3g}") for k, v in numbers.items()})
    )
    assert numbers["flow_px"] <= FLOW_PX_TOL
    assert numbers["rigid_flow_px"] <= FLOW_PX_TOL
    assert numbers["depth_rel"] <= DEPTH_REL_TOL
    assert numbers["pose_abs"] <= POSE_TOL
    assert np.abs(ref_flow).max() > 0.1  # a non-trivial flow was compared


def test_dynamic_batch_from_batch1_export(model_dir, torch_model):
    """The CLI traced every graph from a batch-1 example; batch 2 and 3 must run and match torch."""
    g = torch.Generator().manual_seed(3)
    for batch in (2, 3):
        images = (torch.rand(batch, 3, H, W, generator=g) * 2 - 1).numpy()
        d = compare_graph(build_wrapper("depthnet", torch_model), model_dir / "depthnet.onnx", [images])
        assert d["depth"]["relative"] <= DEPTH_REL_TOL
        depth = 2.0 + 20.0 * torch.rand(batch, 1, H, W, generator=g)
        pose = 0.02 * (torch.rand(batch, 6, generator=g) - 0.5)
        K = torch.tensor([[200.0, 0, W / 2], [0, 200.0, H / 2], [0, 0, 1]]).repeat(batch, 1, 1)
        imgs = [torch.rand(batch, 3, H, W, generator=g) * 2 - 1 for _ in range(2)]
        r = compare_graph(
            build_wrapper("rigidflow", torch_model),
            model_dir / "rigidflow.onnx",
            [x.numpy() for x in (depth, pose, K, *imgs)],
        )
        assert r["rigid_flow"]["max_abs"] <= FLOW_PX_TOL
        session = make_session(model_dir / "posenet.onnx")
        pose_out = session.run(None, {"snippet": np.zeros((batch, 9, H, W), np.float32)})[0]
        assert pose_out.shape == (batch, 2, 6)


# --------------------------------------------------------------------------- manifest
def test_provenance_names_every_prepared_folder_the_stage_trained_on():
    from export.manifest import provenance

    mixed = {"config": {"data_dir": "data/synth40_flow", "extra_data_dirs": ["data/synthB_flow", "data/udacity"]}}
    assert (
        provenance("small", False, "test", ckpt=mixed).data_dir == "data/synth40_flow + data/synthB_flow + data/udacity"
    )
    assert provenance("small", False, "test", ckpt={"config": {"data_dir": "d"}}).data_dir == "d"
    assert provenance("small", True, "test").data_dir is None


def test_manifest_round_trip_and_conventions(model_dir, tmp_path):
    manifest = load_manifest(model_dir)
    # the alpha baked into rigidflow.onnx is recorded beside the conventions every manifest has
    assert manifest.conventions == conventions_json() | {"photometric_alpha": LossWeights.alpha_recon}
    assert manifest.photometric_alpha == 0.85
    assert (manifest.height, manifest.width, manifest.seq_length, manifest.arch) == (H, W, 3, "small")
    assert manifest.precisions == ("fp32", "int8") and not manifest.random_init
    assert Manifest.from_dict(json.loads(json.dumps(manifest.to_dict())), root=model_dir) == manifest
    assert manifest.provenance.checkpoint_sha256 and manifest.provenance.checkpoint_stage == "flow"
    assert manifest.provenance.data_dir == "data/prepared-test"
    assert manifest.metrics["best_step"] == 42
    for spec in manifest.graph("rigidflow").inputs:
        assert spec.shape[0] == "B" and spec.dtype == "float32"
    assert [t.name for t in manifest.graph("rigidflow").inputs] == ["depth", "pose", "intrinsics", "target", "source"]
    # written and read back through the same dataclasses
    copy = tmp_path / "copy"
    shutil.copytree(model_dir, copy)
    write_manifest(manifest, copy)
    assert load_manifest(copy) == manifest


@pytest.mark.parametrize("alpha", [None, 1.5, -0.1, "0.85", True])
def test_photometric_alpha_is_optional_and_in_0_1(tmp_path, alpha):
    """A manifest written before export recorded the alpha reads None; a recorded alpha outside
    [0, 1] or not a number is refused, naming the manifest."""
    model = tmp_path / "small_synth"
    shutil.copytree(REPO / "geonet_infer" / "models" / "small_synth", model)
    assert load_manifest(model).photometric_alpha == 0.85  # the bundled export records it
    raw = json.loads((model / MANIFEST_NAME).read_text())
    if alpha is None:
        del raw["conventions"]["photometric_alpha"]
    else:
        raw["conventions"]["photometric_alpha"] = alpha
    (model / MANIFEST_NAME).write_text(json.dumps(raw))
    if alpha is None:
        assert load_manifest(model).photometric_alpha is None
        return
    with pytest.raises(GeoNetError, match="photometric_alpha") as err:
        load_manifest(model)
    assert str(model / MANIFEST_NAME) in str(err.value)


def test_manifest_detects_flipped_byte(model_dir, tmp_path):
    copy = tmp_path / "m"
    shutil.copytree(model_dir, copy)
    target = copy / "int8" / "posenet.onnx"
    data = bytearray(target.read_bytes())
    data[len(data) // 2] ^= 0x01
    target.write_bytes(bytes(data))
    with pytest.raises(GeoNetError, match="sha256 mismatch") as err:
        load_manifest(copy)
    assert err.value.path == target and "posenet.onnx" in str(err.value)


def test_manifest_errors_name_the_file(model_dir, tmp_path):
    copy = tmp_path / "m"
    shutil.copytree(model_dir, copy)
    (copy / "posenet.onnx").unlink()
    with pytest.raises(GeoNetError, match="missing") as err:
        load_manifest(copy)
    assert err.value.path == copy / "posenet.onnx"
    raw = json.loads((model_dir / MANIFEST_NAME).read_text())
    for mutate, pattern in (
        (lambda d: d.update(schema_version=99), "schema_version"),
        (lambda d: d.pop("conventions"), "conventions"),
        (lambda d: d.pop("height"), "missing key"),
    ):
        bad = json.loads(json.dumps(raw))
        mutate(bad)
        shutil.copytree(model_dir, tmp_path / "b", dirs_exist_ok=True)
        (tmp_path / "b" / MANIFEST_NAME).write_text(json.dumps(bad))
        with pytest.raises(GeoNetError, match=pattern) as err:
            load_manifest(tmp_path / "b")
        assert err.value.path == tmp_path / "b" / MANIFEST_NAME


# --------------------------------------------------------------------------- int8
def test_int8_graphs_load_run_and_report_delta(model_dir):
    manifest = load_manifest(model_dir)
    assert manifest.graph("rigidflow", "int8").file == "rigidflow.onnx"  # rigid op stays fp32
    assert manifest.graph("rigidflow", "int8").precision == "fp32"
    assert not (model_dir / "int8" / "rigidflow.onnx").exists()
    assert "QuantizeLinear" not in op_types(model_dir / "rigidflow.onnx")
    for name in ("depthnet", "posenet", "resflownet"):
        entry = manifest.graph(name, "int8")
        assert entry.file == f"int8/{name}.onnx" and entry.precision == "int8"
        assert {"QuantizeLinear", "DequantizeLinear"} <= op_types(model_dir / entry.file)
        assert (model_dir / entry.file).stat().st_size < 0.5 * (model_dir / f"{name}.onnx").stat().st_size
    quant = manifest.quantization
    assert quant.per_channel and quant.fp32_graphs == ("rigidflow",) and quant.op_types == ()  # every type
    # ResFlowNet's output layer (flow in pixels) stays fp32: its kernels are plain initializers
    flow8 = onnx.load(str(model_dir / "int8" / "resflownet.onnx"))
    float_kernels = {i.name for i in flow8.graph.initializer if i.data_type == onnx.TensorProto.FLOAT}
    writer = {out: node for node in flow8.graph.node for out in node.output}
    assert writer["residual_flow"].op_type == "Conv" and writer["residual_flow"].input[1] in float_kernels
    assert any(line.startswith("fp32 nodes:") for line in quant.graph_notes["resflownet"])
    # which x86 kernels compute each graph exactly; per-channel 8-bit weights reach +-127 in every channel
    assert set(quant.int8_kernels) == {"depthnet", "posenet", "resflownet"}
    assert quant.int8_kernels["depthnet"]["vnni"] and not quant.int8_kernels["depthnet"]["avx2_u8s8"]
    delta = quant.accuracy_delta
    for key in ("depth_abs_rel", "flow_epe_noc"):
        assert np.isfinite(delta[key]["delta"])
        assert delta[key]["delta"] == pytest.approx(delta[key]["int8"] - delta[key]["fp32"])
    # the quantised cascade runs and stays near fp32 on a synthetic-size input
    rng = np.random.default_rng(0)
    frames = [rng.integers(0, 256, (H, W, 3), dtype=np.uint8) for _ in range(3)]
    K = np.array([[200.0, 0, W / 2], [0, 200.0, H / 2], [0, 0, 1]], np.float32)
    fp32, int8 = Predictor(model_dir, "fp32").flow(frames, K), Predictor(model_dir, "int8").flow(frames, K)
    assert np.isfinite(int8.flow).all() and int8.flow.shape == (H, W, 2)
    assert np.abs(int8.depth - fp32.depth).mean() < 0.2 * np.abs(fp32.depth).mean()
    # int8 PoseNet still returns rigid transforms built from its own vectors ([R | t], t = tx ty tz):
    # quantising the Sin/Cos/Concat tail once collapsed them to ~identity.
    pose8 = Predictor(model_dir, "int8").pose(frames)
    R = pose8.matrices[:, :3, :3]
    assert np.abs(pose8.vectors[:, :3]).max() > 1e-4
    np.testing.assert_allclose(pose8.matrices[:, :3, 3], pose8.vectors[:, :3], atol=1e-6)
    np.testing.assert_allclose(R @ R.transpose(0, 2, 1), np.broadcast_to(np.eye(3), R.shape), atol=1e-5)
    np.testing.assert_allclose(pose8.matrices[:, 3], np.broadcast_to([0, 0, 0, 1], (2, 4)), atol=1e-7)


# --------------------------------------------------------------------------- CLI
def test_cli_random_init_small(tmp_path):
    out = tmp_path / "rand"
    out.mkdir()
    (out / "stale.txt").write_text("old")
    args = ["--arch", "small", "--random-init", "--out", str(out), "--height", "64", "--width", "208", "--quiet"]
    assert export_main(args) == 2  # exists, no --force
    assert (out / "stale.txt").exists()
    assert export_main(args + ["--force"]) == 0
    assert not (out / "stale.txt").exists() and not list(tmp_path.glob("rand.tmp-*"))
    manifest = load_manifest(out)
    assert manifest.random_init and manifest.provenance.random_init and manifest.arch == "small"
    assert manifest.graph_names() == GRAPH_NAMES and manifest.quantization is None
    with pytest.raises(GeoNetError, match="random-init"):
        onnx_depth_fn(Predictor(out))
    frames = [np.full((64, 208, 3), 100 + 10 * i, np.uint8) for i in range(3)]
    res = Predictor(out).flow(frames, np.array([[100.0, 0, 104], [0, 100, 32], [0, 0, 1]], np.float32))
    assert res.flow.shape == (64, 208, 2) and np.isfinite(res.flow).all()


def test_cli_wrong_stage_checkpoint(tmp_path, capsys):
    ckpt = tmp_path / "rigid.pt"
    save_small_checkpoint(ckpt, "rigid", 64, 208)
    out = tmp_path / "m"
    assert export_main(["--checkpoint", str(ckpt), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert str(ckpt) in err and "resflownet.onnx needs a stage 'flow' checkpoint" in err
    assert "--graphs depthnet,posenet,rigidflow" in err
    assert no_leftovers(out)
    # the hint works: the rigid graphs alone export from a rigid checkpoint
    assert (
        export_main(["--checkpoint", str(ckpt), "--out", str(out), "--graphs", "depthnet,posenet,rigidflow", "--quiet"])
        == 0
    )
    manifest = load_manifest(out)
    assert manifest.graph_names() == ("depthnet", "posenet", "rigidflow")
    assert manifest.provenance.checkpoint_stage == "rigid" and (manifest.height, manifest.width) == (64, 208)
    with pytest.raises(GeoNetError, match="stage 'flow'"):
        manifest.graph("resflownet")


def test_cli_exports_a_weights_file_of_training_checkpoint(tmp_path, flow_ckpt, torch_model, kitti_raw):
    """``python -m training.checkpoint --combine`` writes a weights file; export takes it as --checkpoint.

    The weights file stores conv kernels as float16, so its graphs agree with the full checkpoint's
    torch model to float16 rounding, not to the 1e-4 of the parity test.
    """
    from training.checkpoint import combine_weights

    weights = tmp_path / "combined.pt"
    combine_weights(flow_ckpt, flow_ckpt, weights)
    out = tmp_path / "m"
    assert export_main(["--checkpoint", str(weights), "--out", str(out), "--quiet"]) == 0
    manifest = load_manifest(out)
    assert manifest.provenance.checkpoint_stage == "flow" and manifest.graph_names() == GRAPH_NAMES
    assert manifest.provenance.checkpoint_step == 42  # the training that made DepthNet/PoseNet (the fixture's)
    spec = InputSpec.from_conventions(H, W, 3)
    images = np.concatenate([spec.to_network(f)[None] for f in kitti_frames(kitti_raw, 2)])
    d = compare_graph(build_wrapper("depthnet", torch_model), out / "depthnet.onnx", [images])
    assert d["depth"]["relative"] <= 1e-2
    assert d["depth"]["relative"] > DEPTH_REL_TOL  # float16 kernels: the graphs came from the weights file


def test_cli_input_errors(tmp_path, capsys, flow_ckpt):
    out = tmp_path / "m"
    assert export_main(["--arch", "resnet18", "--random-init", "--out", str(out)]) == 2
    assert "unknown arch" in capsys.readouterr().err
    empty = tmp_path / "empty"
    empty.mkdir()
    assert (
        export_main(
            ["--checkpoint", str(flow_ckpt), "--out", str(out), "--precision", "fp32,int8", "--calib-data", str(empty)]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert str(empty) in err and "no images" in err
    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    assert export_main(["--arch", "small", "--random-init", "--out", str(blocker / "sub"), "--quiet"]) == 2
    assert "cannot create the output directory" in capsys.readouterr().err
    assert export_main(["--checkpoint", str(tmp_path / "nope.pt"), "--out", str(out)]) == 2
    assert "nope.pt" in capsys.readouterr().err
    frames = REPO / "geonet_infer" / "samples" / "synth_seq" / "image"
    int8 = ["--checkpoint", str(flow_ckpt), "--out", str(out), "--precision", "fp32,int8", "--calib-data", str(frames)]
    assert export_main([*int8, "--int8-ops", "Conv,Bogus"]) == 2
    err = capsys.readouterr().err
    assert "unknown --int8-ops ['Bogus']" in err and "Resize" in err  # the choices are listed
    assert no_leftovers(out)


def test_cli_failure_leaves_no_partial_directory(tmp_path, monkeypatch):
    import export.build as build

    calls = []
    real = build.export_graph

    def fail_on_second(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise ExportCheckError("simulated failure")
        return real(*args, **kwargs)

    monkeypatch.setattr(build, "export_graph", fail_on_second)
    out = tmp_path / "m"
    assert (
        export_main(
            [
                "--arch",
                "small",
                "--random-init",
                "--out",
                str(out),
                "--height",
                "64",
                "--width",
                "208",
                "--graphs",
                "posenet,rigidflow",
                "--quiet",
            ]
        )
        == 1
    )
    assert len(calls) == 2 and no_leftovers(out)


@pytest.mark.slow
def test_cli_and_library_write_the_same_model_directory(tmp_path):
    """``python -m export`` only parses flags into an ExportConfig and calls export_model."""
    from export import ExportConfig, export_model

    cli, lib = tmp_path / "cli", tmp_path / "lib"
    run = subprocess.run(
        [
            sys.executable,
            "-m",
            "export",
            "--arch",
            "small",
            "--random-init",
            "--seed",
            "3",
            "--out",
            str(cli),
            "--height",
            "32",
            "--width",
            "64",
            "--graphs",
            "posenet,rigidflow",
            "--quiet",
        ],
        cwd=REPO,
        capture_output=True,
        text=True,
    )
    assert run.returncode == 0, run.stderr
    assert (
        export_model(
            ExportConfig(
                out=lib,
                arch="small",
                random_init=True,
                seed=3,
                height=32,
                width=64,
                graphs=("posenet", "rigidflow"),
                quiet=True,
            )
        )
        == lib
    )

    def manifest_without_date(d: Path) -> dict:
        m = json.loads((d / MANIFEST_NAME).read_text())
        del m["provenance"]["export_date"]
        return m

    assert manifest_without_date(cli) == manifest_without_date(lib)
    assert sorted(p.name for p in cli.iterdir()) == sorted(p.name for p in lib.iterdir())
    for graph in ("posenet.onnx", "rigidflow.onnx"):  # same files, not only the same manifest
        assert (cli / graph).read_bytes() == (lib / graph).read_bytes()


@pytest.mark.slow
@pytest.mark.parametrize("arch", ["resnet50", "vgg"])
def test_large_arch_depthnet_parity(arch, tmp_path):
    """resnet50 / vgg DepthNet (vgg: TF-legacy bilinear pred upsampling as Gather ops) match torch."""
    from export.to_onnx import export_graph
    from export.wrappers import example_inputs
    from training.model import GeoNet

    torch.manual_seed(0)
    model = GeoNet(arch, 2).eval()
    perturb_model(model)
    h, w = 64, 208
    wrapper = build_wrapper("depthnet", model)
    export_graph(wrapper, example_inputs("depthnet", h, w, 3), io_spec("depthnet", h, w, 3), tmp_path / "d.onnx")
    images = example_inputs("depthnet", h, w, 3, batch=2, generator=torch.Generator().manual_seed(1))[0].numpy()
    d = compare_graph(wrapper, tmp_path / "d.onnx", [images])
    assert d["depth"]["relative"] <= DEPTH_REL_TOL and d["disparity"]["relative"] <= DEPTH_REL_TOL


def test_depth_graph_of_a_scale_normalized_model_normalizes_its_disparity():
    """--scale-normalize trains on disparity / its mean; the exported depth must match that scale."""
    from training.model import GeoNet

    torch.manual_seed(0)
    image = torch.rand(2, 3, 32, 96) * 2 - 1
    plain = GeoNet("small", scale_normalize=False).eval()
    normalized = GeoNet("small", scale_normalize=True).eval()
    normalized.load_state_dict(plain.state_dict())
    with torch.no_grad():
        raw, _ = build_wrapper("depthnet", plain)(image)
        disparity, depth = build_wrapper("depthnet", normalized)(image)
    expected = raw / raw.mean(dim=(1, 2, 3), keepdim=True)  # the definition, per image
    torch.testing.assert_close(disparity, expected)
    torch.testing.assert_close(depth, 1.0 / expected)

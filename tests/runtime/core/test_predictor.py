"""geonet_infer.Predictor: wiring, resolution mapping, sequences, threads, timings and input errors.

Only the bundled model (random init today, a trained one later with the same I/O), numpy,
OpenCV and onnxruntime: no torch. Golden values come from closed-form facts, from numpy /
OpenCV code written here, or from the ONNX graphs driven by hand with onnxruntime; nothing
depends on the weights' values.
"""

from __future__ import annotations

import json
import shutil
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np
import onnxruntime as ort
import pytest

import geonet_infer
from geonet_infer import GeoNetError
from geonet_infer.core.cascade import calibration_input
from geonet_infer.engines import ENGINES, openvino_available
from geonet_infer.io import Camera, read_camera

PKG = Path(geonet_infer.__file__).resolve().parent
MODEL_DIR = PKG / "models" / "small_synth"
SAMPLE = PKG / "samples" / "synth_seq"
KITTI_RAW = "kitti_raw_2011_09_26_sfnd"
H, W = 128, 416  # the bundled model's graph size (checked against the manifest below)
TOL = dict(rtol=1e-5, atol=1e-5)


# ----------------------------------------------------------------------------- helpers / fixtures
def imread_rgb(path) -> np.ndarray:
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert bgr is not None, path
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def sample_K() -> np.ndarray:
    """K of the sample sequence, parsed here from its 'K: fx 0 cx 0 fy cy 0 0 1' line."""
    key, values = (SAMPLE / "calib.txt").read_text().split(":", 1)
    assert key.strip() == "K"
    return np.array([float(v) for v in values.split()], dtype=np.float64).reshape(3, 3)


def upscale2(rgb: np.ndarray) -> np.ndarray:
    """Nearest-neighbour 2x upscaling (each pixel becomes a 2x2 block)."""
    return np.repeat(np.repeat(rgb, 2, axis=0), 2, axis=1)


def normalise(rgb: np.ndarray) -> np.ndarray:
    """uint8 RGB (H, W, 3) -> float32 (3, H, W) with the paper's x / 255 * 2 - 1."""
    return (rgb.astype(np.float32) / 255.0 * 2.0 - 1.0).transpose(2, 0, 1)


@pytest.fixture(scope="module")
def predictor():
    return geonet_infer.load()


@pytest.fixture(scope="module")
def frames() -> list[np.ndarray]:
    files = sorted((SAMPLE / "image").glob("*.png"))
    assert len(files) >= 10
    out = [imread_rgb(f) for f in files]
    assert all(f.shape == (H, W, 3) for f in out)
    return out


@pytest.fixture(scope="module")
def K() -> np.ndarray:
    return sample_K()


@pytest.fixture(scope="module")
def kitti(realdata):
    """Three consecutive 1242x375 KITTI raw frames and their Camera."""
    drive = realdata / KITTI_RAW
    files = sorted((drive / "image_02" / "data").glob("*.png"))[:3]
    return [imread_rgb(f) for f in files], read_camera(drive / "calib_cam_to_cam.txt")


def test_bundled_model_is_the_documented_one(predictor):
    manifest = json.loads((MODEL_DIR / "manifest.json").read_text())
    assert Path(predictor.model_dir).resolve() == MODEL_DIR
    assert (manifest["height"], manifest["width"], manifest["seq_length"]) == (H, W, 3)
    assert predictor.seq_length == 3


# ----------------------------------------------------------------------------- 1. graph wiring
def test_depth_pose_flow_match_the_graphs_driven_by_hand(predictor, frames, K):
    manifest = json.loads((MODEL_DIR / "manifest.json").read_text())
    graphs = manifest["graphs"]["fp32"]

    def run(name, **feeds):
        sess = ort.InferenceSession(str(MODEL_DIR / graphs[name]["file"]), providers=["CPUExecutionProvider"])
        outs = sess.run(None, {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in feeds.items()})
        return dict(zip([o.name for o in sess.get_outputs()], outs))

    prev, tgt, nxt = frames[3:6]
    x_prev, x_tgt, x_nxt = (normalise(f)[None] for f in (prev, tgt, nxt))
    disp = run("depthnet", image=x_tgt)["disparity"]  # (1, 1, H, W)
    pose = run("posenet", snippet=np.concatenate([x_tgt, x_prev, x_nxt], axis=1))  # [target, prev, next]
    rigid = run(
        "rigidflow",
        depth=1.0 / disp,
        pose=pose["pose"][:, 1],
        intrinsics=K[None].astype(np.float32),
        target=x_tgt,
        source=x_nxt,
    )
    hand_input = np.concatenate([x_tgt, x_nxt, rigid["warped"], rigid["rigid_flow"], rigid["error"]], axis=1)

    d = predictor.depth(tgt)
    assert d.depth.shape == (H, W) and d.depth.dtype == np.float32 and d.undistorted is False
    np.testing.assert_allclose(d.disparity, disp[0, 0], **TOL)
    # depth = 1 / disparity turns the disparity's absolute tolerance into a relative one of
    # atol / disparity, largest at the farthest pixel.
    depth_tol = dict(rtol=TOL["rtol"] + TOL["atol"] / float(disp.min()), atol=0)
    np.testing.assert_allclose(d.depth, 1.0 / disp[0, 0], **depth_tol)

    p = predictor.pose([prev, tgt, nxt])
    assert p.matrices.shape == (2, 4, 4) and p.vectors.shape == (2, 6)
    np.testing.assert_allclose(p.matrices, pose["pose_matrix"][0], **TOL)
    np.testing.assert_allclose(p.vectors, pose["pose"][0], **TOL)

    f = predictor.flow([prev, tgt, nxt], K)
    assert f.flow.shape == (H, W, 2) and f.flow.dtype == np.float32
    # Rigid flow = projected pixel - pixel in float32: its resolution is the ulp of coordinates
    # near 416 (3e-5 px), and the hand-normalised input differs from the runtime's by an ulp.
    np.testing.assert_allclose(f.rigid_flow, rigid["rigid_flow"][0].transpose(1, 2, 0), rtol=1e-5, atol=1.5e-4)
    np.testing.assert_allclose(f.depth, 1.0 / disp[0, 0], **depth_tol)
    np.testing.assert_allclose(f.pose, pose["pose_matrix"][0, 1], **TOL)  # target -> NEXT frame
    # ResFlowNet input [target, source, warped, rigid flow, error]: built here vs the runtime's ...
    flow_input = calibration_input(predictor.graph_set, predictor.spec, [prev, tgt, nxt], K)
    assert flow_input.shape == (1, 12, H, W)
    # A sampling point off by the rigid-flow tolerance (1.5e-4 px) moves a bilinear sample of the
    # warped image (and so the error channel) by up to that times the largest step between
    # neighbouring pixels, 2 in the [-1, 1] range.
    # The bundled ResFlowNet reads neither the warped frame nor the error (a direct flow net): the runtime
    # does not compute them and passes zeros (tests/runtime/core/test_unread_inputs.py).
    if predictor.graph_set.engine("rigidflow").output_names == ["rigid_flow"]:
        unread = [6, 7, 8, 11]
        assert not flow_input[:, unread].any()
        hand_input[:, unread] = 0.0
    np.testing.assert_allclose(flow_input, hand_input, rtol=1e-5, atol=2 * 1.5e-4)
    # ... and ResFlowNet on the runtime's own input gives its flow (no ulp amplification here).
    res = run("resflownet", flow_input=flow_input)
    np.testing.assert_allclose(f.flow, res["flow"][0].transpose(1, 2, 0), **TOL)
    np.testing.assert_allclose(f.residual_flow, res["residual_flow"][0].transpose(1, 2, 0), **TOL)
    np.testing.assert_allclose(f.flow, f.rigid_flow + f.residual_flow, rtol=1e-5, atol=1e-5)
    assert f.undistorted is False


# ----------------------------------------------------------------------------- 2. resolution mapping
def test_kitti_resolution_maps_back_to_the_input_size(predictor, kitti):
    rgbs, cam = kitti
    h_in, w_in = rgbs[0].shape[:2]
    assert (h_in, w_in) == (375, 1242)
    big = predictor.flow(rgbs, cam)
    assert big.flow.shape == big.rigid_flow.shape == (375, 1242, 2) and big.flow.dtype == np.float32
    assert big.depth.shape == (375, 1242) and big.depth.dtype == np.float32
    d = predictor.depth(rgbs[1])
    assert d.depth.shape == d.disparity.shape == (375, 1242) and d.depth.dtype == np.float32
    np.testing.assert_allclose(d.depth, 1.0 / d.disparity, rtol=1e-6)
    np.testing.assert_allclose(big.depth, d.depth, **TOL)

    # The same frames resized here with INTER_AREA and K scaled by hand run at the graph size,
    # where nothing is resized; mapping those outputs back with OpenCV must give the big result.
    small = [cv2.resize(f, (W, H), interpolation=cv2.INTER_AREA) for f in rgbs]
    sx, sy = W / w_in, H / h_in
    K_small = np.array(cam.K, dtype=np.float64)
    K_small[0] *= sx
    K_small[1] *= sy
    s = predictor.flow(small, K_small)
    assert s.flow.shape == (H, W, 2)
    expected = cv2.resize(s.flow, (w_in, h_in), interpolation=cv2.INTER_LINEAR) * np.float32([1 / sx, 1 / sy])
    np.testing.assert_allclose(big.flow, expected, rtol=1e-4, atol=1e-3)
    disp_small = predictor.depth(small[1]).disparity
    expected_depth = 1.0 / cv2.resize(disp_small, (w_in, h_in), interpolation=cv2.INTER_LINEAR)
    np.testing.assert_allclose(d.depth, expected_depth, rtol=1e-5)


# ----------------------------------------------------------------------------- 3. scaling law
def test_flow_scales_with_the_input_size_and_depth_does_not(predictor, frames, K):
    small_frames = frames[0:3]
    big_frames = [upscale2(f) for f in small_frames]
    for s, b in zip(small_frames, big_frames):  # premise: the network sees identical inputs
        np.testing.assert_array_equal(cv2.resize(b, (W, H), interpolation=cv2.INTER_AREA), s)
    K2 = K.copy()
    K2[:2] *= 2.0  # fx, cx, fy, cy doubled (skew is 0)
    small = predictor.flow(small_frames, K)
    big = predictor.flow(big_frames, K2)
    assert big.flow.shape == (2 * H, 2 * W, 2)
    for name in ("flow", "rigid_flow"):
        mean_small = getattr(small, name).astype(np.float64).mean(axis=(0, 1))
        mean_big = getattr(big, name).astype(np.float64).mean(axis=(0, 1))
        np.testing.assert_allclose(mean_big, 2 * mean_small, rtol=1e-3, atol=1e-6, err_msg=name)
    assert big.depth.mean() == pytest.approx(small.depth.mean(), rel=1e-3)
    np.testing.assert_allclose(big.pose, small.pose, **TOL)


# ----------------------------------------------------------------------------- 4. batches
def test_depth_of_a_list_equals_depth_of_each_image(predictor, frames):
    a = frames[0]
    b = upscale2(frames[1])
    c = cv2.resize(frames[2], (500, 150), interpolation=cv2.INTER_LINEAR)
    d = cv2.resize(frames[3], (300, 100), interpolation=cv2.INTER_AREA)  # smaller than the graph
    batch = predictor.depth([a, b, c, d])
    assert isinstance(batch, list) and len(batch) == 4
    for img, r in zip([a, b, c, d], batch):
        single = predictor.depth(img)
        assert r.depth.shape == img.shape[:2]
        np.testing.assert_allclose(r.depth, single.depth, **TOL)
        np.testing.assert_allclose(r.disparity, single.disparity, **TOL)
    assert predictor.depth([]) == []


# ----------------------------------------------------------------------------- 5. sequences
def test_predict_sequence_matches_single_calls(predictor, frames, K):
    seq_frames = frames[:6]
    seq = predictor.predict_sequence(seq_frames, K)
    assert [f.index for f in seq.frames] == list(range(6))
    assert seq.depth.shape == (6, H, W) and seq.flow.shape == (5, H, W, 2) and seq.trajectory.shape == (6, 4, 4)

    for img, fr in zip(seq_frames, seq.frames):
        np.testing.assert_allclose(fr.depth, predictor.depth(img).depth, **TOL)

    t = 2  # a middle frame: the snippet centred on it
    mid = predictor.flow(seq_frames[t - 1 : t + 2], K)
    np.testing.assert_allclose(seq.frames[t].flow, mid.flow, **TOL)
    np.testing.assert_allclose(seq.frames[t].rigid_flow, mid.rigid_flow, **TOL)
    np.testing.assert_allclose(seq.frames[t].pose_to_next, mid.pose, **TOL)

    f0, f1 = seq_frames[:2]  # the first frame: the previous neighbour is replicated
    pair = predictor.flow([f0, f1], K)
    padded = predictor.flow([f0, f0, f1], K)
    np.testing.assert_allclose(seq.frames[0].flow, pair.flow, **TOL)
    np.testing.assert_allclose(seq.frames[0].flow, padded.flow, **TOL)
    np.testing.assert_allclose(pair.pose, padded.pose, **TOL)

    last = seq.frames[-1]
    assert last.flow is None and last.rigid_flow is None and last.pose_to_next is None

    np.testing.assert_array_equal(seq.frames[0].camera_to_world, np.eye(4))
    for a, b in zip(seq.frames[:-1], seq.frames[1:]):
        np.testing.assert_allclose(
            b.camera_to_world, a.camera_to_world @ np.linalg.inv(a.pose_to_next), rtol=0, atol=1e-6
        )  # PoseNet's R is orthonormal to float32 precision

    for other in (
        predictor.predict_sequence(seq_frames, K, batch_size=1),
        predictor.predict_sequence((f for f in seq_frames), K, batch_size=4),
    ):
        assert len(other.frames) == 6
        np.testing.assert_allclose(other.depth, seq.depth, **TOL)
        np.testing.assert_allclose(other.flow, seq.flow, **TOL)
        np.testing.assert_allclose(other.trajectory, seq.trajectory, **TOL)


def test_iter_sequence_of_paths_names_frames_after_the_files(predictor, K):
    files = sorted((SAMPLE / "image").glob("*.png"))[:3]
    names = [r.name for r in predictor.iter_sequence(iter(files), K)]
    assert names == [f.stem for f in files]


# ----------------------------------------------------------------------------- 6. threads
@pytest.mark.parametrize("backend", ENGINES)
def test_one_predictor_shared_by_8_threads_gives_identical_results(predictor, frames, K, backend):
    if backend != "onnxruntime":
        if not openvino_available():
            pytest.skip(f"the [{backend}] extra is not installed")
        predictor = geonet_infer.load(backend=backend)
    snippets = [frames[i : i + 3] for i in range(8)]
    sequential = [predictor.flow(s, K) for s in snippets]
    with ThreadPoolExecutor(max_workers=8) as pool:
        concurrent = list(pool.map(lambda s: predictor.flow(s, K), snippets))
    for s, c in zip(sequential, concurrent):
        for name in ("flow", "rigid_flow", "residual_flow", "depth", "pose"):
            assert np.array_equal(getattr(s, name), getattr(c, name)), name
    assert not np.array_equal(sequential[0].depth, sequential[1].depth)  # the snippets really differ


# ----------------------------------------------------------------------------- 7. timings
def _check_timings(timings: dict, stages: tuple[str, ...]):
    for stage in stages + ("total",):
        assert stage in timings, (stage, timings)
    assert all(np.isfinite(v) and v >= 0 for v in timings.values()), timings
    assert timings["total"] == pytest.approx(sum(v for k, v in timings.items() if k != "total"))
    assert timings["total"] > 0


def test_every_result_carries_stage_timings(predictor, frames, K):
    flow_stages = ("preprocess", "depthnet", "posenet", "rigidflow", "postprocess")
    flow_stages += ("resflownet",) if predictor.has_flow else ()
    _check_timings(predictor.depth(frames[0]).timings_ms, ("preprocess", "depthnet", "postprocess"))
    for r in predictor.depth(frames[:2]):
        _check_timings(r.timings_ms, ("preprocess", "depthnet", "postprocess"))
    _check_timings(predictor.depth(SAMPLE / "image" / "000000.png").timings_ms, ("read", "depthnet"))
    _check_timings(predictor.pose(frames[:3]).timings_ms, ("preprocess", "posenet"))
    _check_timings(predictor.flow(frames[:3], K).timings_ms, flow_stages)
    seq = predictor.predict_sequence(frames[:3], K, batch_size=4)
    for fr in seq.frames:
        _check_timings(fr.timings_ms, flow_stages)
    _check_timings(seq.timings_ms, flow_stages)


# ----------------------------------------------------------------------------- 8. errors
def _raises(fn, *needles):
    with pytest.raises(GeoNetError) as err:
        fn()
    msg = str(err.value)
    for needle in needles:
        assert str(needle) in msg, (needle, msg)
    return err.value


def test_bad_images_are_refused_with_the_problem_named(predictor, frames, K, tmp_path):
    img = frames[0]
    _raises(lambda: predictor.depth(img.astype(np.float32)), "float32", "uint8")
    _raises(lambda: predictor.depth(img[..., 0]), "shape", str(img.shape[:2]))
    _raises(lambda: predictor.depth(np.dstack([img, img[..., :1]])), "shape", str((H, W, 4)))
    half = cv2.resize(frames[1], (W // 2, H // 2), interpolation=cv2.INTER_AREA)
    _raises(lambda: predictor.flow([img, half, frames[2]], K), "differ in size", f"{W}x{H}", f"{W // 2}x{H // 2}")
    _raises(lambda: predictor.flow([img], K), "got 1 frames")
    _raises(lambda: predictor.flow(frames[:4], K), "got 4 frames")
    _raises(lambda: predictor.predict_sequence([img], K), "at least 2 frames", "got 1")
    missing = tmp_path / "no_such_frame.png"
    _raises(lambda: predictor.depth(missing), str(missing))
    _raises(lambda: predictor.flow([img, missing], K), str(missing))


def test_bad_intrinsics_are_refused(predictor, frames, K):
    nan = K.copy()
    nan[0, 2] = np.nan
    _raises(lambda: predictor.flow(frames[:3], nan), "NaN")
    for fx in (0.0, -5.0):
        bad = K.copy()
        bad[0, 0] = fx
        _raises(lambda bad=bad: predictor.flow(frames[:3], bad), "focal", f"fx={fx:g}")
    _raises(lambda: predictor.flow(frames[:3], np.eye(2)), "3x3")


def _model_copy(tmp_path: Path) -> Path:
    """The bundled model dir copied into tmp_path (a graph symlinked to outside it would be refused)."""
    out = tmp_path / "model"
    shutil.copytree(MODEL_DIR, out)
    return out


def test_bad_precision_and_missing_model_dir(tmp_path):
    _raises(lambda: geonet_infer.load(precision="fp16"), "fp16")
    missing = tmp_path / "no_model_here"
    _raises(lambda: geonet_infer.load(missing), str(missing))


def test_corrupt_graph_file_is_named_with_sha256(tmp_path):
    model = _model_copy(tmp_path)
    data = bytearray((model / "depthnet.onnx").read_bytes())
    data[len(data) // 2] ^= 0x01
    (model / "depthnet.onnx").write_bytes(bytes(data))
    err = _raises(lambda: geonet_infer.load(model), "depthnet.onnx", "sha256")
    assert err.path == model / "depthnet.onnx"


@pytest.mark.parametrize(
    "edit, needles",
    [
        (lambda m: m.update(schema_version=m["schema_version"] + 1), ("manifest.json", "schema_version")),
        (lambda m: m["conventions"].update(channel_order="XYZ"), ("manifest.json", "unsupported convention", "XYZ")),
        (
            lambda m: m["conventions"]["intrinsics"].update(half_pixel_correction=True),
            ("manifest.json", "unsupported convention", "intrinsics"),
        ),
        (lambda m: m["conventions"]["disp_heads"].pop(m["arch"]), ("manifest.json", "disparity head")),
        (lambda m: m["graphs"]["fp32"]["depthnet"]["outputs"].reverse(), ("manifest.json", "depthnet", "outputs")),
    ],
    ids=["schema_version", "channel_order", "half_pixel", "disp_head", "graph_io"],
)
def test_manifest_that_this_runtime_cannot_drive_is_refused(tmp_path, edit, needles):
    model = _model_copy(tmp_path)
    manifest = json.loads((model / "manifest.json").read_text())
    edit(manifest)
    (model / "manifest.json").write_text(json.dumps(manifest))
    _raises(lambda: geonet_infer.load(model), *needles)


# ----------------------------------------------------------------------------- 9. undistortion
def test_camera_with_distortion_undistorts_first(predictor, frames, K):
    img = frames[4]
    dist = np.array([-0.3, 0.0, 0.0, 0.0, 0.0])
    with_dist = predictor.depth(img, Camera(K, dist, (W, H)))
    without = predictor.depth(img, K)
    assert with_dist.undistorted is True and without.undistorted is False
    assert np.abs(with_dist.depth - without.depth).max() > 1e-4
    by_hand = predictor.depth(cv2.undistort(img, K, dist))  # OpenCV undistortion, then no camera
    np.testing.assert_allclose(with_dist.depth, by_hand.depth, **TOL)


def test_camera_of_another_resolution_is_rescaled(predictor, frames):
    K720 = np.array([[1158.774754, 0.0, 669.642741], [0.0, 1154.076607, 388.079450], [0.0, 0.0, 1.0]])
    K360 = K720.copy()
    K360[0] *= 640 / 1280
    K360[1] *= 360 / 720
    small = [cv2.resize(f, (640, 360), interpolation=cv2.INTER_LINEAR) for f in frames[6:9]]

    rescaled = predictor.flow(small, Camera(K720, None, (1280, 720)))
    plain = predictor.flow(small, K360)
    assert rescaled.undistorted is False and rescaled.flow.shape == (360, 640, 2)
    np.testing.assert_allclose(rescaled.flow, plain.flow, **TOL)
    np.testing.assert_allclose(rescaled.rigid_flow, plain.rigid_flow, **TOL)

    dist = np.array([-0.25677908, 0.04338451, -0.00068745, 0.00012577, -0.11502545])
    undist = predictor.flow(small, Camera(K720, dist, (1280, 720)))
    by_hand = predictor.flow([cv2.undistort(f, K360, dist) for f in small], K360)
    assert undist.undistorted is True
    np.testing.assert_allclose(undist.flow, by_hand.flow, **TOL)
    np.testing.assert_allclose(undist.depth, by_hand.depth, **TOL)


def test_a_manifest_with_conventions_this_runtime_lacks_is_a_model_error(tmp_path):
    """errors.py gives manifests to ModelError: a convention the runtime does not implement is one."""
    from geonet_infer.errors import InputError, ModelError

    model = _model_copy(tmp_path)
    manifest = json.loads((model / "manifest.json").read_text())
    manifest["conventions"].update(channel_order="XYZ")
    (model / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(ModelError, match="unsupported convention") as caught:
        geonet_infer.load(model)
    assert not isinstance(caught.value, InputError)

"""Model directories holding only some graphs, and 5-frame PoseNets, through the runtime.

The converted official checkpoints (issue 28) give such directories: the depth release has no
ResFlowNet, the pose release no DepthNet and 5-frame snippets; `python -m export --graphs`
writes them from our own nets too, which is how the tiny random-init models here are made.
Golden poses come from the ONNX graphs driven by hand with onnxruntime on snippets assembled
here in the official order [t, t-2, t-1, t+1, t+2] (normalisation x / 255 * 2 - 1 by hand),
never from the runtime under test.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import onnxruntime as ort
import pytest

import geonet_infer
from geonet_infer import GeoNetError
from geonet_infer.cli import main

pytestmark = pytest.mark.slow  # its module fixture exports four partial models: ~40 s

pytest.importorskip("torch")  # the tiny models are exported here (train extra)
from export import ExportConfig, export_model  # noqa: E402

H, W = 32, 64  # graph size of the tiny exports; the frames have it too, so no resize is involved
N_FRAMES = 7
# Random-init poses move ~1e-5 from the identity; the runtime matches the hand run to ~1e-11.
POSE_TOL = dict(rtol=0, atol=1e-9)


# ----------------------------------------------------------------------------- fixtures
def _export(root: Path, name: str, graphs: tuple[str, ...], seq_length: int = 3) -> Path:
    out = root / name
    cfg = ExportConfig(
        out=out,
        arch="small",
        random_init=True,
        seed=7,
        height=H,
        width=W,
        seq_length=seq_length,
        graphs=graphs,
        quiet=True,
    )
    return export_model(cfg)


@pytest.fixture(scope="module")
def models(tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("partial_models")
    return {
        "depth": _export(root, "depth_only", ("depthnet",)),
        "rigid5": _export(root, "rigid5", ("depthnet", "posenet", "rigidflow"), seq_length=5),
        "pose5": _export(root, "pose5_only", ("posenet",), seq_length=5),
        "all3": _export(root, "all3", ("depthnet", "posenet", "rigidflow", "resflownet")),
    }


@pytest.fixture(scope="module")
def frames() -> list[np.ndarray]:
    """Consecutive frames of a textured scene panning right by 2 px a frame, at the graph size."""
    rng = np.random.default_rng(3)
    wide = cv2.resize(rng.integers(0, 256, (8, 24, 3), dtype=np.uint8), (W + 2 * N_FRAMES, H), cv2.INTER_CUBIC)
    return [np.ascontiguousarray(wide[:, 2 * t : 2 * t + W]) for t in range(N_FRAMES)]


@pytest.fixture(scope="module")
def K() -> np.ndarray:
    return np.array([[W, 0, W / 2], [0, W, H / 2], [0, 0, 1]], dtype=np.float64)


def frame_folder(root: Path, frames: list[np.ndarray]) -> Path:
    folder = root / "frames"
    folder.mkdir()
    for t, rgb in enumerate(frames):
        assert cv2.imwrite(str(folder / f"{t:06d}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    return folder


def calib_file(root: Path, K: np.ndarray) -> Path:
    path = root / "calib.txt"
    path.write_text("K: " + " ".join(f"{v:g}" for v in K.ravel()) + "\n")
    return path


def run_cli(capsys, *argv) -> tuple[int, str, str]:
    rc = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return rc, out, err


# ----------------------------------------------------------------------------- independent helpers
def normalise(rgb: np.ndarray) -> np.ndarray:
    """uint8 RGB (H, W, 3) -> float32 (3, H, W) with the paper's x / 255 * 2 - 1."""
    return (rgb.astype(np.float32) / 255.0 * 2.0 - 1.0).transpose(2, 0, 1)


def posenet_by_hand(model: Path, snippet_frames: list[np.ndarray]) -> np.ndarray:
    """(L-1, 4, 4) target -> source matrices from posenet.onnx on frames given in feed order."""
    sess = ort.InferenceSession(str(model / "posenet.onnx"), providers=["CPUExecutionProvider"])
    x = np.concatenate([normalise(f) for f in snippet_frames])[None]
    names = [o.name for o in sess.get_outputs()]
    return dict(zip(names, sess.run(None, {"snippet": x})))["pose_matrix"][0].astype(np.float64)


def official_snippet(frames: list[np.ndarray], t: int, k: int = 2) -> list[np.ndarray]:
    """[t, t-2, t-1, t+1, t+2] (k = 2), ends replicated: the official order, written out here."""
    clip = [frames[min(max(i, 0), len(frames) - 1)] for i in range(t - k, t + k + 1)]
    return [clip[k]] + clip[:k] + clip[k + 1 :]


def rigid_inverse_by_hand(T: np.ndarray) -> np.ndarray:
    """[R t; 0 1]^-1 = [R^T -R^T t; 0 1] (a rigid transform's inverse; np.linalg.inv differs by the
    float32 rotation's departure from orthonormality, ~1e-9 here)."""
    out = np.eye(4)
    out[:3, :3] = T[:3, :3].T
    out[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return out


def trajectory_by_hand(steps: list[np.ndarray]) -> np.ndarray:
    """camera_to_world[t + 1] = camera_to_world[t] @ inv(T_t->t+1), first = identity."""
    out = [np.eye(4)]
    for T in steps:
        out.append(out[-1] @ rigid_inverse_by_hand(T))
    return np.stack(out)


# ----------------------------------------------------------------------------- 1. loading, API refusals
def test_depth_only_model_loads_and_predicts_depth(models, frames):
    predictor = geonet_infer.load(models["depth"])
    assert predictor.tasks == ("depth",)
    depth = predictor.depth(frames[0])
    assert depth.depth.shape == (H, W) and np.isfinite(depth.depth).all() and (depth.depth > 0).all()
    seq = list(predictor.iter_sequence(frames[:4], None, tasks=("depth",)))
    assert [r.index for r in seq] == [0, 1, 2, 3]
    np.testing.assert_allclose(seq[0].depth, depth.depth, rtol=1e-5)  # batch of 4 vs 1: float rounding only
    assert all(r.pose_to_next is None and r.flow is None for r in seq)


def _refused(fn, *needles) -> str:
    with pytest.raises(GeoNetError) as err:
        fn()
    msg = str(err.value)
    for needle in needles:
        assert str(needle) in msg, (needle, msg)
    assert "\n" not in msg
    return msg


def test_api_refuses_a_task_whose_graph_is_missing_naming_graph_and_directory(models, frames, K):
    depth_only = geonet_infer.load(models["depth"])
    _refused(lambda: depth_only.pose(frames[:3]), "posenet", models["depth"])
    _refused(lambda: depth_only.flow(frames[:3], K), "posenet", "rigidflow", models["depth"])
    _refused(lambda: depth_only.iter_sequence(frames, K), "posenet", models["depth"])  # default: every task
    _refused(lambda: depth_only.iter_sequence(frames, None, tasks=("pose",)), "posenet", models["depth"])
    pose_only = geonet_infer.load(models["pose5"])
    assert pose_only.tasks == ("pose",)
    _refused(lambda: pose_only.depth(frames[0]), "depthnet", models["pose5"])
    _refused(lambda: pose_only.iter_sequence(frames, None, tasks=("depth", "pose")), "depthnet", models["pose5"])
    rigid = geonet_infer.load(models["rigid5"])
    assert rigid.tasks == ("depth", "pose") and rigid.missing_graphs("flow") == ("resflownet",)
    _refused(lambda: rigid.require_tasks(("flow",)), "flow", "resflownet", models["rigid5"])
    _refused(lambda: depth_only.iter_sequence(frames, None, tasks=("depth", "optical")), "optical")


# ----------------------------------------------------------------------------- 1. predict
def test_predict_tasks_depth_on_a_depth_only_model_runs_end_to_end(models, frames, tmp_path, capsys):
    folder, out = frame_folder(tmp_path, frames), tmp_path / "out"
    rc, _, err = run_cli(capsys, "predict", folder, "--out", out, "--model", models["depth"], "--tasks", "depth")
    assert rc == 0, err
    assert sorted(p.stem for p in (out / "depth").glob("*.npy")) == [f"{t:06d}" for t in range(N_FRAMES)]
    reference = geonet_infer.load(models["depth"]).depth(frames[3]).depth
    np.testing.assert_allclose(np.load(out / "depth" / "000003.npy"), reference, rtol=1e-6)
    assert json.loads((out / "summary.json").read_text())["tasks"] == ["depth"]


@pytest.mark.parametrize(
    "model, tasks, missing",
    [("rigid5", "flow", "resflownet"), ("depth", "flow", "posenet"), ("depth", "pose", "posenet")],
)
def test_predict_refuses_a_task_the_model_cannot_do_before_any_frame(
    models, frames, K, tmp_path, capsys, model, tasks, missing
):
    folder, out = frame_folder(tmp_path, frames), tmp_path / "out"
    argv = [
        "predict",
        folder,
        "--out",
        out,
        "--model",
        models[model],
        "--tasks",
        tasks,
        "--calib",
        calib_file(tmp_path, K),
    ]
    rc, stdout, err = run_cli(capsys, *argv)
    assert rc == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert missing in lines[0] and str(models[model]) in lines[0] and f"task {tasks}" in lines[0]
    assert not out.exists() and stdout == ""


def test_predict_without_tasks_does_what_the_model_can_and_says_what_it_skipped(models, frames, tmp_path, capsys):
    folder, out = frame_folder(tmp_path, frames), tmp_path / "out"
    rc, _, err = run_cli(capsys, "predict", folder, "--out", out, "--model", models["depth"], "--no-progress")
    assert rc == 0, err
    notes = [line for line in err.splitlines() if "skipp" in line]
    assert len(notes) == 1 and "pose" in notes[0] and "flow" in notes[0] and "posenet" in notes[0], err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["tasks"] == ["depth"] and summary["frames"] == N_FRAMES
    assert summary["skipped_tasks"]["pose"] == ["posenet"]
    assert set(summary["skipped_tasks"]["flow"]) == {"posenet", "rigidflow", "resflownet"}
    assert len(list((out / "depth").glob("*.npy"))) == N_FRAMES and not (out / "poses_kitti.txt").exists()


def test_predict_explicit_tasks_record_no_skipped_task(models, frames, tmp_path, capsys):
    folder, out = frame_folder(tmp_path, frames), tmp_path / "out"
    rc, _, err = run_cli(capsys, "predict", folder, "--out", out, "--model", models["rigid5"], "--tasks", "pose")
    assert rc == 0, err
    assert "skipp" not in err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["tasks"] == ["pose"] and summary["skipped_tasks"] == {}


# ----------------------------------------------------------------------------- 2. info
def test_info_lists_the_tasks_a_model_can_do_and_the_missing_graphs(models, capsys):
    rc, out, err = run_cli(capsys, "info", "--model", models["rigid5"])
    assert rc == 0, err
    lines = {line.split(":")[0].strip(): line for line in out.splitlines() if line.startswith("  task ")}
    assert "depthnet" in lines["task depth"] and "missing" not in lines["task depth"]
    assert "posenet" in lines["task pose"] and "missing" not in lines["task pose"]
    assert "missing resflownet" in lines["task flow"]
    rc, out, err = run_cli(capsys, "info", "--model", models["depth"], "--json")
    assert rc == 0, err
    tasks = json.loads(out)["model"]["tasks"]
    assert tasks["depth"] == {"available": True, "graphs": ["depthnet"], "missing": []}
    assert tasks["pose"] == {"available": False, "graphs": ["posenet"], "missing": ["posenet"]}
    assert tasks["flow"]["available"] is False
    assert tasks["flow"]["missing"] == ["posenet", "rigidflow", "resflownet"]
    rc, out, err = run_cli(capsys, "info", "--model", models["all3"], "--json")
    assert all(t["available"] for t in json.loads(out)["model"]["tasks"].values())


# ----------------------------------------------------------------------------- 3. 5-frame PoseNets
def test_seq5_pose_matches_posenet_on_the_official_snippet_order(models, frames):
    predictor = geonet_infer.load(models["rigid5"])
    assert predictor.seq_length == 5
    got = predictor.pose(frames[1:6]).matrices  # target = frames[3]
    want = posenet_by_hand(models["rigid5"], [frames[3], frames[1], frames[2], frames[4], frames[5]])
    np.testing.assert_allclose(got, want, **POSE_TOL)
    # the check can tell orders apart: plain temporal order gives other poses
    temporal = posenet_by_hand(models["rigid5"], frames[1:6])
    assert np.abs(temporal - want).max() > 1e3 * POSE_TOL["atol"]
    # a pose-only model (the pose release alone) gives the same poses
    pose_only = geonet_infer.load(models["pose5"]).pose(frames[1:6]).matrices
    np.testing.assert_allclose(pose_only, posenet_by_hand(models["pose5"], official_snippet(frames, 3)), **POSE_TOL)


def _sequence_steps(model: Path, frames: list[np.ndarray]) -> list[np.ndarray]:
    """T_t->t+1 for t = 0 .. N-2: source t+1 is the third source of the official 5-frame snippet."""
    return [posenet_by_hand(model, official_snippet(frames, t))[2] for t in range(len(frames) - 1)]


@pytest.mark.parametrize("model", ["rigid5", "pose5"])
def test_seq5_iter_sequence_poses_and_trajectory(models, frames, model):
    predictor = geonet_infer.load(models[model])
    steps = _sequence_steps(models[model], frames)
    results = list(predictor.iter_sequence(frames, None, tasks=("pose",), batch_size=3))
    assert [r.index for r in results] == list(range(N_FRAMES))
    for r, T in zip(results, steps):
        np.testing.assert_allclose(r.pose_to_next, T, **POSE_TOL)
    assert results[-1].pose_to_next is None
    np.testing.assert_allclose(np.stack([r.camera_to_world for r in results]), trajectory_by_hand(steps), **POSE_TOL)


def test_seq5_predict_writes_a_pose_for_every_frame_chained_correctly(models, frames, K, tmp_path, capsys):
    folder, out = frame_folder(tmp_path, frames), tmp_path / "out"
    argv = ["predict", folder, "--out", out, "--model", models["rigid5"], "--calib", calib_file(tmp_path, K)]
    rc, _, err = run_cli(capsys, *argv, "--batch-size", "2", "--no-progress")
    assert rc == 0, err
    rows = np.loadtxt(out / "poses_kitti.txt").reshape(-1, 3, 4)
    assert rows.shape[0] == N_FRAMES
    want = trajectory_by_hand(_sequence_steps(models["rigid5"], frames))
    np.testing.assert_allclose(rows, want[:, :3], rtol=0, atol=1e-8)  # written with 10 significant digits
    summary = json.loads((out / "summary.json").read_text())
    assert summary["tasks"] == ["depth", "pose"] and summary["skipped_tasks"] == {"flow": ["resflownet"]}


def _pose_eval_folder(root: Path, frames: list[np.ndarray], K: np.ndarray) -> Path:
    seq = root / "seq_0000"
    (seq / "image").mkdir(parents=True)
    for t, rgb in enumerate(frames):
        assert cv2.imwrite(str(seq / "image" / f"{t:06d}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    (seq / "poses.txt").write_text("".join(f"1 0 0 {0.1 * t} 0 1 0 0 0 0 1 {t}\n" for t in range(len(frames))))
    (seq / "calib.txt").write_text("K: " + " ".join(f"{v:g}" for v in K.ravel()) + "\n")
    return root


def test_eval_pose_feeds_a_seq5_model_the_official_snippet_and_a_seq3_model_still_works(models, frames, K, tmp_path):
    from geonet_infer.eval.datasets import pose_dataset
    from geonet_infer.eval.evaluation import evaluate_pose, model_pose_fn

    data = pose_dataset(_pose_eval_folder(tmp_path, frames[:6], K))
    assert [item.name for item in data.items] == ["seq_0000/000000", "seq_0000/000001"]
    for model in ("rigid5", "all3"):
        seen = []
        predictor = geonet_infer.load(models[model])
        result = evaluate_pose(
            model_pose_fn(predictor, allow_random_init=True),
            data,
            observe=lambda item, gt, pred, row, seen=seen: seen.append(pred),
        )
        assert len(seen) == 2 and all(np.isfinite(p).all() for p in seen)
        assert np.isfinite(result["metrics"]["ate_snippet"]), result
        if model == "rigid5":  # one call on [2, 0, 1, 3, 4]; frame p's pose G_p = T_0 inv(T_p), T_2 = I
            for start, pred in zip((0, 1), seen):
                s = frames[start : start + 5]
                T = posenet_by_hand(models[model], [s[2], s[0], s[1], s[3], s[4]])
                T = np.insert(T, 2, np.eye(4), axis=0)
                want = np.stack([T[0] @ rigid_inverse_by_hand(T[p]) for p in range(5)])
                np.testing.assert_allclose(pred, want, **POSE_TOL)


def test_batch_does_what_the_model_can_and_refuses_a_task_it_cannot(models, frames, tmp_path, capsys):
    """batch resolves tasks as predict does: without --tasks a depth-only model gives depth (the skipped
    tasks named on stderr); --tasks flow on it is refused before any work, naming the missing graph."""
    folder = frame_folder(tmp_path, frames)
    rc, _, err = run_cli(
        capsys, "batch", folder, "--out", tmp_path / "refused", "--model", models["depth"], "--tasks", "flow"
    )
    assert rc == 2 and "posenet" in err and str(models["depth"]) in err and err.count("\n") == 1, err
    assert not (tmp_path / "refused").exists()
    out = tmp_path / "out"
    rc, _, err = run_cli(
        capsys, "batch", folder, "--out", out, "--model", models["depth"], "--workers", "1", "--no-progress"
    )
    assert rc == 0, err
    assert "skipping pose" in err and "flow" in err
    depth_files = sorted(p.stem for p in (out / folder.name / "depth").glob("*.npy"))
    assert depth_files == [f"{t:06d}" for t in range(N_FRAMES)]
    assert not (out / folder.name / "flow").exists()

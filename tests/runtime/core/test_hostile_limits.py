"""Issue 41, cases 7-14 and 16-22: every size or count a user sets has its limit at every entrance,
crashes become one-line errors (exit 2), and no silent wrong output.

Limits are checked by asking for the over-limit value and expecting the refusal; nothing here
allocates what the limit guards against. Where a door would allocate before refusing (bench), the
allocating call is replaced by one that fails the test, so a missing limit fails fast.
"""

from __future__ import annotations

import dataclasses
import json
import os
import resource
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

import geonet_infer
from geonet_infer import GeoNetError
from geonet_infer.cli import main
from geonet_infer.core.predictor import Predictor
from tests.conftest import GEONET_CLI
from tests.runtime.core.test_hostile_model import _synth_pose_sequence, edit_manifest, model_copy
from tests.runtime.output.test_hostile_predict import (
    REPO,
    SAMPLE_CALIB,
    SAMPLE_FRAMES,
    error_lines,
    run_cli,
    sample_folder,
    summary_of,
    write_video,
)

DEPTH = ("--tasks", "depth", "--no-progress", "--quiet")


def one_line(stderr: str) -> str:
    lines = error_lines(stderr)
    assert len(lines) == 1, stderr
    return lines[0]


def refused(fn, *needles) -> str:
    with pytest.raises(GeoNetError) as err:
        fn()
    msg = str(err.value)
    assert "\n" not in msg
    for needle in needles:
        assert str(needle) in msg, msg
    return msg


@pytest.fixture(scope="module")
def predictor():
    return geonet_infer.load(threads=1)


# ----------------------------------------------------------------------------- 7-11, 22: limits at every door
def _no_bench_frames(*args, **kwargs):
    raise AssertionError("bench went on to make its frames: the limit was not checked first")


CLI_LIMITS = {  # id -> (argv after the command's input/--out, text the one error line must hold)
    "predict --colour-scale first:1000000": (["predict", "{in}", "--colour-scale", "first:1000000"], "1000000"),
    "predict --colour-scale first:²": (["predict", "{in}", "--colour-scale", "first:²"], "first:N"),
    "predict --batch-size": (["predict", "{in}", "--batch-size", "100000"], "100000"),
    "predict --threads": (["predict", "{in}", "--threads", "5000"], "5000"),
    "predict --world-points": (["predict", "{in}", "--world-points", "1000000000"], "world points"),
    "predict --fps": (["predict", "{in}", "--fps", "1e9", "--video-out", "{out}/v.mp4"], "--fps"),
    "batch --batch-size": (["batch", "{in}", "--batch-size", "100000"], "100000"),
    "bench --batch": (["bench", "--batch", "100000"], "100000"),
    "bench --threads": (["bench", "--threads", "5000"], "5000"),
    "bench --seq-frames": (["bench", "--seq-frames", "100000"], "100000"),
    "bench --input-size": (["bench", "--input-size", "100000x100000"], "pixels"),
}


@pytest.mark.parametrize("case", list(CLI_LIMITS))
def test_every_cli_door_refuses_a_size_over_its_limit(tmp_path, capfd, monkeypatch, case):
    monkeypatch.setattr("geonet_infer.cli.bench.bench_frames", _no_bench_frames)
    argv, needle = CLI_LIMITS[case]
    folder = sample_folder(tmp_path, 3)
    out = tmp_path / "out"
    argv = [a.format(**{"in": folder, "out": out}) for a in argv]
    if argv[0] != "bench":
        argv += ["--out", str(out), *DEPTH]
    else:
        argv += ["--iters", "1", "--warmup", "0", "--tasks", "depth", "--quiet"]
    rc, _, stderr = run_cli(capfd, *argv)
    assert rc == 2, stderr
    assert needle in one_line(stderr)
    assert not out.exists()


def _no_graphs(*args, **kwargs):
    raise AssertionError("the graphs were loaded: the limit was not checked first")


def test_api_doors_refuse_sizes_over_their_limits(tmp_path, monkeypatch, predictor):
    from geonet_infer.batch import run_batch
    from geonet_infer.io.frames import open_frames
    from geonet_infer.output.options import OutputOptions
    from geonet_infer.output.predict import predict_to_dir

    frame = np.zeros((32, 64, 3), np.uint8)
    with monkeypatch.context() as patch:  # 5000 threads took 100 s to load
        patch.setattr("geonet_infer.core.predictor.GraphSet", _no_graphs)
        refused(lambda: geonet_infer.load(threads=5000), "5000", "CPUs")
    refused(lambda: predictor.depth([frame] * 65), "65", "64")  # before any of them runs
    refused(lambda: predictor.iter_sequence([frame] * 3, batch_size=10**6), "1000000")  # before the first frame
    refused(lambda: OutputOptions(colour_scale="first:1000000"), "first:1000000")
    refused(lambda: OutputOptions(world_points=10**9), "world points")
    refused(lambda: OutputOptions(video_fps=1e9), "1e+09")
    folder = sample_folder(tmp_path, 3)
    out = tmp_path / "out"
    refused(lambda: predict_to_dir(predictor, open_frames(folder), out, tasks=("depth",), batch_size=10**5), "100000")
    refused(lambda: run_batch([folder], tmp_path / "batch", tasks=("depth",), batch_size=10**5), "100000")
    assert not out.exists() and not (tmp_path / "batch").exists()


def test_source_frames_over_the_pixel_cap_are_refused(tmp_path, capfd, monkeypatch):
    from geonet_infer.io import images

    monkeypatch.setattr(images, "MAX_IMAGE_PIXELS", 1000)  # the 64x48 frames are 3072 pixels
    video = write_video(tmp_path / "clip.avi", frames=3)
    out = tmp_path / "out"
    rc, _, stderr = run_cli(capfd, "predict", "--source", video, "--out", out, *DEPTH)
    assert rc == 2, stderr
    assert "64x48" in one_line(stderr) and "1,000 pixels" in one_line(stderr)
    assert not out.exists()


def test_first_n_of_huge_frames_fixes_the_scale_within_the_held_pixel_budget(tmp_path, capfd, monkeypatch):
    # The sample frames are 416x128 = 53,248 pixels: a budget of 2.5 frames fixes first:8 after 3.
    monkeypatch.setattr("geonet_infer.output.predict.MAX_HELD_PIXELS", 133_000)
    folder = sample_folder(tmp_path, 10)
    out = tmp_path / "out"
    rc, _, stderr = run_cli(capfd, "predict", folder, "--out", out, "--colour-scale", "first:8", *DEPTH)
    assert rc == 0, stderr
    scale = summary_of(out)["colour_scale"]
    assert scale["mode"] == "first:8" and scale["frames"] == 3


# ----------------------------------------------------------------------------- 12-14: one line, exit 2
def test_a_seq_length_the_posenet_was_not_exported_for_is_refused_at_load(tmp_path, capfd):
    model = model_copy(tmp_path)
    edit_manifest(model, lambda m: m.update(seq_length=5))
    refused(lambda: geonet_infer.load(model), "posenet", "seq_length 5", "15")
    assert main(["info", "--model", str(model)]) == 2
    assert "seq_length 5" in one_line(capfd.readouterr().err)
    folder = sample_folder(tmp_path, 5)
    rc, _, stderr = run_cli(capfd, "predict", folder, "--out", tmp_path / "out", "--model", model, "--no-progress")
    assert rc == 2 and "seq_length 5" in one_line(stderr)


def _depth_only(model: Path) -> None:
    def keep_depth(manifest):
        manifest["graphs"] = {p: {"depthnet": g["depthnet"]} for p, g in manifest["graphs"].items()}

    edit_manifest(model, keep_depth)


def test_bench_on_a_depth_only_model_times_depth(tmp_path, capfd):
    model = model_copy(tmp_path)
    _depth_only(model)
    out = tmp_path / "bench.json"
    argv = ["--iters", "1", "--warmup", "0", "--block", "1", "--rewarm-ms", "0", "--input-size", "graph"]
    rc, _, stderr = run_cli(capfd, "bench", "--model", model, "--precision", "fp32", *argv, "--json", out, "--quiet")
    assert rc == 0, stderr
    rows = json.loads(out.read_text())["results"]
    assert {(r["task"], r["mode"]) for r in rows} == {("depth", "graph"), ("depth", "e2e")}


def _nested_manifest(tmp_path: Path) -> list[str]:
    model = model_copy(tmp_path)
    (model / "manifest.json").write_text("[" * 200_000 + "]" * 200_000)
    return ["info", "--model", str(model)]


def _huge_lock(tmp_path: Path) -> list[str]:
    folder = sample_folder(tmp_path, 3)
    out = tmp_path / "out"
    assert main(["predict", str(folder), "--out", str(out), *DEPTH]) == 0
    (out / ".geonet-predict.lock").write_text("99999999999999999999\n")  # no process has this pid
    return ["predict", str(folder), "--out", str(out), *DEPTH]


CRASHES = {  # id -> (argv maker, expected exit code, text of the one line (None: no error line))
    "lock 99999999999999999999": (_huge_lock, 0, None),
    "--source 99999999999999999999": (
        lambda t: ["predict", "--source", "99999999999999999999", "--out", str(t / "o")],
        2,
        "camera index",
    ),
    "--source ²": (lambda t: ["predict", "--source", "²", "--out", str(t / "o")], 2, "cannot open"),
    "manifest nested 200000 deep": (_nested_manifest, 2, "cannot parse the manifest"),
}


@pytest.mark.parametrize("case", list(CRASHES))
def test_hostile_values_are_one_line_errors_not_tracebacks(tmp_path, capfd, case):
    make, code, needle = CRASHES[case]
    argv = make(tmp_path)
    capfd.readouterr()
    rc, _, stderr = run_cli(capfd, *argv)
    assert rc == code, stderr
    if needle is not None:
        assert needle in one_line(stderr)


# ----------------------------------------------------------------------------- 16: degenerate output
def test_a_camera_height_too_small_to_mean_anything_is_refused(tmp_path, capfd, predictor):
    folder = sample_folder(tmp_path, 3)
    out = tmp_path / "out"
    argv = ["predict", folder, "--out", out, "--calib", SAMPLE_CALIB, "--camera-height", "1e-300", *DEPTH]
    rc, _, stderr = run_cli(capfd, *argv)
    assert rc == 2 and "1e-300" in one_line(stderr)
    assert not out.exists()
    frame = cv2.cvtColor(cv2.imread(str(SAMPLE_FRAMES[0])), cv2.COLOR_BGR2RGB)
    K = np.array([[200.0, 0, 208], [0, 200, 64], [0, 0, 1]])
    refused(lambda: predictor.depth(frame, K, camera_height=1e-300), "1e-300")


def test_a_degenerate_depth_fails_its_frame_like_nan(tmp_path, capfd, monkeypatch):
    real = Predictor.iter_sequence

    def flattened(self, *args, **kwargs):
        for result in real(self, *args, **kwargs):
            if result.index == 1:  # finite, but every pixel 0: what a camera height of 1e-300 gave
                result = dataclasses.replace(result, depth=np.zeros_like(result.depth))
            yield result

    monkeypatch.setattr(Predictor, "iter_sequence", flattened)
    folder = sample_folder(tmp_path, 4)
    out = tmp_path / "out"
    rc, _, stderr = run_cli(capfd, "predict", folder, "--out", out, *DEPTH)
    assert rc == 1, stderr
    [failure] = summary_of(out)["failures"]
    assert failure["frame"] == "000001" and "degenerate depth" in failure["reason"]
    assert not (out / "depth" / "000001.npy").exists() and (out / "depth" / "000002.npy").exists()


# ----------------------------------------------------------------------------- 18: stdin frames of another size
def test_stdin_frames_of_another_size_than_declared_fail_with_a_warning(tmp_path):
    rng = np.random.default_rng(0)
    data = rng.integers(0, 256, (5, 48, 64, 3), dtype=np.uint8).tobytes()  # 5 frames of 64x48
    out = tmp_path / "out"
    proc = subprocess.run(
        [*GEONET_CLI, "predict", "-", "--stdin-frames", "63x48", "--out", str(out)] + list(DEPTH),
        input=data,
        cwd=REPO,
        capture_output=True,
        timeout=120,
    )
    stderr = proc.stderr.decode()
    assert proc.returncode == 1, stderr
    warnings = [line for line in error_lines(stderr) if "--stdin-frames" in line]
    assert len(warnings) == 1 and "63x48" in warnings[0], stderr
    assert summary_of(out)["failed"] == 1


# ----------------------------------------------------------------------------- 20: eval pose, absurd GT
def test_eval_pose_with_a_finite_but_absurd_ground_truth_is_an_input_error(tmp_path, capfd):
    seq = _synth_pose_sequence(tmp_path)
    lines = (seq / "poses.txt").read_text().splitlines()
    lines[2] = "1 0 0 1e308 0 1 0 0 0 0 1 2.0"
    (seq / "poses.txt").write_text("\n".join(lines) + "\n")
    rc, out, stderr = run_cli(capfd, "eval", "pose", "--data", tmp_path, "--method", "identity")
    assert rc == 2
    assert "poses.txt" in one_line(stderr) and "line 3" in one_line(stderr)
    assert "nan" not in out


# ----------------------------------------------------------------------------- 21: frame order, bools
def test_numbered_frames_run_in_numeric_order(tmp_path, capfd):
    folder = tmp_path / "frames"
    folder.mkdir()
    for i, n in enumerate(range(3, 16)):
        shutil.copyfile(SAMPLE_FRAMES[i % len(SAMPLE_FRAMES)], folder / f"f{n}.png")
    odd = cv2.imread(str(folder / "f9.png"))
    cv2.imwrite(str(folder / "f9.png"), odd[:, :400])  # another size: fails a sequence task, records the frame after
    out = tmp_path / "out"
    # pose (a sequence task): depth alone now takes photos of any size (issue 43)
    rc, _, stderr = run_cli(capfd, "predict", folder, "--out", out, "--tasks", "pose", "--no-progress")
    assert rc == 1, stderr
    # in numeric order f9 comes between f8 and f10; in name order it would be the last frame
    assert summary_of(out)["gaps"] == [{"frame": "f10", "skipped_before": ["f9"]}]


def test_a_bool_where_the_manifest_needs_a_number_is_refused(tmp_path):
    model = model_copy(tmp_path)
    edit_manifest(model, lambda m: m["conventions"]["image_norm"].update(scale=True))
    refused(lambda: geonet_infer.load(model), "conventions.image_norm.scale", "True", "not a number")


# ----------------------------------------------------------------------------- 22: misleading messages
def _small_files_only():  # in the child: no file past 64 KiB (EFBIG, as on a full disk); numpy then
    resource.setrlimit(resource.RLIMIT_FSIZE, (65536, 65536))  # says "N requested and M written"


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="RLIMIT_FSIZE")
def test_a_short_write_names_the_file(tmp_path):
    folder = sample_folder(tmp_path, 2)
    out = tmp_path / "out"
    code = "import signal, sys; signal.signal(signal.SIGXFSZ, signal.SIG_IGN); from geonet_infer.cli import main; "
    code += "sys.exit(main(sys.argv[1:]))"
    proc = subprocess.run(
        [sys.executable, "-c", code, "predict", str(folder), "--out", str(out), *DEPTH],
        cwd=tmp_path,  # not the repository root: `-c` puts the working directory first on sys.path
        capture_output=True,
        text=True,
        timeout=120,
        preexec_fn=_small_files_only,
    )
    assert proc.returncode == 3, proc.stderr
    line = one_line(proc.stderr)
    assert str(out / "depth" / "000000.npy") in line and "requested" in line


def test_an_rgba_array_gets_advice_about_its_alpha_channel(predictor):
    rgba = np.zeros((64, 64, 4), np.uint8)
    assert "alpha" in refused(lambda: predictor.depth(rgba), "(64, 64, 4)")


def test_a_stream_url_is_recorded_as_given(tmp_path, capfd):
    video = write_video(tmp_path / "clip.mp4", frames=3)
    url = f"file://{video}"
    out = tmp_path / "out"
    rc, _, stderr = run_cli(capfd, "predict", "--source", url, "--out", out, *DEPTH)
    assert rc == 0, stderr
    assert summary_of(out)["input"]["path"] == url
    assert json.loads((out / ".geonet-predict").read_text())["input"] == url


def test_points_of_an_image_of_another_size_is_an_input_error(predictor):
    frame = cv2.cvtColor(cv2.imread(str(SAMPLE_FRAMES[0])), cv2.COLOR_BGR2RGB)
    result = predictor.depth(frame, np.array([[200.0, 0, 208], [0, 200, 64], [0, 0, 1]]))
    refused(lambda: result.points(frame[:64]), "(64, 416, 3)", "(128, 416)")


class _LateRunner:
    """Runs every sequence in this process, but stops listening (Ctrl-C) before the last result
    comes back: that sequence is complete on disk, as after an interrupted Ray job."""

    name, address, limits, workers, threads = "local", None, [], 1, 1

    @classmethod
    def start(cls, config, options, n_units, workers, threads, **kwargs):
        runner = cls()
        runner.config, runner.options = config, options
        return runner

    def results(self, units):
        from geonet_infer.batch.units import run_sequence

        predictor = geonet_infer.load(threads=1)
        for i, unit in enumerate(units):
            result = run_sequence(unit, self.config, predictor, options=self.options)
            assert result["status"] == "done", result
            if i == len(units) - 1:
                raise KeyboardInterrupt
            yield result

    def live_frames(self) -> int:
        return 0

    def close(self) -> None:
        pass


def test_an_interrupted_batch_summary_counts_sequences_done_on_disk_with_their_frames(tmp_path, monkeypatch):
    from geonet_infer.batch import run as batch_run

    monkeypatch.setitem(batch_run.RUNNERS, "local", _LateRunner)
    inputs = [sample_folder(tmp_path, n, name) for n, name in ((3, "a"), (4, "b"))]
    out = tmp_path / "out"
    with pytest.raises(KeyboardInterrupt):
        batch_run.run_batch(inputs, out, tasks=("depth",), vis=False, progress=False, log=lambda msg: None)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["interrupted"] and summary["sequences"]["done"] == 2
    assert summary["frames"] == 7
    assert [(r["sequence"], r["frames"]) for r in summary["per_sequence"]] == [("a", 3), ("b", 4)]


# ----------------------------------------------------------------------------- 17, 19, 22: export (needs torch)
@pytest.mark.train_extra
def test_calibration_frames_the_runtime_refuses_are_refused(tmp_path):
    pytest.importorskip("torch")
    from geonet_infer.convert.quantize import load_frames

    folder = tmp_path / "calib"
    folder.mkdir()
    for i in range(3):
        cv2.imwrite(str(folder / f"{i:06d}.png"), np.zeros((1, 1, 3), np.uint8))
    refused(lambda: load_frames(folder, 128, 416, 10), "000000.png", "1x1")


@pytest.mark.train_extra
def test_export_calib_frames_negative_is_a_count_error_not_a_folder_mixup(tmp_path, capsys):
    pytest.importorskip("torch")
    from export.__main__ import main as export_main

    with pytest.raises(SystemExit) as exc:
        export_main(["--random-init", "--arch", "small", "--out", str(tmp_path / "m"), "--calib-frames", "-5"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "positive number of frames" in err and "different folders" not in err


@pytest.mark.train_extra
def test_export_from_tf_path_with_glob_characters_reads(tmp_path):
    """TensorFlow's reader took the prefix as a glob pattern; ours opens such a path as it is."""
    pytest.importorskip("torch")
    from geonet_infer.convert.official import TFCheckpoint
    from geonet_infer.convert.tf_checkpoint import write_checkpoint

    prefix = write_checkpoint(tmp_path / "ckpt [1]*?" / "model-1", {"pose_net/Conv/weights": np.ones((1, 1, 3, 2))})
    ckpt = TFCheckpoint.open(prefix)
    assert ckpt.shapes == {"pose_net/Conv/weights": [1, 1, 3, 2]} and ckpt.dtypes["pose_net/Conv/weights"] == "float64"
    assert ckpt.tensor("pose_net/Conv/weights").sum() == 6


def _constant_graph(path: Path, value: float) -> Path:
    import onnx
    from onnx import TensorProto, helper

    x = helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 4])
    y = helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, 4])
    w = helper.make_tensor("w", TensorProto.FLOAT, [1], [value])
    graph = helper.make_graph([helper.make_node("Mul", ["x", "w"], ["y"])], "g", [x], [y], [w])
    onnx.save(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)]), path)
    return path


@pytest.mark.parametrize("weight, needle", [(float("nan"), "NaN/inf"), (0.0, "everywhere")], ids=["nan", "zero"])
def test_export_refuses_a_graph_whose_output_is_nan_or_degenerate(tmp_path, weight, needle):
    pytest.importorskip("torch")
    from export.build import _check_outputs
    from export.to_onnx import ExportCheckError

    example = (np.linspace(-1, 1, 4, dtype=np.float32)[None],)
    _check_outputs(_constant_graph(tmp_path / "ok.onnx", 2.0), example)  # a working graph passes
    with pytest.raises(ExportCheckError, match=needle):
        _check_outputs(_constant_graph(tmp_path / "bad.onnx", weight), example)
    if weight == 0.0:  # a hard motion gate's zero poses on frames it calls still (issue 53) are an answer
        _check_outputs(_constant_graph(tmp_path / "still.onnx", weight), example, may_be_constant=("y",))
        with pytest.raises(ExportCheckError, match="NaN"):  # never NaN
            _check_outputs(_constant_graph(tmp_path / "nan.onnx", float("nan")), example, may_be_constant=("y",))


def test_export_from_tf_refuses_a_checkpoint_with_nan_weights(tmp_path, capsys):
    pytest.importorskip("torch")
    from export.__main__ import main as export_main
    from geonet_infer.convert.official import official_variables
    from geonet_infer.convert.random_checkpoint import random_values
    from geonet_infer.convert.tf_checkpoint import write_checkpoint

    values = random_values(official_variables()["pose_seq3"], np.random.default_rng(0))
    name = next(n for n in sorted(values) if n.endswith("/weights"))
    values[name][...] = np.nan
    prefix = write_checkpoint(tmp_path / "ckpt" / "model-1", values)
    out = tmp_path / "model"
    rc = export_main(["--from-tf", f"pose={prefix}", "--out", str(out), "--height", "64", "--width", "224", "--quiet"])
    assert rc == 2
    assert name in one_line(capsys.readouterr().err)
    assert not out.exists() and os.listdir(tmp_path) == ["ckpt"]

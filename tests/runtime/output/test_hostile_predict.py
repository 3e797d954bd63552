"""`geonet-infer predict` under hostile and careless use (issue 27): nothing lost, nothing silently wrong.

Each test reproduces one case of the issue with a tiny hand-made input (the bundled sample frames,
a PNG header written by hand, a video written with cv2.VideoWriter) and checks the documented
behaviour: a failed frame recorded with its real reason, a one-line error with the right exit code,
an output folder that never mixes two runs. Tests that could crash the interpreter (OpenCV segfaults)
or need a signal run the CLI in a subprocess (`python -m geonet_infer.cli`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import json
import os
import shutil
import signal
import struct
import subprocess
import sys
import time
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

import geonet_infer
from geonet_infer.cli import main
from geonet_infer.core.predictor import Predictor
from tests.conftest import GEONET_CLI

PKG = Path(geonet_infer.__file__).resolve().parent
SAMPLE = PKG / "samples" / "synth_seq"
SAMPLE_CALIB = SAMPLE / "calib.txt"
SAMPLE_FRAMES = sorted((SAMPLE / "image").glob("*.png"))
REPO = PKG.parent


def sample_folder(tmp_path: Path, n: int = 5, name: str = "frames") -> Path:
    """A folder with ``n`` sample frames named 000000.png ... (the 12 samples repeated as needed)."""
    folder = tmp_path / name
    folder.mkdir()
    for i in range(n):
        shutil.copyfile(SAMPLE_FRAMES[i % len(SAMPLE_FRAMES)], folder / f"{i:06d}.png")
    return folder


def run_cli(capture, *argv) -> tuple[int, str, str]:
    rc = main([str(a) for a in argv])
    out, err = capture.readouterr()
    return rc, out, err


def run_sub(*argv, timeout_s: float = 120, **kwargs) -> subprocess.CompletedProcess:
    return subprocess.run(
        [*GEONET_CLI, *map(str, argv)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=timeout_s,
        **kwargs,
    )


def error_lines(stderr: str) -> list[str]:
    return [line for line in stderr.splitlines() if line.strip()]


def summary_of(out: Path) -> dict:
    return json.loads((out / "summary.json").read_text())


def stems(folder: Path, pattern: str) -> list[str]:
    return sorted(p.name.split(".")[0] for p in folder.glob(pattern))


def temp_files(root: Path) -> list[Path]:
    """Hidden files other than predict's ownership marker: leftovers of the atomic writer or the lock."""
    return [p for p in root.rglob("*") if p.name.startswith(".") and p.name != ".geonet-predict"]


def png_header(width: int, height: int) -> bytes:
    """A PNG signature and IHDR chunk claiming ``width`` x ``height`` RGB 8-bit, then a bogus IDAT and IEND."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", b"\x00" * 64) + chunk(b"IEND", b"")


def write_video(path: Path, frames: int = 38, size=(64, 48)) -> Path:
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 10, size)
    assert writer.isOpened()
    rng = np.random.default_rng(0)
    for _ in range(frames):
        writer.write(rng.integers(0, 256, (size[1], size[0], 3), dtype=np.uint8))
    writer.release()
    return path


# ----------------------------------------------------------------------------- 1. file names that are not UTF-8
def test_frame_name_not_utf8_is_processed_not_a_segfault(tmp_path):
    folder = sample_folder(tmp_path, 4)
    odd = os.fsencode(folder) + b"/000004\xff.png"
    shutil.copyfile(SAMPLE_FRAMES[4], odd)
    out = tmp_path / "out"
    proc = run_sub("predict", folder, "--out", out, "--calib", SAMPLE_CALIB, "--no-progress")
    assert proc.returncode == 0, (proc.returncode, proc.stderr[-2000:])
    assert b"000004\xff.npy" in os.listdir(os.fsencode(out / "depth"))
    assert summary_of(out)["frames"] == 5


def test_video_name_not_utf8_is_a_one_line_error(tmp_path):
    video = write_video(tmp_path / "clip.mp4", frames=4)
    odd = os.fsencode(tmp_path) + b"/clip\xff.mp4"
    os.rename(video, odd)
    proc = run_sub("predict", os.fsdecode(odd), "--out", tmp_path / "out", "--tasks", "depth", "--no-progress")
    assert proc.returncode == 2, (proc.returncode, proc.stderr[-2000:])
    [line] = error_lines(proc.stderr)
    assert "clip" in line and "UTF-8" in line


# ----------------------------------------------------------------------------- 2. pixel cap
def test_frames_over_the_pixel_cap_are_refused_before_decoding(tmp_path, capsys):
    folder = sample_folder(tmp_path, 4)
    (folder / "000004.png").write_bytes(png_header(10_000, 10_000))  # 100 Mpx: over the cap, under OpenCV's own
    (folder / "000005.png").write_bytes(png_header(100_000, 100_000))  # OpenCV's own limit raises cv2.error
    out = tmp_path / "out"
    rc, _, stderr = run_cli(capsys, "predict", folder, "--out", out, "--calib", SAMPLE_CALIB, "--no-progress")
    assert rc == 1, stderr
    summary = summary_of(out)
    assert summary["frames"] == 4
    reasons = {f["frame"]: f["reason"] for f in summary["failures"]}
    assert set(reasons) == {"000004", "000005"}
    from geonet_infer.io.images import MAX_IMAGE_PIXELS

    for name, size in (("000004", "10000x10000"), ("000005", "100000x100000")):
        assert f"{name}.png" in reasons[name] and size in reasons[name]
        assert f"{MAX_IMAGE_PIXELS:,}" in reasons[name] or str(MAX_IMAGE_PIXELS) in reasons[name]


def test_video_over_the_pixel_cap_is_refused(tmp_path, monkeypatch):
    import geonet_infer.io.images as images
    from geonet_infer import GeoNetError
    from geonet_infer.io import open_frames

    video = write_video(tmp_path / "clip.mp4", frames=3)
    monkeypatch.setattr(images, "MAX_IMAGE_PIXELS", 1000)  # the 64x48 frames are 3072 pixels
    with pytest.raises(GeoNetError, match=r"clip\.mp4.*64x48.*1,000 pixels"):
        open_frames(video)


# ----------------------------------------------------------------------------- 3. threads and batch size
@pytest.mark.parametrize("flag", ["--threads", "--batch-size"])
def test_threads_and_batch_size_have_limits(tmp_path, capsys, flag):
    from geonet_infer.engines import usable_cpus
    from geonet_infer.limits import MAX_BATCH_SIZE

    folder = sample_folder(tmp_path, 3)
    out = tmp_path / "out"
    value = 5000 if flag == "--threads" else 100_000
    rc, _, stderr = run_cli(capsys, "predict", folder, "--out", out, "--tasks", "depth", flag, value, "--no-progress")
    assert rc == 2
    [line] = error_lines(stderr)
    assert flag in line and str(value) in line
    assert str(usable_cpus() if flag == "--threads" else MAX_BATCH_SIZE) in line
    assert not out.exists()


# ----------------------------------------------------------------------------- 4. existing output folders
def test_refuses_a_non_empty_folder_it_did_not_write(tmp_path, capsys):
    folder = sample_folder(tmp_path, 3)
    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    rc, _, stderr = run_cli(capsys, "predict", folder, "--out", out, "--tasks", "depth", "--no-progress")
    assert rc == 2
    [line] = error_lines(stderr)
    assert str(out) in line and "another --out" in line
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"] and (out / "notes.txt").read_text() == "mine"


def test_a_second_run_replaces_the_first_runs_outputs_only(tmp_path, capsys):
    out = tmp_path / "out"
    long = sample_folder(tmp_path, 5, "long")
    assert run_cli(capsys, "predict", long, "--out", out, "--calib", SAMPLE_CALIB, "--no-progress")[0] == 0
    (out / "notes.txt").write_text("mine")  # the user's own file, added after the first run
    (out / "depth" / "keep.txt").write_text("mine too")
    short = sample_folder(tmp_path, 3, "short")
    rc, _, stderr = run_cli(capsys, "predict", short, "--out", out, "--tasks", "depth", "--no-progress")
    assert rc == 0, stderr
    names = ["000000", "000001", "000002"]
    assert stems(out / "depth", "*.npy") == names and stems(out / "depth", "*.png") == names
    assert not (out / "flow").exists() and not (out / "poses_kitti.txt").exists()
    assert (out / "notes.txt").read_text() == "mine" and (out / "depth" / "keep.txt").read_text() == "mine too"
    assert summary_of(out)["frames"] == 3 and temp_files(out) == []


def test_a_folder_locked_by_a_live_predict_is_refused_and_a_stale_lock_is_taken(tmp_path, capsys):
    folder = sample_folder(tmp_path, 3)
    out = tmp_path / "out"
    argv = ("predict", folder, "--out", out, "--tasks", "depth", "--no-progress")
    assert run_cli(capsys, *argv)[0] == 0
    lock = out / ".geonet-predict.lock"
    lock.write_text(f"{os.getpid()}\n")  # this test's process: alive
    rc, _, stderr = run_cli(capsys, *argv)
    assert rc == 2
    [line] = error_lines(stderr)
    assert str(os.getpid()) in line and "another" in line
    assert lock.read_text() == f"{os.getpid()}\n"  # not ours: left alone
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    lock.write_text(f"{dead.pid}\n")
    rc, _, stderr = run_cli(capsys, *argv)
    assert rc == 0, stderr
    assert not lock.exists()


def test_sigterm_mid_run_cleans_up_writes_an_interrupted_summary_and_exits_130(tmp_path):
    folder = sample_folder(tmp_path, 150)
    out = tmp_path / "out"
    proc = subprocess.Popen(
        [*GEONET_CLI, "predict", str(folder), "--out", str(out), "--no-progress"] + ["--calib", str(SAMPLE_CALIB)],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    deadline = time.monotonic() + 60
    while len(list((out / "depth").glob("*.npy"))) < 3 and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.05)
    proc.send_signal(signal.SIGTERM)
    _, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 130, stderr[-2000:]
    [line] = error_lines(stderr)
    assert "interrupted" in line
    summary = summary_of(out)
    assert summary["interrupted"] is True and 2 <= summary["frames"] < 150
    # the frame being written when the signal came is removed, so files and summary agree
    assert len(list((out / "depth").glob("*.npy"))) == len(list((out / "depth").glob("*.png"))) == summary["frames"]
    assert temp_files(out) == []


@pytest.mark.parametrize("cut", ["queued", "recorded"])
def test_an_interrupt_between_two_steps_of_the_writer_neither_loses_nor_hides_a_written_frame(
    tmp_path, capsys, monkeypatch, cut
):
    """Python runs a signal's handler between any two bytecodes of the main thread. A Ctrl-C right after the
    write pool took frame 3 ("queued": its files were written, it was never recorded) left 8 frames on disk
    and 7 in the summary (CI, 2026-12-07); so would one right after a written frame left the queue
    ("recorded"). The signal is raised at exactly those points (signal.raise_signal runs its handler there)."""
    from geonet_infer.output import writer as writer_module

    calls = {"n": 0}

    def cut_here() -> None:
        calls["n"] += 1
        if calls["n"] == 4:
            signal.raise_signal(signal.SIGINT)

    class CutPool(writer_module.ThreadPoolExecutor):
        def submit(self, *args, **kwargs):
            future = super().submit(*args, **kwargs)
            if cut == "queued":
                cut_here()
            return future

    class CutQueue(writer_module.deque):
        def popleft(self):
            item = super().popleft()
            if cut == "recorded":
                cut_here()
            return item

    monkeypatch.setattr(writer_module, "ThreadPoolExecutor", CutPool)
    monkeypatch.setattr(writer_module, "deque", CutQueue)
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    folder = sample_folder(tmp_path, 12)
    out = tmp_path / "out"
    rc, _, stderr = run_cli(capsys, "predict", folder, "--out", out, "--no-progress", "--calib", SAMPLE_CALIB)
    assert rc == 130, stderr
    assert calls["n"] >= 4
    summary = summary_of(out)
    assert summary["interrupted"] is True
    npy, png = stems(out / "depth", "*.npy"), stems(out / "depth", "*.png")
    assert npy == png == [f"{i:06d}" for i in range(summary["frames"])]
    assert summary["frames"] >= 4  # the frame written when the signal came is counted, not left behind uncounted
    assert temp_files(out) == []
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_closing_the_writer_removes_the_files_of_frames_written_but_never_recorded(tmp_path, monkeypatch):
    """A second Ctrl-C stops predict's drain: close() lets the started writes finish, then removes their files,
    so the files on disk are the frames recorded (the summary's count); recorded frames stay."""
    import threading

    from geonet_infer.core.results import FrameResult
    from geonet_infer.output import writer as writer_module

    gate, waiting, made = threading.Event(), threading.Semaphore(0), []
    real_npy = writer_module._WRITERS["depth-npy"]

    def gated_npy(path, depth):
        if path.stem >= "f3":
            waiting.release()
            assert gate.wait(30)
        real_npy(path, depth)
        made.append(path.stem)

    monkeypatch.setitem(writer_module._WRITERS, "depth-npy", gated_npy)
    recorded: list[str] = []
    writer = writer_module.FrameWriter(
        tmp_path, ("depth",), {"depth-npy", "depth-vis"}, lambda result, rgb, written: recorded.append(result.name)
    )
    depth = np.linspace(1, 50, 6 * 8, dtype=np.float32).reshape(6, 8)
    for i in range(5):
        fields = dict(camera_to_world=np.eye(4), pose_to_next=None, pose_vector_to_next=None, flow=None)
        writer.submit(FrameResult(i, f"f{i}", depth, 1 / depth, **fields, undistorted=False, timings_ms={}))
        if i == 2:
            writer.drain()
    assert waiting.acquire(timeout=30) and waiting.acquire(timeout=30)  # both writes started (none cancelled)
    gate.set()  # frames 3 and 4 now written, never drained
    writer.close()
    assert sorted(made) == ["f0", "f1", "f2", "f3", "f4"]
    assert recorded == ["f0", "f1", "f2"]
    assert stems(tmp_path / "depth", "*.npy") == stems(tmp_path / "depth", "*.png") == recorded


def test_names_claimed_while_an_interrupt_cuts_the_marker_write_are_claimed_again(tmp_path, monkeypatch):
    """A video's frame names are claimed in blocks as it decodes. A Ctrl-C inside the marker's write must not
    leave the names taken as claimed: the next frame would be written unlisted, and the next run into OUT
    refuse it as a file predict did not write."""
    from geonet_infer.output import ownership

    out = tmp_path / "out"
    record = {"written_by": "geonet-infer predict", "version": "test"}
    owned = ownership.OwnedFolder(out, {"a.npy"}, "in.mp4", marker=".m", lock=".m.lock", record=record)
    real_write = ownership.atomic_write
    cut = {"left": 1}

    @contextlib.contextmanager
    def interrupted_write(path):
        with real_write(path) as tmp:
            yield tmp
            if cut["left"]:
                cut["left"] -= 1
                raise KeyboardInterrupt  # the temp file is dropped, the marker stays as it was

    with owned:
        monkeypatch.setattr(ownership, "atomic_write", interrupted_write)
        with pytest.raises(KeyboardInterrupt):
            owned.add({"b.npy"})
        owned.add({"b.npy"})  # the next frame claims the name again
        assert ownership.read_marker(out / ".m")["files"] == ["a.npy", "b.npy"]


# ----------------------------------------------------------------------------- 5. non-finite outputs
@pytest.mark.parametrize("what", ["depth", "flow", "pose"])
def test_a_non_finite_output_fails_its_frame_and_is_not_written(tmp_path, capsys, monkeypatch, what):
    real = Predictor.iter_sequence

    def poisoned(self, *args, **kwargs):
        for result in real(self, *args, **kwargs):
            if result.index == 2:
                if what == "depth":
                    result = dataclasses.replace(result, depth=np.full_like(result.depth, np.nan))
                elif what == "flow":
                    result = dataclasses.replace(result, flow=np.full_like(result.flow, np.inf))
                else:
                    result = dataclasses.replace(result, camera_to_world=np.full((4, 4), np.nan))
            yield result

    monkeypatch.setattr(Predictor, "iter_sequence", poisoned)
    folder = sample_folder(tmp_path, 5)
    out = tmp_path / "out"
    rc, _, stderr = run_cli(capsys, "predict", folder, "--out", out, "--calib", SAMPLE_CALIB, "--no-progress")
    assert rc == 1, stderr
    [failure] = summary_of(out)["failures"]
    assert failure["frame"] == "000002" and f"NaN/inf {what}" in failure["reason"]
    assert "000002" not in stems(out / "depth", "*") and "000002" not in stems(out / "flow", "*")
    for line in (out / "poses_kitti.txt").read_text().splitlines():
        assert np.isfinite(np.array(line.split(), dtype=float)).all()


# ----------------------------------------------------------------------------- 6. truncated video
def test_a_truncated_mp4_is_reported_and_exits_1(tmp_path, capsys):
    video = write_video(tmp_path / "clip.mp4", frames=38)
    data = bytearray(video.read_bytes())
    moov = data.find(b"moov") - 4  # cv2.VideoWriter puts the index after the media data
    cut = moov // 2
    data[cut:moov] = bytes(moov - cut)  # the second half of the media data lost (zeroed)
    video.write_bytes(bytes(data))
    cap = cv2.VideoCapture(str(video))  # independent count: what OpenCV decodes, what the container lists
    listed, decodable = int(cap.get(cv2.CAP_PROP_FRAME_COUNT)), 0
    while cap.read()[0]:
        decodable += 1
    cap.release()
    assert listed == 38 and 2 <= decodable < 38
    out = tmp_path / "out"
    rc, _, stderr = run_cli(capsys, "predict", video, "--out", out, "--tasks", "depth", "--no-progress")
    assert rc == 1, stderr
    summary = summary_of(out)
    assert summary["truncated"] == f"decoded {decodable} of {listed} frames"
    assert summary["frames"] == decodable and summary["failed"] == listed - decodable
    warnings = [line for line in error_lines(stderr) if "truncated" in line]
    assert len(warnings) == 1 and f"decoded {decodable} of {listed} frames" in warnings[0]


def overcounted_avi(path: Path, frames: int, listed: int) -> Path:
    """An MJPG AVI of ``frames`` frames whose headers (avih total frames, strh length) say ``listed``."""
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, (64, 48))
    rng = np.random.default_rng(0)
    for _ in range(frames):
        writer.write(rng.integers(0, 256, (48, 64, 3), dtype=np.uint8))
    writer.release()
    data = bytearray(path.read_bytes())
    avih, strh = data.find(b"avih") + 8, data.find(b"strh") + 8  # RIFF chunk bodies (AVI 1.0 layout)
    data[avih + 16 : avih + 20] = struct.pack("<I", listed)  # dwTotalFrames
    data[strh + 32 : strh + 36] = struct.pack("<I", listed)  # dwLength
    path.write_bytes(bytes(data))
    cap = cv2.VideoCapture(str(path))  # independent: the header OpenCV reads now over-counts
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == listed
    cap.release()
    return path


def test_a_video_whose_header_over_counts_exits_0_with_one_note(tmp_path, capsys):
    # Container frame counts are often approximate (issue 43): a clean end 3 frames early is no failure.
    video = overcounted_avi(tmp_path / "clip.avi", frames=6, listed=9)
    out = tmp_path / "out"
    rc, _, stderr = run_cli(capsys, "predict", video, "--out", out, "--tasks", "depth", "--no-progress")
    assert rc == 0, stderr
    summary = summary_of(out)
    assert summary["frames"] == 6 and summary["failed"] == 0 and summary["truncated"] is None
    assert summary["notes"] == ["the video ended after 6 frames, 3 before its header's count of 9 (container "
                                "counts are often approximate)"]  # fmt: skip
    notes = [line for line in error_lines(stderr) if "header's count" in line]
    assert len(notes) == 1 and "note" in notes[0], stderr


@pytest.mark.parametrize("listed", [1_000_000, 2_000_000_000])
@pytest.mark.parametrize("how", ["predict", "predict --max-frames 20", "batch"])
def test_a_header_that_lies_about_the_length_sizes_no_work(tmp_path, listed, how):
    """Issue 55: an AVI of 8 frames whose header claims a million (or two billion) made predict claim,
    check and list every claimed frame (over 60 s, 1.1-3 GB). Now: the 8 depths, one record for the rest,
    one warning line, and an ownership marker of a few hundred names (claimed in blocks as frames decode)."""
    video = overcounted_avi(tmp_path / "clip.avi", frames=8, listed=listed)
    out = tmp_path / "out"
    command, *extra = how.split(" ", 1)
    argv = [command, video, "--out", out, "--tasks", "depth", "--no-progress", *(extra[0].split() if extra else [])]
    proc = run_sub(*argv, timeout_s=120)
    assert proc.returncode == 1, proc.stderr[-2000:]
    folder = out if command == "predict" else out / "clip"
    assert len(list((folder / "depth").glob("*.npy"))) == 8
    summary = summary_of(folder)
    assert summary["failures"] == [
        {"frame": f"000008-{listed - 1:06d}", "reason": f"{video}: truncated: {summary['truncated']}"}
    ]
    assert f"the {listed - 8} frames its header lists beyond them did not decode" in summary["truncated"]
    marker = json.loads(next(folder.glob(".geonet-predict*")).read_text())
    assert len(marker["files"]) < 4000
    if command == "predict":
        assert len([line for line in error_lines(proc.stderr) if "truncated" in line]) == 1


# ----------------------------------------------------------------------------- 7. camera sanity limits
@pytest.mark.parametrize(
    "case, argv, named",
    [
        ("tiny focal", ["--intrinsics", "1e-30,1e-30,208,64"], "--intrinsics"),
        ("far principal point", ["--intrinsics", "400,400,1e30,64"], "--intrinsics"),
        ("huge distortion", ["--calib", "CALIB"], "cam.txt"),
        ("huge camera height", ["--calib", str(SAMPLE_CALIB), "--camera-height", "1e38"], "--camera-height"),
        ("zero camera height", ["--calib", str(SAMPLE_CALIB), "--camera-height", "0"], "--camera-height"),
    ],
)
def test_insane_calibration_is_refused_with_one_line(tmp_path, capsys, case, argv, named):
    folder = sample_folder(tmp_path, 3)
    calib = tmp_path / "cam.txt"
    calib.write_text("fx 400\nfy 400\ncx 208\ncy 64\ndist 1e6 0 0 0 0\n")
    argv = [calib if a == "CALIB" else a for a in argv]
    out = tmp_path / "out"
    rc, _, stderr = run_cli(capsys, "predict", folder, "--out", out, *argv, "--no-progress")
    assert rc == 2, (case, stderr)
    [line] = error_lines(stderr)
    assert named in line, line
    assert not (out / "depth").exists()


def test_real_dashcam_and_kitti_calibrations_stay_accepted(realdata):
    from geonet_infer.io import read_camera

    for rel, size in (
        ("udacity_dashcam/calib_advanced_lane_lines.txt", (1280, 720)),
        ("kitti_raw_2011_09_26_sfnd/calib_cam_to_cam.txt", (1242, 375)),
    ):
        camera = read_camera(realdata / rel)
        camera.scaled_to(*size).check_image_size(*size, rel)


# ----------------------------------------------------------------------------- 8. the OS refuses a write
FSIZE_SCRIPT = """
import resource, signal, sys
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # writes past the limit fail with EFBIG instead of killing
resource.setrlimit(resource.RLIMIT_FSIZE, (4096, 4096))
import numpy as np
from geonet_infer.io import write_image
try:
    write_image(sys.argv[1], np.random.default_rng(0).integers(0, 256, (64, 64, 3), dtype=np.uint8))
except OSError as exc:
    print("OSError", exc.errno)
except Exception as exc:
    print(type(exc).__name__, exc)
"""


def test_a_png_write_the_disk_refuses_is_an_os_error_not_a_bad_suffix(tmp_path):
    proc = subprocess.run(
        [sys.executable, "-c", FSIZE_SCRIPT, str(tmp_path / "x.png")], cwd=tmp_path, capture_output=True, text=True
    )
    assert proc.stdout.strip() == f"OSError {errno.EFBIG}", proc.stdout + proc.stderr
    assert os.listdir(tmp_path) == []  # no temp file left


@pytest.mark.parametrize("case", ["out_is_a_file", "disk_full_npy", "disk_full_text"])
def test_os_errors_while_writing_exit_3_with_one_line(tmp_path, capsys, monkeypatch, case):
    folder = sample_folder(tmp_path, 3)
    out = tmp_path / "out"
    if case == "out_is_a_file":
        out.write_text("a file")
    elif case == "disk_full_npy":

        def full(*args, **kwargs):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

        monkeypatch.setattr(np, "save", full)
    else:
        real_write_text = Path.write_text

        def full_text(self, *args, **kwargs):
            if self.name.startswith(".poses_kitti") or self.name.startswith(".summary"):
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(self))
            return real_write_text(self, *args, **kwargs)

        monkeypatch.setattr(Path, "write_text", full_text)
    rc, _, stderr = run_cli(capsys, "predict", folder, "--out", out, "--calib", SAMPLE_CALIB, "--no-progress")
    assert rc == 3, stderr
    [line] = error_lines(stderr)
    assert line.startswith("geonet-infer predict: error:")
    if out.is_dir():
        assert temp_files(out) == []


# ----------------------------------------------------------------------------- 9. unreadable frames: the real reason
def test_an_unreadable_frame_is_reported_with_its_real_reason(tmp_path, capsys, monkeypatch):
    folder = sample_folder(tmp_path, 6)
    (folder / "000002.png").write_bytes(b"")
    (folder / "000003.png").write_text("these are my notes, not a picture\n")
    locked = folder / "000004.png"
    real_read_bytes = Path.read_bytes

    def read_bytes(self):  # tests run as root, where chmod 000 does not stop a read
        if self == locked:
            raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), str(self))
        return real_read_bytes(self)

    monkeypatch.setattr(Path, "read_bytes", read_bytes)
    out = tmp_path / "out"
    rc, _, stderr = run_cli(capsys, "predict", folder, "--out", out, "--calib", SAMPLE_CALIB, "--no-progress")
    assert rc == 1, stderr
    reasons = {f["frame"]: f["reason"] for f in summary_of(out)["failures"]}
    assert set(reasons) == {"000002", "000003", "000004"}
    assert "empty file" in reasons["000002"]
    assert "not an image" in reasons["000003"]
    assert "Permission denied" in reasons["000004"]
    assert not any("valid PNG/JPEG" in r for r in reasons.values())


# ----------------------------------------------------------------------------- 10. mixed frame sizes
def test_the_odd_sized_frame_is_skipped_even_when_it_sorts_first(tmp_path, capsys):
    folder = sample_folder(tmp_path, 5)
    small = cv2.resize(cv2.imread(str(folder / "000000.png")), (208, 64))
    assert cv2.imwrite(str(folder / "000000.png"), small)
    out = tmp_path / "out"
    rc, _, stderr = run_cli(capsys, "predict", folder, "--out", out, "--calib", SAMPLE_CALIB, "--no-progress")
    assert rc == 1, stderr
    summary = summary_of(out)
    assert summary["frames"] == 4 and summary["image_size"] == [416, 128]
    [failure] = summary["failures"]
    assert failure["frame"] == "000000" and "208x64" in failure["reason"]


def test_header_sizes_match_what_opencv_encoded():
    from geonet_infer.io.images import IMAGE_SUFFIXES, encoded_size

    image = np.random.default_rng(0).integers(0, 256, (23, 37, 3), dtype=np.uint8)
    for suffix in IMAGE_SUFFIXES:
        ok, data = cv2.imencode(suffix, image)
        assert ok and encoded_size(data.tobytes()) == (37, 23), suffix
    assert encoded_size(b"these are my notes") is None

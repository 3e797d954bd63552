"""Nothing lost, round two (issue 41): what `predict` and `batch` write and remove, checked against the
inputs and against files they did not make, after symlinks are resolved; SIGTERM at any moment; the
result video checked after writing.

Inputs are copies of the bundled sample's 128x416 frames (depth only: fast). Every check compares files
by their bytes as recorded before the run (sha256), never by what the code under test reports.
"""

from __future__ import annotations

import hashlib
import json
import os
import resource
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import pytest

from tests.runtime.batch.test_batch import CLI, make_sequences
from tests.runtime.output.test_hostile_predict import REPO, error_lines, run_cli, sample_folder, summary_of, write_video

DEPTH = ["--tasks", "depth", "--no-progress", "--quiet"]


def sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def digest(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): sha(p) for p in sorted(folder.rglob("*")) if p.is_file()}


def frame_count(video: Path) -> int:
    """Frames OpenCV decodes from ``video`` (0 if it cannot be opened)."""
    cap = cv2.VideoCapture(str(video))
    n = 0
    while cap.isOpened() and cap.grab():
        n += 1
    cap.release()
    return n


# ----------------------------------------------------------------------------- 1. files predict did not make
@pytest.mark.parametrize("what", ["video", "camera", "frame"])
def test_a_file_predict_did_not_write_is_never_overwritten(tmp_path, capsys, what):
    """Case 1: a file of the user's at a path this run would write (not listed by the earlier run) is refused
    before anything is written or removed, and the next run (without that output) keeps it too."""
    frames = sample_folder(tmp_path, 3)
    out = tmp_path / "O"
    assert run_cli(capsys, "predict", frames, "--out", out, *DEPTH)[0] == 0
    mine = {"video": out / "holiday.mp4", "camera": out / "camera.txt", "frame": out / "depth" / "000003.npy"}[what]
    if what == "video":
        write_video(mine, frames=4)
    else:
        mine.write_bytes(b"my own file\n")
    extra = {
        "video": ["--video-out", mine],
        "camera": ["--intrinsics", "400,400,208,64"],
        "frame": [],
    }[what]
    second = sample_folder(tmp_path, 4, "four") if what == "frame" else frames
    before = digest(out)
    rc, _, stderr = run_cli(capsys, "predict", second, "--out", out, *DEPTH, *extra)
    assert rc == 2, stderr
    [line] = error_lines(stderr)
    assert mine.name in line and "did not write" in line
    assert digest(out) == before  # nothing written, nothing removed
    rc, _, stderr = run_cli(capsys, "predict", frames, "--out", out, *DEPTH)  # the next run keeps it too
    assert rc == 0, stderr
    assert sha(mine) == before[str(mine.relative_to(out))]


# ----------------------------------------------------------------------------- 2. symlinks resolved
def test_video_out_through_a_symlink_to_an_outside_file_is_refused(tmp_path, capsys):
    """Case 2: OUT/link -> a folder outside OUT; --video-out OUT/link/mine.mp4 is a file predict did not write."""
    frames = sample_folder(tmp_path, 3)
    out, elsewhere = tmp_path / "O", tmp_path / "elsewhere"
    assert run_cli(capsys, "predict", frames, "--out", out, *DEPTH)[0] == 0
    elsewhere.mkdir()
    mine = write_video(elsewhere / "mine.mp4", frames=4)
    (out / "link").symlink_to(elsewhere)
    before = sha(mine)
    rc, _, stderr = run_cli(capsys, "predict", frames, "--out", out, *DEPTH, "--video-out", out / "link" / "mine.mp4")
    assert rc == 2, stderr
    [line] = error_lines(stderr)
    assert "mine.mp4" in line
    assert sha(mine) == before and os.listdir(elsewhere) == ["mine.mp4"]


def test_outputs_through_a_symlinked_folder_are_refused(tmp_path, capsys):
    """Ownership: a frame's files (point clouds here) go only into OUT, even when OUT/points is a symlink."""
    frames = sample_folder(tmp_path, 3)
    out, elsewhere = tmp_path / "O", tmp_path / "elsewhere"
    assert run_cli(capsys, "predict", frames, "--out", out, *DEPTH)[0] == 0
    elsewhere.mkdir()
    (out / "points").symlink_to(elsewhere)
    argv = ("predict", frames, "--out", out, *DEPTH, "--intrinsics", "400,400,208,64", "--point-cloud", "camera")
    before = digest(out)
    rc, _, stderr = run_cli(capsys, *argv)
    assert rc == 2, stderr
    [line] = error_lines(stderr)
    assert "points" in line
    assert os.listdir(elsewhere) == [] and digest(out) == before  # refused before anything was written


# ----------------------------------------------------------------------------- 3, 5. inputs never written or removed
@pytest.mark.parametrize("case", ["clip_as_video_out", "frames_in_out"])
def test_a_run_never_writes_or_removes_its_own_input(tmp_path, capsys, case):
    """Case 3: the input clip inside an earlier run's OUT given as --video-out; case 5: the input frames are
    an earlier run's OUT/depth (its colour maps), which the clean-up would delete before reading them."""
    frames = sample_folder(tmp_path, 3)
    out = tmp_path / "O"
    assert run_cli(capsys, "predict", frames, "--out", out, *DEPTH)[0] == 0
    if case == "clip_as_video_out":
        clip = write_video(out / "clip.mp4", frames=4)
        argv = [clip, "--out", out, *DEPTH, "--video-out", clip]
    else:
        argv = [out / "depth", "--out", out, *DEPTH]
    before = digest(out)
    rc, _, stderr = run_cli(capsys, "predict", *argv)
    assert rc == 2, stderr
    [line] = error_lines(stderr)
    assert "input" in line
    assert digest(out) == before


# ----------------------------------------------------------------------------- 4. batch keeps the user's files
@pytest.mark.parametrize("how", ["rerun", "resume_redo"])
def test_batch_keeps_files_it_did_not_make_in_its_sequence_folders(tmp_path, capfd, how):
    """Case 4: files and folders the user put into batch's sequence folders survive a re-run, and a resume
    that redoes the sequence; batch removes exactly the files it listed."""
    from tests.runtime.batch.test_batch import cli

    seqs = make_sequences(tmp_path / "in", ["seqA", "seqB"], 3)
    out = tmp_path / "out"
    argv = ["batch", *seqs, "--out", out, *DEPTH, "--no-vis", "--workers", "1"]
    assert cli(capfd, *argv)[0] == 0
    (out / "seqA" / "labels.txt").write_text("my labels\n")
    (out / "seqB" / "annot").mkdir()
    (out / "seqB" / "annot" / "boxes.json").write_text("[]\n")
    if how == "resume_redo":
        (out / "seqA" / "depth" / "000000.npy").unlink()  # seqA must be redone
        (out / "seqB" / "depth" / "000001.npy").unlink()
        argv.append("--resume")
    rc, stdout, stderr = cli(capfd, *argv)
    assert rc == 0, stderr
    if how == "resume_redo":
        assert "2 redone" in stdout
    assert (out / "seqA" / "labels.txt").read_text() == "my labels\n"
    assert (out / "seqB" / "annot" / "boxes.json").read_text() == "[]\n"
    for seq in ("seqA", "seqB"):
        assert sorted(p.name for p in (out / seq / "depth").iterdir()) == [f"00000{i}.npy" for i in range(3)]
    # a resume right after skips both: the user's files are not outputs to check
    rc, stdout, _ = cli(capfd, "batch", *seqs, "--out", out, *DEPTH, "--no-vis", "--workers", "1", "--resume")
    assert rc == 0 and "2 skipped" in stdout, stdout


# ----------------------------------------------------------------------------- 15. the video is checked after writing
def _small_files_only():  # in the child: no file past 32 KiB (EFBIG), as on a nearly full disk
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (32 * 1024, 32 * 1024))


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="RLIMIT_FSIZE")
def test_a_video_the_disk_cut_short_exits_3_and_is_not_left(tmp_path):
    """Case 15: OpenCV's writer ignores a failed write; the video is re-opened and its frames counted."""
    frames = sample_folder(tmp_path, 8)
    out, video = tmp_path / "O", tmp_path / "result.mp4"
    proc = subprocess.run(
        [*CLI, "predict", str(frames), "--out", str(out), "--tasks", "pose", "--no-progress"]
        + ["--video-out", str(video)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
        preexec_fn=_small_files_only,
    )
    assert proc.returncode == 3, proc.stderr[-2000:]
    [line] = error_lines(proc.stderr)
    assert str(video) in line
    assert not video.exists() and [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


# ----------------------------------------------------------------------------- 22. re-runs and SIGKILL
def test_an_identical_rerun_replaces_its_own_video_outside_out(tmp_path, capsys):
    """Case 22: the video a run wrote outside OUT is its own on an identical re-run (recorded in OUT's marker
    with its digest); a file the user put there instead is still refused."""
    frames = sample_folder(tmp_path, 3)
    out, video = tmp_path / "O", tmp_path / "videos" / "result.mp4"
    argv = ("predict", frames, "--out", out, *DEPTH, "--video-out", video)
    assert run_cli(capsys, *argv)[0] == 0
    assert frame_count(video) == 3
    rc, _, stderr = run_cli(capsys, *argv)
    assert rc == 0, stderr
    assert frame_count(video) == 3
    write_video(video, frames=4)  # the user's own video under that name now
    before = sha(video)
    rc, _, stderr = run_cli(capsys, *argv)
    assert rc == 2 and "did not write" in error_lines(stderr)[0], stderr
    assert sha(video) == before


@pytest.mark.parametrize("where", ["inside", "outside"])
def test_the_temp_video_of_a_killed_run_is_removed_by_the_next(tmp_path, where):
    """Case 22: SIGKILL leaves the streamed video's temp file; the next run into the same OUT removes it."""
    frames = sample_folder(tmp_path, 150)
    out = tmp_path / "O"
    video = out / "result.mp4" if where == "inside" else tmp_path / "videos" / "result.mp4"
    argv = [*CLI, "predict", str(frames), "--out", str(out), *DEPTH, "--video-out", str(video)]
    proc = subprocess.Popen(argv, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 120
        while not list(video.parent.glob(".result.*.mp4")) and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.05)
        proc.kill()
        proc.wait(30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert list(video.parent.glob(".result.*.mp4")), "the killed run left no temp video"
    short = sample_folder(tmp_path, 3, "short")
    proc = subprocess.run(
        [*CLI, "predict", str(short), "--out", str(out), *DEPTH, "--video-out", str(video)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert list(video.parent.glob(".result.*.mp4")) == []
    assert frame_count(video) == 3
    assert summary_of(out)["video"]["frames"] == 3
    json.loads((out / ".geonet-predict").read_text())  # the marker stays readable


# ----------------------------------------------------------------------------- 6. SIGTERM at any moment
class _Exited(BaseException):
    """os._exit, made visible to the test."""


def test_a_second_sigterm_in_a_workers_clean_up_ends_the_worker(tmp_path, monkeypatch):
    """Case 6: a SIGTERM sent to the whole group reaches a busy worker, then the job's own SIGTERM (stopping
    the pool) comes while the worker removes its unfinished folder. That one must neither cut the clean-up
    short (stray files, no marker: --resume refused) nor escape to the pool's loop (the next sequence starts).

    It signals its own process, so it runs in a fresh interpreter: in the whole suite's process, where
    earlier tests loaded TensorFlow, Ray and OpenVINO, the same signals ended pytest with SIGSEGV."""
    if not os.environ.get("GEONET_ISOLATED_TEST"):
        checkout = Path(__file__).resolve().parents[3]  # not REPO: site-packages in the runtime-only run
        this_test = test_a_second_sigterm_in_a_workers_clean_up_ends_the_worker.__name__
        name = f"{Path(__file__).resolve().relative_to(checkout)}::{this_test}"
        proc = subprocess.run(
            # pytest's script, not `python -m pytest` (which puts the repository root, and so the source tree,
            # first on sys.path); the runtime-only run keeps its empty pythonpath
            [str(Path(sys.executable).with_name("pytest")), "-q", "-p", "no:cacheprovider", name]
            + (["-o", "pythonpath="] if os.environ.get("GEONET_RUNTIME_ONLY") else []),
            cwd=checkout,
            env={**os.environ, "GEONET_ISOLATED_TEST": "1"},
            capture_output=True,
            text=True,
            timeout=300,
        )
        assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
        return
    from geonet_infer.batch import BatchConfig, WorkUnit, local

    out = tmp_path / "out"
    out.mkdir()
    unit = WorkUnit(0, "s1", str(tmp_path / "in"))

    def sequence(unit, config, predictor, on_frame, options):  # a sequence stopped while it writes
        folder = out / unit.name
        (folder / "depth").mkdir(parents=True)
        (folder / ".geonet-batch").write_text("{}\n")
        (folder / ".geonet-predict").write_text(json.dumps({"files": ["depth/000000.npy", "depth/000001.npy"]}))
        (folder / "depth" / "000000.npy").write_bytes(b"written")
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(5)  # the handler raises here
        return {"status": "done"}

    real_discard = local.discard

    def discard(folder):
        os.kill(os.getpid(), signal.SIGTERM)  # the job's own SIGTERM, during the clean-up
        real_discard(folder)

    def exit_(code):
        raise _Exited(code)

    monkeypatch.setattr(local, "run_sequence", sequence)
    monkeypatch.setattr(local, "discard", discard)
    monkeypatch.setattr(local.os, "_exit", exit_)
    monkeypatch.setattr(local, "_WORKER", {})
    local._WORKER.update(config=BatchConfig(out_dir=str(out)), options={}, started=[0], busy=None, predictor=object())
    previous = signal.signal(signal.SIGTERM, local._on_sigterm)
    try:
        with pytest.raises(_Exited) as exited:
            local._work(unit)
    finally:
        signal.signal(signal.SIGTERM, previous)
    assert exited.value.args == (143,)
    assert os.listdir(out) == []  # the unfinished sequence is gone, markers and all


def test_the_summary_counts_a_sequence_finished_after_the_stop_with_its_frames(tmp_path, monkeypatch):
    """Case 6: a sequence completes on disk (its .done written) after the job stopped listening; the summary
    counts it as done, with its frames and its row (it said done 1, frames 0, per_sequence [])."""
    from geonet_infer.batch import run as batch_run
    from geonet_infer.batch import run_sequence
    from geonet_infer.core.predictor import load

    class LateRunner:  # the job is stopped right after the sequence finished, before its result came back
        name, workers, threads, limits, address = "late", 1, 1, [], None

        @classmethod
        def start(cls, config, options, n_units, workers, threads, *, manifest, address, log):
            runner = cls()
            runner.config, runner.options = config, options
            return runner

        def results(self, units):
            run_sequence(units[0], self.config, load(threads=1), None, self.options)
            raise KeyboardInterrupt
            yield  # a generator, as the runners' results are

        def live_frames(self):
            return 0

        def close(self):
            pass

    monkeypatch.setitem(batch_run.RUNNERS, "late", LateRunner)
    (seq,) = make_sequences(tmp_path / "in", ["s1"], 3)
    out = tmp_path / "out"
    with pytest.raises(KeyboardInterrupt):
        batch_run.run_batch([seq], out, runner="late", tasks=("depth",), progress=False, vis=False)
    assert (out / "s1" / ".done").is_file()
    summary = json.loads((out / "summary.json").read_text())
    assert summary["interrupted"] is True and summary["sequences"]["done"] == 1
    assert summary["frames"] == 3 == len(list((out / "s1" / "depth").glob("*.npy")))
    assert [(r["sequence"], r["status"], r["frames"]) for r in summary["per_sequence"]] == [("s1", "done", 3)]


def _progress(out: Path) -> int:
    return len(list(out.glob("s[0-9]/depth/*.npy")))


@pytest.mark.parametrize("after, again", [(1, 0.1), (4, 0.0), (14, None)])
def test_sigterm_to_the_group_at_any_moment_leaves_a_state_resume_accepts(tmp_path, after, again):
    """Case 6: SIGTERM to the job's process group (as `timeout` and schedulers send it) when ``after`` frames
    are written, and ``again`` seconds later once more: exit 130; no sequence that had not started completes;
    the summary agrees with the folders; every unfinished folder is gone; --resume finishes the job."""
    seqs = make_sequences(tmp_path / "in", ["s1", "s2", "s3"], 12)
    out = tmp_path / "out"
    argv = [*CLI, "batch", *map(str, seqs), "--out", str(out), *DEPTH, "--no-vis", "--workers", "2"]
    proc = subprocess.Popen(argv, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True)
    try:
        deadline = time.monotonic() + 120
        while _progress(out) < after and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.01)
        assert proc.poll() is None, "the job ended before the signal"
        os.killpg(proc.pid, signal.SIGTERM)
        started = {p.name for p in out.glob("s[0-9]")}
        if again is not None:
            time.sleep(again)
            os.killpg(proc.pid, signal.SIGTERM)
        _, stderr = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
    assert proc.returncode == 130, stderr[-2000:]
    done = {p.parent.name for p in out.glob("s[0-9]/.done")}
    assert done <= started, f"{sorted(done - started)} started after the SIGTERM"
    assert {p.name for p in out.glob("s[0-9]")} == done  # unfinished folders removed, markers and all
    summary = json.loads((out / "summary.json").read_text())
    assert summary["sequences"]["done"] == len(done)
    assert {r["sequence"] for r in summary["per_sequence"] if r["status"] == "done"} == done
    assert summary["frames"] == sum(json.loads((out / s / ".done").read_text())["frames"] for s in done)
    resume = subprocess.run([*argv, "--resume"], cwd=REPO, capture_output=True, text=True, timeout=180)
    assert resume.returncode == 0, resume.stderr[-2000:]
    assert {p.parent.name for p in out.glob("s[0-9]/.done")} == {"s1", "s2", "s3"}

"""`geonet-infer batch`: same outputs as `predict`, nothing lost on SIGKILL / Ctrl-C, failures recorded.

Inputs are short sequences copied from the bundled sample (its calib.txt via --calib).
Reference outputs come from `geonet-infer predict` on each sequence, with the same
--batch-size (onnxruntime results can depend on the batch's composition). Every output
file is compared byte for byte, except the summary.json files (they hold timings) and
batch's own ``.done`` markers. No torch.
"""

from __future__ import annotations

import importlib.util
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

import geonet_infer
from geonet_infer.batch import FAILURES_NAME, MARKER_NAME, OWNER_NAME, plan_units, plan_workers
from geonet_infer.cli import main
from geonet_infer.output.layout import OUTPUT_MARKER
from tests.conftest import GEONET_CLI

PKG = Path(geonet_infer.__file__).resolve().parent
SAMPLE = PKG / "samples" / "synth_seq"
SAMPLE_CALIB = SAMPLE / "calib.txt"
FRAMES = sorted((SAMPLE / "image").glob("*.png"))
CLI = GEONET_CLI


def on_ci() -> bool:
    return os.environ.get("CI", "").strip().lower() not in ("", "0", "false", "no")


def make_sequences(root: Path, names, n_frames: int) -> list[Path]:
    out = []
    for name in names:
        folder = root / name
        folder.mkdir(parents=True)
        for f in FRAMES[:n_frames]:
            shutil.copyfile(f, folder / f.name)
        out.append(folder)
    return out


def tree(folder: Path, skip=("summary.json", MARKER_NAME, OWNER_NAME, OUTPUT_MARKER)) -> dict[str, bytes]:
    """Relative path -> bytes of every file under ``folder`` whose name is not in ``skip``."""
    return {
        str(p.relative_to(folder)): p.read_bytes()
        for p in sorted(folder.rglob("*"))
        if p.is_file() and p.name not in skip
    }


def done_record(folder: Path) -> dict:
    """A sequence's .done without the hash of its summary.json (which holds timings)."""
    record = json.loads((folder / MARKER_NAME).read_text())
    record["outputs"].pop("summary.json")
    return record


def assert_complete_and_clean(out: Path, names) -> None:
    """Every sequence has its .done; no temporary file anywhere (only .done, the ownership markers (batch's,
    and each sequence's list of its files) and the job's .lock are hidden)."""
    for name in names:
        assert (out / name / MARKER_NAME).is_file(), name
    hidden = [
        p for p in out.rglob(".*") if p.name not in (MARKER_NAME, OWNER_NAME, OUTPUT_MARKER) and p != out / ".lock"
    ]
    assert hidden == []


def cli(capfd, *argv) -> tuple[int, str, str]:
    rc = main([str(a) for a in argv])
    out, err = capfd.readouterr()
    return rc, out, err


@pytest.fixture(scope="module")
def three(tmp_path_factory):
    """3 sequences of 4 frames and `predict`'s output for each."""
    root = tmp_path_factory.mktemp("batch")
    seqs = make_sequences(root / "in", ["seq_a", "seq_b", "seq_c"], 4)
    for seq in seqs:
        assert (
            main(
                [
                    "predict",
                    str(seq),
                    "--out",
                    str(root / "predict" / seq.name),
                    "--calib",
                    str(SAMPLE_CALIB),
                    "--no-progress",
                    "--batch-size",
                    "4",
                ]
            )
            == 0
        )
    return root, seqs


def assert_same_as_predict(out: Path, root: Path, seqs) -> None:
    for seq in seqs:
        expected = tree(root / "predict" / seq.name)
        got = tree(out / seq.name)
        assert sorted(got) == sorted(expected), seq.name
        assert [k for k in expected if got[k] != expected[k]] == [], seq.name


# ----------------------------------------------------------------------------- same outputs as predict
def test_local_engine_matches_predict(three, tmp_path, capfd):
    root, seqs = three
    out = tmp_path / "out"
    rc, stdout, stderr = cli(
        capfd,
        "batch",
        *seqs,
        "--out",
        out,
        "--calib",
        SAMPLE_CALIB,
        "--no-progress",
        "--workers",
        2,
        "--threads-per-worker",
        1,
        "--batch-size",
        4,
    )
    assert rc == 0, stderr
    assert_same_as_predict(out, root, seqs)
    assert_complete_and_clean(out, [s.name for s in seqs])
    assert (out / FAILURES_NAME).read_text() == ""
    summary = json.loads((out / "summary.json").read_text())
    assert summary["sequences"] == {"total": 3, "done": 3, "failed": 0, "skipped": 0, "not_run": 0}
    assert (summary["frames"], summary["engine"], summary["workers"], summary["threads_per_worker"]) == (
        12,
        "local",
        2,
        1,
    )
    assert summary["exit_code"] == 0 and "3 sequences done" in stdout
    for row, seq in zip(summary["per_sequence"], seqs):  # each sequence's output check, summed up as predict's
        check = json.loads((root / "predict" / seq.name / "summary.json").read_text())["check"]
        assert row["check"] == {k: v for k, v in check.items() if k not in ("method", "per_pair")}, seq.name
        assert row["check"]["pairs"] == 3


def require_ray() -> None:
    """Skip without ray, except on CI (env var CI set), where a missing ray is a failure.

    The runtime-only venv (scripts/test_runtime.sh) installs the runtime without extras by design;
    the source-tree suite, which installs the ray extra, runs these tests on CI."""
    if importlib.util.find_spec("ray") is None:
        if on_ci() and not os.environ.get("GEONET_RUNTIME_ONLY"):
            pytest.fail("ray is not installed and CI is set: install the extra (pip install '.[ray]')", pytrace=False)
        pytest.skip("ray not installed (pip install 'geonet-infer[ray]')")


# Starts a Ray cluster (as a standing cluster would be), runs the CLI against it, stops it.
JOIN_SCRIPT = """
import subprocess, sys, ray
ray.init(address="local", num_cpus=2, include_dashboard=False, logging_level="ERROR")
try:
    sys.exit(subprocess.run(sys.argv[1:] + ["--ray-address", ray.get_runtime_context().gcs_address]).returncode)
finally:
    ray.shutdown()
"""


@pytest.mark.parametrize("cluster", ["own", "joined"])
def test_ray_engine_matches_predict(three, tmp_path, cluster):
    require_ray()
    root, seqs = three
    out = tmp_path / "out"
    argv = [
        *CLI,
        "batch",
        *map(str, seqs),
        "--out",
        str(out),
        "--calib",
        str(SAMPLE_CALIB),
        "--runner",
        "ray",
        "--no-progress",
        "--batch-size",
        "4",
    ]
    if cluster == "joined":
        argv = [sys.executable, "-c", JOIN_SCRIPT, *argv]
    # A subprocess: Ray's cluster, logging and signal handlers stay out of the test process.
    proc = subprocess.run(argv, capture_output=True, text=True, timeout=240)
    assert proc.returncode == 0, proc.stderr
    assert_same_as_predict(out, root, seqs)
    assert_complete_and_clean(out, [s.name for s in seqs])
    summary = json.loads((out / "summary.json").read_text())
    assert summary["engine"] == "ray" and summary["sequences"]["done"] == 3
    assert (summary["ray_address"] is None) == (cluster == "own")
    up = "Ray local cluster up in " if cluster == "own" else "Ray joined in "
    assert proc.stderr.count(up) == 1 and "'core_worker.cc ... constructor arguments' error line is harmless" in (
        proc.stderr
    )
    # actors x threads fit the cluster's CPUs (else Ray Data would wait forever)
    assert summary["workers"] * summary["threads_per_worker"] <= (summary["usable_cpus"] if cluster == "own" else 2)


# ----------------------------------------------------------------------------- nothing lost
def _children(pid: int) -> list[int]:
    kids = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            kids.append(int(stat.parent.name))
    return kids


def _cmdline(pid: int) -> bytes:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return b""


def _wait_for(predicate, timeout: float):
    """The predicate's first true value within ``timeout`` s, else False."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if value := predicate():
            return value
        time.sleep(0.05)
    return False


def _bytes_written(pid: int) -> int:
    """Bytes the process has passed to write() so far (/proc/PID/io wchar); 0 once it is gone."""
    try:
        text = Path(f"/proc/{pid}/io").read_text()
    except OSError:
        return 0
    return next(int(line.split()[1]) for line in text.splitlines() if line.startswith("wchar:"))


def _alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


@pytest.mark.parametrize("how", ["SIGKILL", "SIGINT"])
def test_killed_job_resumes_to_identical_outputs(tmp_path, capfd, how):
    names = ["k1", "k2", "k3", "k4", "k5", "k6"]  # enough that the signal lands before the last one ends
    seqs = make_sequences(tmp_path / "in", names, 12)
    common = ["--calib", SAMPLE_CALIB, "--no-progress", "--batch-size", "4", "--workers", "1"]
    ref = tmp_path / "ref"
    assert cli(capfd, "batch", *seqs, "--out", ref, *common)[0] == 0

    out = tmp_path / "out"
    proc = subprocess.Popen(
        [*CLI, "batch", *map(str, seqs), "--out", str(out), *map(str, common)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        # the job gets SIGINT with its default action, as from a user's terminal: in two CI rehearsals
        # (the whole file, started in the background) the SIGINT'd job ran to its end; an ignored SIGINT
        # inherited from the suite's process is the likely cause (not pinned down)
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    try:
        assert _wait_for(lambda: any(out.glob(f"*/{MARKER_NAME}")), 120), "no sequence finished"
        workers = _children(proc.pid) if sys.platform.startswith("linux") else []
        proc.send_signal(getattr(signal, how))
        _, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    done = [n for n in names if (out / n / MARKER_NAME).exists()]
    assert 1 <= len(done) < len(names), "the kill came too late to test anything"
    if how == "SIGINT":
        assert proc.returncode == 130 and "interrupted" in stderr
        assert json.loads((out / "summary.json").read_text())["interrupted"] is True
        assert [p for p in out.iterdir() if p.is_dir() and p.name not in done] == []  # unfinished ones removed
    else:
        assert proc.returncode == -signal.SIGKILL
        # the workers die with the job: nothing keeps writing into OUT while --resume runs
        assert _wait_for(lambda: not any(_alive(w) for w in workers), 30), "orphan workers"
        # and a partial folder (as after a power cut) is redone: plant one with a stray temp file
        # (with batch's ownership marker and the list of the files its run may write, both written
        # before anything else)
        partial = out / names[-1]
        (partial / "depth").mkdir(parents=True, exist_ok=True)
        (partial / OWNER_NAME).write_text("{}\n")
        listed = ["depth/000000.npy", "depth/000001.npy"]
        (partial / OUTPUT_MARKER).write_text(json.dumps({"files": listed}) + "\n")
        (partial / "depth" / "000000.npy").write_bytes(b"half")
        (partial / "depth" / ".000001.abc123_x.npy").write_bytes(b"tmp")  # mkstemp's 8 random characters

    rc, stdout, stderr = cli(capfd, "batch", *seqs, "--out", out, *common, "--resume")
    assert rc == 0, stderr
    assert f"{len(done)} skipped" in stdout
    assert_complete_and_clean(out, names)
    for name in names:
        assert tree(out / name) == tree(ref / name), name
        assert done_record(out / name) == done_record(ref / name), name
    summary = json.loads((out / "summary.json").read_text())
    assert summary["sequences"]["skipped"] == len(done) and summary["sequences"]["done"] == len(names) - len(done)


# ----------------------------------------------------------------------------- failures
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="finds the workers through /proc")
def test_a_worker_that_dies_fails_its_sequence_and_the_rest_completes(tmp_path):
    names = ["w1", "w2", "w3"]
    seqs = make_sequences(tmp_path / "in", names, 12)
    out = tmp_path / "out"
    proc = subprocess.Popen(
        [
            *CLI,
            "batch",
            *map(str, seqs),
            "--out",
            str(out),
            "--calib",
            str(SAMPLE_CALIB),
            "--no-progress",
            "--workers",
            "2",
            "--threads-per-worker",
            "1",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:

        def writing_worker():  # the worker writing a sequence (as an OOM kill would find it)
            started = [d for d in out.glob("w*") if not (d / MARKER_NAME).exists() and any(d.rglob("*.npy"))]
            workers = [w for w in _children(proc.pid) if b"spawn_main" in _cmdline(w)]
            # The one that has written the most: the other may still be loading the model, and killing an
            # idle worker fails no sequence (its pool is rebuilt, the run exits 0).
            return bool(started) and len(workers) == 2 and max(workers, key=_bytes_written)

        victim = _wait_for(writing_worker, 120)
        assert victim, "no worker got busy"
        os.kill(victim, signal.SIGKILL)
        stdout, stderr = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 1, stderr
    records = [json.loads(line) for line in (out / FAILURES_NAME).read_text().splitlines()]
    assert len(records) == 1 and records[0]["frame"] is None and "worker process died" in records[0]["reason"]
    dead = records[0]["sequence"]
    assert not (out / dead).exists()  # its partial folder is removed
    assert_complete_and_clean(out, [n for n in names if n != dead])


def test_corrupt_inputs_are_recorded_and_the_rest_completes(tmp_path, capfd):
    good, bad_frame = make_sequences(tmp_path / "in", ["good", "bad_frame"], 4)
    (bad_frame / FRAMES[1].name).write_bytes(FRAMES[1].read_bytes()[:200])  # truncated PNG
    video = tmp_path / "in" / "noise.mp4"
    video.write_bytes(os.urandom(4096))
    drive = tmp_path / "in" / "2011_01_01_drive_0001_sync"
    make_sequences(drive / "image_02", ["data"], 3)
    (drive / "calib_cam_to_cam.txt").write_text("this is not a calibration\n")
    listing = tmp_path / "in" / "inputs.txt"  # relative to the list's folder, a comment, a blank line
    listing.write_text("# sequences\ngood\nnoise.mp4\n\nbad_frame\n2011_01_01_drive_0001_sync\n")

    out = tmp_path / "out"
    rc, stdout, stderr = cli(capfd, "batch", listing, "--out", out, "--tasks", "depth,pose", "--no-progress")
    assert rc == 1, stderr
    records = [json.loads(line) for line in (out / FAILURES_NAME).read_text().splitlines()]
    by_seq = {(r["sequence"], r["frame"]): r["reason"] for r in records}
    assert set(by_seq) == {("noise", None), ("bad_frame", FRAMES[1].stem), ("2011_01_01_drive_0001_sync", None)}
    assert "noise.mp4" in by_seq[("noise", None)]
    assert "calib_cam_to_cam.txt" in by_seq[("2011_01_01_drive_0001_sync", None)]
    assert_complete_and_clean(out, ["good", "bad_frame"])
    assert not (out / "noise").exists() and not (out / "2011_01_01_drive_0001_sync").exists()
    assert len(list((out / "bad_frame" / "depth").glob("*.npy"))) == 3
    summary = json.loads((out / "summary.json").read_text())
    assert summary["sequences"] == {"total": 4, "done": 2, "failed": 2, "skipped": 0, "not_run": 0}
    assert summary["frames_failed"] == 1 and summary["exit_code"] == 1

    # --resume: the complete ones are skipped, their bad frame stays on record; the failed ones are retried
    rc, stdout, stderr = cli(
        capfd, "batch", listing, "--out", out, "--tasks", "depth,pose", "--no-progress", "--resume"
    )
    assert rc == 1 and "2 skipped" in stdout
    again = {(r["sequence"], r["frame"]) for r in map(json.loads, (out / FAILURES_NAME).read_text().splitlines())}
    assert again == set(by_seq)


def test_ray_missing_is_a_usage_error(tmp_path, capfd, monkeypatch):
    (seq,) = make_sequences(tmp_path / "in", ["s"], 2)
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` raises ImportError
    rc, _, stderr = cli(
        capfd, "batch", seq, "--out", tmp_path / "out", "--runner", "ray", "--tasks", "depth", "--no-progress"
    )
    assert rc == 2 and len(stderr.strip().splitlines()) == 1
    assert "pip install 'geonet-infer[ray]'" in stderr


@pytest.mark.parametrize(
    "case",
    [
        "missing_input",
        "unknown_model",
        "resume_other_options",
        "address_without_ray",
        "empty_list",
        "unreachable_ray_cluster",
    ],
)
def test_bad_usage_exits_2_with_one_line(tmp_path, capfd, monkeypatch, case):
    (seq,) = make_sequences(tmp_path / "in", ["s"], 2)
    out = tmp_path / "out"
    argv = ["batch", seq, "--out", out, "--no-progress", "--tasks", "depth"]
    if case == "missing_input":
        argv[1:2] = [seq, tmp_path / "nope"]
    elif case == "unknown_model":
        argv += ["--model", "no_such_model"]
    elif case == "resume_other_options":
        assert cli(capfd, *argv)[0] == 0
        argv = [a if a != "depth" else "depth,pose" for a in argv] + ["--resume"]
    elif case == "address_without_ray":
        argv += ["--ray-address", "auto"]
    elif case == "unreachable_ray_cluster":  # fails fast (ray.init alone would retry for minutes) ...
        argv += ["--runner", "ray", "--ray-address", "127.0.0.1:1"]
        monkeypatch.setitem(sys.modules, "ray", None)  # ... and before anything imports ray
    elif case == "empty_list":
        (tmp_path / "list.txt").write_text("# nothing\n")
        argv[1] = tmp_path / "list.txt"
    rc, _, stderr = cli(capfd, *argv)
    assert rc == 2
    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("geonet-infer batch: error:"), stderr
    if case == "unreachable_ray_cluster":
        assert "cannot reach the Ray cluster at 127.0.0.1:1" in lines[0], lines[0]


# ----------------------------------------------------------------------------- planning
def test_sequence_names_are_unique_and_deterministic(tmp_path):
    for d in ("x/cam", "y/cam", "z/x/cam", "solo"):
        (tmp_path / d).mkdir(parents=True)
    (tmp_path / "clip.mp4").write_bytes(b"")
    paths = [
        tmp_path / "x/cam",
        tmp_path / "y/cam",
        tmp_path / "z/x/cam",
        tmp_path / "solo",
        tmp_path / "solo/",
        tmp_path / "clip.mp4",
    ]
    names = [u.name for u in plan_units(paths)]
    assert names == ["cam__x", "cam__y", "cam__x__2", "solo", "clip"]  # the same input twice runs once
    assert [u.name for u in plan_units(paths)] == names


def test_default_workers_times_threads_fit_the_cpus():
    assert plan_workers(10, None, None, cpus=2) == (2, 1)
    assert plan_workers(1, None, None, cpus=8) == (1, 8)  # one sequence: one worker, all threads
    assert plan_workers(10, None, 2, cpus=8) == (4, 2)
    assert plan_workers(10, 3, None, cpus=8) == (3, 2)
    assert plan_workers(2, 4, 1, cpus=2) == (2, 1)  # never more workers than sequences
    for n in (1, 3, 16):
        for cpus in (1, 2, 3, 16):
            w, t = plan_workers(n, None, None, cpus=cpus)
            assert w * t <= cpus


def test_ray_pool_never_asks_for_more_cpus_than_the_nodes_have():
    from geonet_infer.batch.ray import size_pool  # importable without ray (ray is imported lazily)

    assert size_pool([2], 3, None, None)[:2] == (2, 1)
    assert size_pool([2], 3, 4, 1)[:2] == (2, 1)  # asked for 4 actors on 2 CPUs
    assert size_pool([2], 3, None, 4)[:2] == (1, 2)  # threads capped at the node's CPUs
    assert size_pool([4, 4], 10, None, 3)[:2] == (2, 3)  # per node: 4 // 3 = 1 actor each
    assert size_pool([2], 3, 4, 1)[2] is not None  # and says so


def test_engine_is_the_deprecated_name_of_runner(tmp_path, capfd):
    """`--engine` (0.x) still works for one release, with a note; `--runner` is the flag."""
    seq = tmp_path / "seq"
    shutil.copytree(SAMPLE / "image", seq)
    rc, _, stderr = cli(
        capfd,
        "batch",
        seq,
        "--out",
        tmp_path / "out",
        "--calib",
        SAMPLE_CALIB,
        "--engine",
        "local",
        "--tasks",
        "depth",
        "--no-progress",
        "--no-vis",
    )
    assert rc == 0, stderr
    assert "--engine is deprecated, use --runner" in stderr
    assert json.loads((tmp_path / "out" / "summary.json").read_text())["engine"] == "local"


def test_run_batch_runs_flow_for_an_input_without_intrinsics_with_the_assumed_ones(tmp_path):
    """The needs-K rule (geonet_infer.core.tasks) is applied once, by run_batch: one note names the inputs
    without a calibration, and each sequence's summary records the assumed intrinsics."""
    from geonet_infer.batch import run_batch
    from geonet_infer.io.camera import ASSUMED_FOCAL_PER_WIDTH

    frames = tmp_path / "frames"
    frames.mkdir()
    for f in FRAMES[:3]:
        shutil.copy(f, frames / f.name)
    notes: list[str] = []
    run_batch([frames], tmp_path / "out", tasks=("flow",), progress=False, log=notes.append)
    assert any("no calibration; intrinsics assumed" in n and str(frames) in n for n in notes), notes
    camera = json.loads((tmp_path / "out" / "frames" / "summary.json").read_text())["camera"]
    assert camera["origin"] == "assumed" and camera["K"][0][0] == pytest.approx(
        ASSUMED_FOCAL_PER_WIDTH * camera["size"][0]
    )
    run_batch([frames], tmp_path / "dis", tasks=("flow",), flow_method="dis", progress=False, log=lambda m: None)

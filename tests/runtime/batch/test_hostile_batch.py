"""`geonet-infer batch` used carelessly or hostilely (issue 27): nothing lost, nothing silently wrong.

Each test reproduces one way the batch job used to lose data or misreport, on tiny inputs
(copies of the bundled sample's 128x416 frames; depth only unless flow is the point).
"""

from __future__ import annotations

import hashlib
import json
import resource
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest

import geonet_infer
from geonet_infer import batch as batch_mod
from geonet_infer.batch import MARKER_NAME
from geonet_infer.batch import local as batch_local
from geonet_infer.batch import run as batch_run
from geonet_infer.models.manifest import load_manifest
from tests.runtime.batch.test_batch import CLI, FRAMES, SAMPLE_CALIB, _wait_for, cli, make_sequences, require_ray

DEPTH = ["--tasks", "depth", "--no-progress", "--no-vis"]
OWNER_NAME = ".geonet-batch"  # the ownership marker batch writes in each folder it makes
FILES_MARKER = ".geonet-predict"  # the list of the files a sequence's run may write (what a re-run removes)
KNOWN_HIDDEN = {MARKER_NAME, OWNER_NAME, FILES_MARKER, ".lock"}


def digest(folder: Path) -> dict[str, str]:
    """Relative path -> sha256 of every file under ``folder`` (an independent record of what was there)."""
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


def leftovers(out: Path) -> list[Path]:
    """Temporary files: hidden names batch does not own, or ``*.tmp``."""
    return [
        p
        for p in out.rglob("*")
        if p.is_file() and (p.name.endswith(".tmp") or p.name.startswith(".")) and p.name not in KNOWN_HIDDEN
    ]


def one_error_line(stderr: str) -> str:
    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("geonet-infer batch: error:"), stderr
    return lines[0]


# ----------------------------------------------------------------------------- 1. never delete what batch did not make
@pytest.mark.parametrize("where", ["parent", "same", "inside", "kitti_date"])
def test_out_overlapping_an_input_is_refused_before_any_work(tmp_path, capfd, where):
    if where == "kitti_date":
        date = tmp_path / "2011_09_26"
        (seq,) = make_sequences(date / "2011_09_26_drive_0001_sync" / "image_02", ["data"], 3)
        seq = seq.parent.parent  # the drive
        out = date
    else:
        (seq,) = make_sequences(tmp_path, ["seqA"], 3)
        out = {"parent": tmp_path, "same": seq, "inside": seq / "out"}[where]
    before = digest(tmp_path)
    rc, _, stderr = cli(capfd, "batch", seq, "--out", out, *DEPTH)
    assert rc == 2
    assert "input" in one_error_line(stderr)
    assert digest(tmp_path) == before  # nothing deleted, nothing written


def test_a_folder_batch_did_not_make_is_refused(tmp_path, capfd):
    (seq,) = make_sequences(tmp_path / "in", ["seqA"], 3)
    out = tmp_path / "mine"
    (out / "seqA").mkdir(parents=True)
    (out / "seqA" / "notes.txt").write_text("my notes\n")
    (out / "notes.txt").write_text("more notes\n")
    rc, _, stderr = cli(capfd, "batch", seq, "--out", out, *DEPTH)
    assert rc == 2 and "--out" in one_error_line(stderr)
    assert sorted(map(str, digest(out))) == ["notes.txt", "seqA/notes.txt"]


def test_a_sequence_folder_batch_did_not_make_is_left_alone(tmp_path, capfd):
    seq_a, seq_b = make_sequences(tmp_path / "in", ["seqA", "seqB"], 3)
    out = tmp_path / "out"
    assert cli(capfd, "batch", seq_b, "--out", out, *DEPTH)[0] == 0  # OUT is batch's now
    (out / "seqA").mkdir()
    (out / "seqA" / "notes.txt").write_text("my notes\n")
    rc, _, stderr = cli(capfd, "batch", seq_a, seq_b, "--out", out, *DEPTH)
    assert rc == 2 and "seqA" in one_error_line(stderr)
    assert (out / "seqA" / "notes.txt").read_text() == "my notes\n"
    # and an empty folder (nothing to lose) is fine
    shutil.rmtree(out / "seqA")
    (out / "seqA").mkdir()
    rc, _, stderr = cli(capfd, "batch", seq_a, "--out", out, *DEPTH)
    assert rc == 0, stderr
    assert (out / "seqA" / MARKER_NAME).is_file()


# ----------------------------------------------------------------------------- 2. resume verifies, not trusts
def test_resume_redoes_a_sequence_whose_outputs_changed(tmp_path, capfd):
    seqs = make_sequences(tmp_path / "in", ["s1", "s2", "s3"], 3)
    out = tmp_path / "out"
    assert cli(capfd, "batch", *seqs, "--out", out, *DEPTH)[0] == 0
    first = {s.name: digest(out / s.name) for s in seqs}
    (out / "s1" / "depth" / f"{FRAMES[1].stem}.npy").unlink()
    npy = out / "s2" / "depth" / f"{FRAMES[2].stem}.npy"
    npy.write_bytes(npy.read_bytes()[:100])
    rc, stdout, stderr = cli(capfd, "batch", *seqs, "--out", out, *DEPTH, "--resume")
    assert rc == 0, stderr
    assert "1 skipped" in stdout and "2 redone" in stdout
    for s in seqs:
        now = digest(out / s.name)
        assert {k: v for k, v in now.items() if not k.endswith("summary.json") and k != MARKER_NAME} == {
            k: v for k, v in first[s.name].items() if not k.endswith("summary.json") and k != MARKER_NAME
        }, s.name
    summary = json.loads((out / "summary.json").read_text())
    redone = {r["sequence"]: r["reason"] for r in summary["redone"]}
    assert sorted(redone) == ["s1", "s2"]
    assert f"{FRAMES[1].stem}.npy" in redone["s1"] and f"{FRAMES[2].stem}.npy" in redone["s2"]
    assert summary["sequences"]["skipped"] == 1 and summary["sequences"]["done"] == 2


def test_resume_redoes_a_sequence_whose_input_frames_changed(tmp_path, capfd):
    (seq,) = make_sequences(tmp_path / "in", ["s1"], 3)
    out = tmp_path / "out"
    assert cli(capfd, "batch", seq, "--out", out, *DEPTH)[0] == 0
    old = (out / "s1" / "depth" / f"{FRAMES[0].stem}.npy").read_bytes()
    shutil.copyfile(FRAMES[6], seq / FRAMES[0].name)  # another picture under the same name
    rc, stdout, stderr = cli(capfd, "batch", seq, "--out", out, *DEPTH, "--resume")
    assert rc == 0, stderr
    assert "0 skipped" in stdout and "1 redone" in stdout
    assert FRAMES[0].name in json.loads((out / "summary.json").read_text())["redone"][0]["reason"]
    assert (out / "s1" / "depth" / f"{FRAMES[0].stem}.npy").read_bytes() != old
    # a resume right after finds everything as recorded
    rc, stdout, _ = cli(capfd, "batch", seq, "--out", out, *DEPTH, "--resume")
    assert rc == 0 and "1 skipped" in stdout and "0 redone" in stdout


# ----------------------------------------------------------------------------- 3. workers capped
def test_workers_are_capped_by_cpus_and_memory():
    per = 300 * 1024**2
    assert batch_mod.cap_workers(16, 1, cpus=2, mem_available=64 * 1024**3, per_worker=per)[:2] == (2, 1)
    assert batch_mod.cap_workers(None, 8, cpus=2, mem_available=64 * 1024**3, per_worker=per)[:2] == (None, 2)
    w, t, notes = batch_mod.cap_workers(4, 1, cpus=8, mem_available=2 * per + per // 2, per_worker=per)
    assert (w, t) == (2, 1) and "memory" in notes[0]
    assert (
        batch_mod.cap_workers(None, None, cpus=8, mem_available=per, per_worker=per)[0] == 1
    )  # the default is capped too
    assert batch_mod.cap_workers(3, 2, cpus=8, mem_available=None, per_worker=per) == (
        3,
        2,
        [],
    )  # unknown memory: no cap
    assert batch_mod.cap_workers(16, 1, cpus=16, mem_available=64 * 1024**3, per_worker=per) == (16, 1, [])
    # the estimate grows with the model's graphs
    model = Path(geonet_infer.__file__).parent / "models" / "small_synth"
    assert (
        batch_mod.worker_memory_bytes(load_manifest(model), "fp32")
        > batch_mod.WORKER_BASE_BYTES + (model / "depthnet.onnx").stat().st_size
    )


def test_too_many_workers_warns_and_records_the_cap(tmp_path, capfd, monkeypatch):
    seqs = make_sequences(tmp_path / "in", ["s1", "s2"], 2)
    for module in (batch_local, batch_run):  # the runner's sizing and the summary's record
        monkeypatch.setattr(module, "usable_cpus", lambda: 1)
    out = tmp_path / "out"
    rc, _, stderr = cli(capfd, "batch", *seqs, "--out", out, *DEPTH, "--workers", 16)
    assert rc == 0, stderr
    warnings = [line for line in stderr.splitlines() if "--workers 16" in line]
    assert len(warnings) == 1 and "1 usable CPU" in warnings[0], stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["workers"] == 1 and summary["workers_requested"] == 16 and summary["limits"]


@pytest.mark.parametrize("flag", ["--workers", "--threads-per-worker"])
def test_absurd_worker_counts_are_refused(tmp_path, capfd, flag):
    (seq,) = make_sequences(tmp_path / "in", ["s1"], 2)
    rc, _, stderr = cli(capfd, "batch", seq, "--out", tmp_path / "out", *DEPTH, flag, 5000)
    assert rc == 2 and "5000" in one_error_line(stderr)
    assert not (tmp_path / "out").exists()


# ----------------------------------------------------------------------------- 4, 5. SIGTERM
def _sigterm_run(tmp_path, engine: str, first_output_timeout: float):
    names = ["t1", "t2", "t3", "t4"]
    seqs = make_sequences(tmp_path / "in", names, 12)
    out = tmp_path / "out"
    argv = [*CLI, "batch", *map(str, seqs), "--out", str(out), "--tasks", "depth", "--no-progress"]
    argv += ["--workers", "1", "--threads-per-worker", "1", "--batch-size", "1", "--runner", engine]
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        started = lambda: any(out.glob("t*/depth/*.npy"))  # noqa: E731
        assert _wait_for(started, first_output_timeout), "no output appeared"
        proc.send_signal(signal.SIGTERM)
        _, stderr = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 130, stderr
    # Ray's C++ core prints a notice of its own on every run; ours is one line, and no stack dump
    # (notes, such as Ray's start-up time, are not about the stop)
    ours = [line for line in stderr.splitlines() if "geonet-infer" in line and "batch: note:" not in line]
    assert ours == ["geonet-infer batch: interrupted"]
    assert "SIGTERM received" not in stderr and "Traceback" not in stderr, stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["interrupted"] is True and summary["exit_code"] == 130
    assert leftovers(out) == []
    done = [n for n in names if (out / n / MARKER_NAME).is_file()]
    assert [p.name for p in out.iterdir() if p.is_dir() and p.name not in done] == []  # unfinished ones removed
    assert summary["sequences"]["done"] == len(done) < len(names)
    return out, seqs, argv, done


def test_sigterm_stops_a_local_job_with_a_summary_and_130(tmp_path):
    _sigterm_run(tmp_path, "local", 120)


def test_sigterm_stops_a_ray_job_with_a_summary_and_130_and_resume_with_ray_finishes_it(tmp_path):
    """Stopped mid-way (the pending sequences' folders discarded), then --resume --runner ray: the done
    ones are skipped, the others predicted, each equal to a local job's outputs of the same sequence."""
    require_ray()
    out, seqs, argv, done = _sigterm_run(tmp_path, "ray", 240)
    proc = subprocess.run([*argv, "--resume"], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert f"{len(seqs) - len(done)} sequences done, 0 failed, {len(done)} skipped" in proc.stdout, proc.stdout
    assert leftovers(out) == []
    local = tmp_path / "local"
    assert cli_run([*argv[: argv.index("--out")], "--out", str(local), "--tasks", "depth", "--no-progress"]) == 0
    for seq in seqs:
        ours = sorted((out / seq.name / "depth").glob("*.npy"))
        assert [p.name for p in ours] == [p.name for p in sorted((local / seq.name / "depth").glob("*.npy"))]
        assert all(p.read_bytes() == (local / seq.name / "depth" / p.name).read_bytes() for p in ours), seq.name


def cli_run(argv: list[str]) -> int:
    return subprocess.run(argv, capture_output=True, text=True, timeout=300).returncode


def test_an_actor_that_cannot_load_the_model_fails_each_sequence_and_leaves_no_folder(tmp_path):
    """The model passes the driver's checks (manifest, hashes, protobuf) but onnxruntime refuses it in
    the actors (an unknown operator, written with onnx): each sequence fails with that reason, exit 1."""
    require_ray()
    onnx = pytest.importorskip("onnx")
    from geonet_infer.models import bundled_models
    from tests.runtime.core.test_hostile_model import rehash

    model = tmp_path / "model"
    shutil.copytree(bundled_models()["small_synth"], model)
    graph = onnx.load(str(model / "depthnet.onnx"))
    graph.graph.node[0].op_type = "GeoNetNoSuchOp"
    onnx.save(graph, str(model / "depthnet.onnx"))
    rehash(model, "depthnet.onnx")
    seqs = make_sequences(tmp_path / "in", ["a", "b"], 2)
    out = tmp_path / "out"
    argv = [*CLI, "batch", *map(str, seqs), "--out", str(out), "--model", str(model), "--tasks", "depth"]
    proc = subprocess.run([*argv, "--runner", "ray", "--no-progress"], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 1, proc.stderr
    failures = [json.loads(line) for line in (out / "failures.jsonl").read_text().splitlines()]
    assert sorted(f["sequence"] for f in failures) == ["a", "b"]
    assert all(f["reason"].startswith("the actor could not load the model: ") and "GeoNetNoSuchOp" in f["reason"]
               for f in failures)  # fmt: skip
    assert [p for p in out.iterdir() if p.is_dir()] == [] and leftovers(out) == []
    assert json.loads((out / "summary.json").read_text())["sequences"]["failed"] == 2


# ----------------------------------------------------------------------------- OS refusals: exit 3, one line
@pytest.mark.parametrize("where", ["under", "is"])
def test_out_under_a_file_exits_3_with_one_line(tmp_path, capfd, where):
    (seq,) = make_sequences(tmp_path / "in", ["s1"], 2)
    (tmp_path / "afile").write_text("x")
    out = tmp_path / "afile" / "out" if where == "under" else tmp_path / "afile"
    rc, _, stderr = cli(capfd, "batch", seq, "--out", out, *DEPTH)
    assert rc == 3 and "afile" in one_error_line(stderr)
    assert (tmp_path / "afile").read_text() == "x"


def _small_files_only():  # in the child: any file past 64 KiB cannot be written (EFBIG), as on a full disk
    resource.setrlimit(resource.RLIMIT_FSIZE, (64 * 1024, 64 * 1024))


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="RLIMIT_FSIZE")
def test_a_write_refused_by_the_os_in_a_worker_exits_3_not_1(tmp_path):
    seqs = make_sequences(tmp_path / "in", ["s1", "s2"], 2)
    out = tmp_path / "out"
    proc = subprocess.run(
        [*CLI, "batch", *map(str, seqs), "--out", str(out), *DEPTH, "--workers", "1"],
        capture_output=True,
        text=True,
        timeout=120,
        preexec_fn=_small_files_only,
    )
    assert proc.returncode == 3, proc.stderr
    assert str(out / "s1") in one_error_line(proc.stderr)  # numpy reports a short write without the errno
    assert "Traceback" not in proc.stderr
    assert json.loads((out / "summary.json").read_text())["exit_code"] == 3
    assert leftovers(out) == []
    assert [p for p in out.iterdir() if p.is_dir()] == []  # no half-written sequence


def test_no_temp_files_after_a_complete_run(tmp_path, capfd):
    seqs = make_sequences(tmp_path / "in", ["s1", "s2"], 2)
    out = tmp_path / "out"
    rc, _, stderr = cli(capfd, "batch", *seqs, "--out", out, "--calib", SAMPLE_CALIB, "--no-progress")
    assert rc == 0, stderr
    assert leftovers(out) == [] and (out / OWNER_NAME).is_file()


def test_a_folder_stopped_while_writing_its_marker_is_removed_whole(tmp_path):
    """A worker stopped (SIGTERM, SIGKILL) while it wrote the folder's file list leaves that list's temp:
    discarding the unfinished folder removes it too, and a user's file still keeps the folder."""
    from geonet_infer.batch.units import discard

    folder = tmp_path / "s2"
    folder.mkdir()
    (folder / OWNER_NAME).write_text("{}\n")
    (folder / "..geonet-predict.ktjixf0g.tmp").write_text('{"files": [')  # the name CI saw left behind
    discard(folder)
    assert not folder.exists()

    folder.mkdir()
    (folder / OWNER_NAME).write_text("{}\n")
    (folder / "..geonet-predict.abcd1234.tmp").write_text("")
    (folder / "notes.txt").write_text("the user's")
    discard(folder)
    assert sorted(p.name for p in folder.iterdir()) == [OWNER_NAME, "notes.txt"]

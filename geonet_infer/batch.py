"""Batch inference: many sequences, one output folder, a process pool (or Ray Data, :mod:`.batch_ray`).

``geonet-infer batch`` is a thin CLI over :func:`run_batch`. Every sequence goes through
:func:`geonet_infer.pipeline.predict_to_dir`, so ``OUT/<sequence>/`` has exactly the layout
of ``geonet-infer predict``; next to the sequences::

    OUT/.geonet-batch            ownership marker: batch made this folder (also in each OUT/<sequence>/)
    OUT/<sequence>/...           predict's layout (depth/, flow/, flow_vis/, poses_*.txt, summary.json)
    OUT/<sequence>/.done         completion record, written (atomically) after all the sequence's files:
                                 each output's size and sha256, and the inputs' names, sizes and mtimes
    OUT/failures.jsonl           one JSON object a line: {"sequence", "input", "frame" (or null), "reason"}
    OUT/summary.json             sequences done/failed/skipped, frames, frames/s, engine, workers, threads
    OUT/.lock                    held while a job runs (a second job on the same OUT stops with exit 2)

Nothing is lost: batch only writes into a folder it made (or an empty one), refuses an OUT
that is, holds or is inside an input, and only ever deletes a sequence folder carrying its
ownership marker. Files are written under temporary names and renamed (``io.atomic``); a
sequence without ``.done`` is incomplete, and ``resume=True`` redoes it (its folder is
deleted first), and redoes a complete one whose outputs or inputs no longer match its
``.done``, while skipping the others. A failure (unreadable input or calibration, bad
frame, any exception in a worker, a worker process that died) is recorded and the job goes
on; the operating system refusing a write into OUT (disk full, read-only) stops the job
(exit 3). Work units are whole sequences: the frames of a sequence depend on each other
(pose and flow pair frame t with t + 1, and each frame's depth is reused).
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import json
import multiprocessing
import os
import platform
import shutil
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import asdict, dataclass, field
from pathlib import Path

from geonet_infer import __version__
from geonet_infer.errors import GeoNetError, InputError
from geonet_infer.io.atomic import atomic_write
from geonet_infer.io.calib import Camera, read_camera
from geonet_infer.io.frames import FrameSource, open_frames
from geonet_infer.manifest import file_sha256
from geonet_infer.pipeline import SUMMARY_NAME, TASKS, predict_to_dir
from geonet_infer.predictor import describe_skipped, resolve_tasks
from geonet_infer.session import usable_cpus

__all__ = [
    "ENGINES",
    "MARKER_NAME",
    "OWNER_NAME",
    "FAILURES_NAME",
    "LIST_SUFFIX",
    "BatchConfig",
    "WorkUnit",
    "expand_inputs",
    "plan_units",
    "sequence_name",
    "plan_workers",
    "cap_workers",
    "worker_memory_bytes",
    "run_sequence",
    "run_batch",
]

ENGINES = ("local", "ray")
MARKER_NAME = ".done"
OWNER_NAME = ".geonet-batch"
FAILURES_NAME = "failures.jsonl"
LOCK_NAME = ".lock"
LIST_SUFFIX = ".txt"
_RESERVED = {SUMMARY_NAME, FAILURES_NAME, LOCK_NAME, MARKER_NAME, OWNER_NAME}
MAX_WORKERS = 1024  # workers or threads per worker above this are a typo, not a machine
# Peak memory of one local worker, estimated as a base plus a multiple of the model's graph files
# (weights, onnxruntime's copies and arenas). Measured: 447 MB for the bundled small_synth model
# (20 MB of fp32 graphs), 128x416 frames, batch size 4, all tasks; the estimate gives 461 MB.
WORKER_BASE_BYTES = 256 * 1024**2
WORKER_GRAPH_FACTOR = 10
_KITTI = ("image_02", "data")


# ----------------------------------------------------------------------------- work units
@dataclass(frozen=True)
class WorkUnit:
    """One sequence: ``index`` = position in the input order, ``name`` = its folder under OUT."""

    index: int
    name: str
    path: str  # absolute


@dataclass(frozen=True)
class BatchConfig:
    """What every worker needs (picklable: it travels to processes and Ray actors).

    camera: from --calib / --intrinsics for every sequence; None = each input's own
    calibration (a KITTI drive's calib_cam_to_cam.txt), or none.
    """

    out_dir: str
    model: str | None = None
    precision: str = "fp32"
    backend: str = "onnxruntime"
    threads: int = 1
    tasks: tuple[str, ...] = TASKS
    batch_size: int = 4
    camera: Camera | None = None
    vis: bool = True  # depth colour maps and flow colour wheels

    def options(self) -> dict:
        """What decides the outputs (stored in each ``.done``; a resume with other options is refused)."""
        from geonet_infer.models import resolve_model

        cam = (
            None
            if self.camera is None
            else {
                "K": self.camera.K.tolist(),
                "dist": None if self.camera.dist is None else self.camera.dist.tolist(),
                "size": None if self.camera.size is None else list(self.camera.size),
            }
        )
        return {
            "model": str(resolve_model(self.model).resolve()),
            "precision": self.precision,
            "backend": self.backend,
            "tasks": list(self.tasks),
            "batch_size": self.batch_size,
            "camera": cam,
            "vis": self.vis,
        }


def read_input_list(path: Path) -> list[Path]:
    """Paths listed in a text file, one a line; blank lines and ``#`` comments skipped;
    relative paths are relative to the list file's folder."""
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(
            path,
            f"cannot read this input list ({exc.__class__.__name__})",
            "pass a text file with one input path a line",
        ) from None
    out = []
    for line in text.splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            p = Path(line).expanduser()
            out.append(p if p.is_absolute() else path.parent / p)
    return out


def expand_inputs(inputs) -> list[Path]:
    """INPUTS as given: ``.txt`` files replaced by the paths they list; every path must exist.

    Raises GeoNetError naming the first missing path (and how many are missing).
    """
    paths: list[Path] = []
    for given in map(Path, inputs):
        if given.suffix.lower() == LIST_SUFFIX and given.is_file():
            listed = read_input_list(given)
            bad = [p for p in listed if p.suffix.lower() == LIST_SUFFIX and p.is_file()]
            if bad:
                raise InputError(
                    bad[0], f"listed in {given}, but input lists do not nest", "list the sequences themselves"
                )
            paths += listed
        else:
            paths.append(given)
    missing = [p for p in paths if not p.exists()]
    if missing:
        more = f" (and {len(missing) - 1} more missing)" if len(missing) > 1 else ""
        raise InputError(
            missing[0], f"not found{more}", "pass sequence folders, videos, KITTI drives or a .txt file listing them"
        )
    if not paths:
        raise InputError(None, "no inputs", "pass sequence folders, videos, KITTI drives or a .txt list")
    return paths


def sequence_name(path) -> str:
    """The sequence's name as ``open_frames`` gives it (video stem, KITTI drive or folder name),
    worked out from the path alone (a broken video still gets its name)."""
    p = Path(os.path.abspath(path))
    if p.is_file():
        return p.stem
    if (p / _KITTI[0] / _KITTI[1]).is_dir():
        return p.name
    if p.name == _KITTI[1] and p.parent.name == _KITTI[0]:
        return p.parent.parent.name
    if p.name == _KITTI[0] and (p / _KITTI[1]).is_dir():
        return p.parent.name
    return p.name


def _safe_name(name: str) -> str:
    """A folder name under OUT that cannot be a reserved or hidden file."""
    if not name or name.startswith(".") or name in _RESERVED or "/" in name or "\\" in name:
        return f"seq_{name.lstrip('.')}" if name.strip(".") else "seq"
    return name


def _sequence_root(path: Path) -> Path:
    """The folder or file a sequence is named after (a KITTI drive for ``.../image_02/data``)."""
    p = Path(os.path.abspath(path))
    if p.is_dir() and p.name == _KITTI[1] and p.parent.name == _KITTI[0]:
        return p.parent.parent
    if p.is_dir() and p.name == _KITTI[0] and (p / _KITTI[1]).is_dir():
        return p.parent
    return p


def plan_units(paths) -> list[WorkUnit]:
    """One unit per distinct input (the same real path twice = once), in input order.

    Names are the sequences' names. Inputs that share a name are each called
    ``<name>__<folder it is in>``; if that still collides, the later ones get ``__2``,
    ``__3``, ... in input order. So the names depend only on the inputs and their order.
    """
    seen, distinct = set(), []
    for p in paths:
        real = os.path.realpath(p)
        if real not in seen:
            seen.add(real)
            distinct.append(Path(os.path.abspath(p)))
    base = [_safe_name(sequence_name(p)) for p in distinct]
    names = [
        f"{n}__{_sequence_root(p).parent.name or 'root'}" if base.count(n) > 1 else n for p, n in zip(distinct, base)
    ]
    final: list[str] = []
    for n in names:
        candidate, k = n, 1
        while candidate in final or (candidate != n and candidate in names):
            k += 1
            candidate = f"{n}__{k}"
        final.append(candidate)
    return [WorkUnit(i, n, str(p)) for i, (n, p) in enumerate(zip(final, distinct))]


def needs_own_calib(path) -> bool:
    """Whether the input has no calibration of its own (anything but a KITTI drive with its file)."""
    from geonet_infer.io.frames import find_kitti_calib

    root = _sequence_root(path)
    if not (root.is_dir() and (root / _KITTI[0] / _KITTI[1]).is_dir()):
        return True
    return find_kitti_calib(root) is None


# ----------------------------------------------------------------------------- one sequence
def _reason(exc: BaseException) -> str:
    if isinstance(exc, GeoNetError):
        return str(exc)
    return f"{exc.__class__.__name__}: {exc}".strip()


def _owned(folder: Path) -> bool:
    return (folder / OWNER_NAME).is_file()


def _is_empty(folder: Path) -> bool:
    return folder.is_dir() and next(folder.iterdir(), None) is None


def _not_ours(folder: Path) -> GeoNetError:
    return InputError(
        folder,
        f"holds files that geonet-infer batch did not make (no {OWNER_NAME} in it); it is left alone",
        "choose another --out (a new or empty folder, or one an earlier batch made)",
    )


def _claim(folder: Path) -> None:
    """Make ``folder`` (or take an empty one) and mark it as batch's; refuse a folder with others' files."""
    if folder.exists() and not folder.is_dir():
        raise NotADirectoryError(errno.ENOTDIR, "exists and is not a folder", str(folder))
    if _owned(folder):
        return
    if folder.exists() and not _is_empty(folder):
        raise _not_ours(folder)
    folder.mkdir(parents=True, exist_ok=True)
    _mark(folder)


def _mark(folder: Path) -> None:
    """Write batch's ownership marker into ``folder``: a plain write, no temp file, so a marker cut
    short by a crash still says who made the folder."""
    (folder / OWNER_NAME).write_text(json.dumps({"made_by": "geonet-infer batch", "version": __version__}) + "\n")


def _discard(folder: Path) -> None:
    """Remove a sequence folder batch made (or an empty one); anything else is left alone (GeoNetError)."""
    if not folder.exists():
        return
    if not _owned(folder):
        if _is_empty(folder):
            folder.rmdir()
            return
        raise _not_ours(folder)
    shutil.rmtree(folder, ignore_errors=True)
    if folder.exists():  # something kept writing into it; one more try, then let it fail loudly
        shutil.rmtree(folder)


def _input_files(source: FrameSource, own_calib: bool) -> list[Path]:
    """The files a sequence's outputs are made from: its frames (or video), and its own calibration."""
    files = list(getattr(source, "files", None) or [Path(source.path)])
    if own_calib and source.default_calib is not None:
        files.append(Path(source.default_calib))
    return files


def _fingerprint(unit_path: str, files: list[Path]) -> list[list]:
    """[name, size, mtime_ns] of each input file (fast: no hashing of the inputs)."""
    base = unit_path if os.path.isdir(unit_path) else os.path.dirname(unit_path)
    out = []
    for p in files:
        st = os.stat(p)
        out.append([os.path.relpath(os.path.abspath(p), base), st.st_size, st.st_mtime_ns])
    return out


def _record_outputs(folder: Path) -> dict[str, list]:
    """{relative path: [size, sha256]} of every file of a sequence folder but batch's own markers."""
    own = {folder / MARKER_NAME, folder / OWNER_NAME}
    return {
        p.relative_to(folder).as_posix(): [p.stat().st_size, file_sha256(p)]
        for p in sorted(folder.rglob("*"))
        if p.is_file() and p not in own
    }


def _stale(marker: dict, unit: WorkUnit, folder: Path, own_calib: bool) -> str | None:
    """Why a complete sequence must be redone (outputs or inputs differ from its ``.done``), or None."""
    try:
        outputs = {str(rel): (int(size), str(digest)) for rel, (size, digest) in marker["outputs"].items()}
        before = {str(name): (size, mtime) for name, size, mtime in marker["inputs"]}
    except (KeyError, TypeError, ValueError, AttributeError):
        return f"its {MARKER_NAME} has no record to check the outputs against"
    for rel, (size, digest) in outputs.items():
        p = folder / rel
        if not p.is_file():
            return f"{rel} is missing"
        if p.stat().st_size != size or file_sha256(p) != digest:
            return f"{rel} changed since it was written"
    try:
        now = _fingerprint(unit.path, _input_files(open_frames(unit.path), own_calib))
    except (GeoNetError, OSError) as exc:
        return f"its input cannot be read now ({_reason(exc)})"
    after = {name: (size, mtime) for name, size, mtime in now}
    changed = sorted(n for n in before.keys() | after.keys() if before.get(n) != after.get(n))
    if changed:
        more = f" and {len(changed) - 1} more" if len(changed) > 1 else ""
        return f"input {changed[0]}{more} changed since the run (added, removed, or another size or time)"
    return None


class _CountingSource:
    """A FrameSource that calls ``on_frame()`` for each frame read (live progress)."""

    def __init__(self, source, on_frame: Callable[[], None]):
        self._source, self._on_frame = source, on_frame

    def __getattr__(self, name):
        return getattr(self._source, name)

    def __len__(self) -> int:
        return len(self._source)

    def __iter__(self):
        for frame in self._source:
            self._on_frame()
            yield frame


def run_sequence(
    unit: WorkUnit,
    config: BatchConfig,
    predictor,
    on_frame: Callable[[], None] | None = None,
    options: dict | None = None,
) -> dict:
    """Predict one sequence into ``OUT/<name>/`` and write its ``.done``; never raises ``Exception``.

    Returns a result dict: sequence, input, index, status ("done" | "failed"), frames,
    failures (records for failures.jsonl; bad frames of a done sequence, or one record with
    frame None for a failed one), wall_s, and os_error (errno, strerror, filename) when the
    operating system refused a write into OUT (the job stops on it). A failed sequence leaves
    no folder behind. A folder batch did not make is never touched (the sequence fails).
    """
    out = Path(config.out_dir) / unit.name
    started = time.perf_counter()
    result = {
        "index": unit.index,
        "sequence": unit.name,
        "input": unit.path,
        "status": "failed",
        "frames": 0,
        "failures": [],
        "wall_s": 0.0,
        "os_error": None,
    }
    writing = False
    try:
        _discard(out)  # a partial folder of an interrupted run, or the results of an earlier job
        source = open_frames(unit.path)
        camera = config.camera
        if camera is None and source.default_calib is not None:
            camera = read_camera(source.default_calib).validate(source.default_calib)
        inputs = _fingerprint(unit.path, _input_files(source, config.camera is None))
        if on_frame is not None:
            source = _CountingSource(source, on_frame)
        writing = True
        out.mkdir()
        _mark(out)
        summary = predict_to_dir(
            predictor,
            source,
            out,
            camera=camera,
            tasks=config.tasks,
            batch_size=config.batch_size,
            progress=False,
            vis=config.vis,
        )
        failures = [
            {"sequence": unit.name, "input": unit.path, "frame": f["frame"], "reason": f["reason"]}
            for f in summary["failures"]
        ]
        marker = {
            "sequence": unit.name,
            "input": unit.path,
            "frames": summary["frames"],
            "failures": failures,
            "options": options if options is not None else config.options(),
            "inputs": inputs,
            "outputs": _record_outputs(out),
        }
        with atomic_write(out / MARKER_NAME) as tmp:
            tmp.write_text(json.dumps(marker) + "\n")
        result.update(status="done", frames=summary["frames"], failures=failures)
    except Exception as exc:  # noqa: BLE001 - any failure is recorded and the job goes on
        if writing and isinstance(exc, OSError):  # disk full, read-only, ...: every sequence would fail alike
            result["os_error"] = [exc.errno, exc.strerror or str(exc), exc.filename or str(out)]
        with contextlib.suppress(Exception):
            _discard(out)
        result["failures"] = [{"sequence": unit.name, "input": unit.path, "frame": None, "reason": _reason(exc)}]
    result["wall_s"] = time.perf_counter() - started
    return result


def read_marker(folder: Path) -> dict | None:
    try:
        marker = json.loads((folder / MARKER_NAME).read_text())
        return marker if isinstance(marker, dict) else None
    except (OSError, ValueError):
        return None


# ----------------------------------------------------------------------------- workers x threads
def plan_workers(n_units: int, workers: int | None, threads: int | None, cpus: int | None = None) -> tuple[int, int]:
    """(workers, threads per worker): by default workers x threads <= the usable CPUs.

    Neither given: one worker per CPU (at most one per sequence), the CPUs split among them.
    One given: the other fills the CPUs. Both given: as given (may oversubscribe; the
    caller warns). Never more workers than sequences.
    """
    cpus = usable_cpus() if cpus is None else cpus
    n = max(1, n_units)
    if workers is None and threads is None:
        workers = min(cpus, n)
        threads = max(1, cpus // workers)
    elif workers is None:
        workers = min(max(1, cpus // threads), n)
    elif threads is None:
        threads = max(1, cpus // min(workers, n))
    return min(workers, n), threads


def check_counts(workers: int | None, threads: int | None) -> None:
    """GeoNetError (exit 2) for a worker or thread count no machine has (a typo)."""
    for flag, value in (("--workers", workers), ("--threads-per-worker", threads)):
        if value is not None and not 1 <= value <= MAX_WORKERS:
            raise InputError(None, f"{flag} {value} is out of range", f"pass 1 to {MAX_WORKERS}")


def worker_memory_bytes(manifest, precision: str) -> int:
    """Estimated peak memory of one local worker: :data:`WORKER_BASE_BYTES` plus
    :data:`WORKER_GRAPH_FACTOR` times the size of the graph files of ``manifest`` it loads."""
    return WORKER_BASE_BYTES + int(WORKER_GRAPH_FACTOR * manifest.files_mib(precision) * 2**20)


def memory_available() -> int | None:
    """Bytes this job may still use: MemAvailable of /proc/meminfo, capped by a cgroup v2 limit;
    None where neither can be read (then workers are not capped by memory)."""
    avail = None
    with contextlib.suppress(OSError, ValueError, IndexError):
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                avail = int(line.split()[1]) * 1024
    with contextlib.suppress(OSError, ValueError):
        limit = Path("/sys/fs/cgroup/memory.max").read_text().strip()
        if limit != "max":
            used = int(Path("/sys/fs/cgroup/memory.current").read_text())
            free = max(0, int(limit) - used)
            avail = free if avail is None else min(avail, free)
    return avail


def cap_workers(
    workers: int | None,
    threads: int | None,
    *,
    cpus: int,
    mem_available: int | None,
    per_worker: int,
    n_units: int | None = None,
) -> tuple[int | None, int | None, list[str]]:
    """(workers, threads, notes): requests capped at the usable CPUs, and workers at what the
    available memory holds (``per_worker`` bytes each). None stays None (the default)
    unless memory holds fewer workers than the default would start. One note per cap."""
    notes = []
    if threads is not None and threads > cpus:
        notes.append(f"--threads-per-worker {threads}: more than the {cpus} usable CPUs; using {cpus}")
        threads = cpus
    if workers is not None and workers > cpus:
        notes.append(f"--workers {workers}: more than the {cpus} usable CPUs; using {cpus}")
        workers = cpus
    if mem_available is not None and per_worker > 0:
        fit = max(1, mem_available // per_worker)
        want = workers if workers is not None else cpus
        if n_units is not None:
            want = min(want, max(1, n_units))
        if want > fit:
            what = f"--workers {workers}" if workers is not None else f"{want} workers"
            notes.append(
                f"{what} would need about {want * per_worker / 1024**3:.1f} GiB of memory, "
                f"{mem_available / 1024**3:.1f} GiB is available; using {fit}"
            )
            workers = fit
    return workers, threads, notes


# ----------------------------------------------------------------------------- local engine
_WORKER: dict = {}


class _Stopped(BaseException):
    """Raised in a busy local worker by SIGTERM (the parent stops the job)."""


def _on_sigterm(signum, frame):
    if _WORKER.get("busy") is not None:
        raise _Stopped()
    os._exit(0)


def _die_with_parent(main_pid: int) -> None:
    """SIGTERM this worker when the job's process dies (also by SIGKILL): no orphan writes into OUT.

    Linux: PR_SET_PDEATHSIG (the job is the direct parent: spawn). Elsewhere, and should
    the job have died before prctl: a thread that sees the worker re-parented.
    """
    parent = os.getppid()
    if sys.platform.startswith("linux"):
        with contextlib.suppress(Exception):
            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(1, signal.SIGTERM, 0, 0, 0)  # PR_SET_PDEATHSIG

    def watch():
        while True:
            try:
                os.kill(main_pid, 0)
                alive = os.getppid() == parent
            except ProcessLookupError:
                alive = False
            except OSError:
                alive = True
            if not alive:
                os.kill(os.getpid(), signal.SIGTERM)
                return
            time.sleep(1.0)

    threading.Thread(target=watch, daemon=True, name="job-watch").start()


def _init_worker(config: BatchConfig, options: dict, frames, started, parent_pid: int) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C goes to the whole group; the parent decides
    signal.signal(signal.SIGTERM, _on_sigterm)
    _die_with_parent(parent_pid)
    from tqdm import tqdm

    # predict_to_dir makes a (disabled) tqdm; by default tqdm then creates a multiprocessing lock,
    # which a worker stopped by SIGTERM (os._exit) would leave registered: "leaked semaphore" warnings.
    tqdm.set_lock(threading.RLock())
    from geonet_infer.predictor import load

    _WORKER.update(config=config, options=options, frames=frames, started=started, busy=None)
    try:
        _WORKER["predictor"] = load(
            config.model, precision=config.precision, threads=config.threads, backend=config.backend
        )
    except Exception as exc:  # noqa: BLE001 - reported per sequence by _work
        _WORKER["predictor"], _WORKER["load_error"] = None, exc


def _count_frame() -> None:
    frames = _WORKER["frames"]
    with frames.get_lock():
        frames.value += 1


def _work(unit: WorkUnit) -> dict:
    out = Path(_WORKER["config"].out_dir) / unit.name
    _WORKER["started"][unit.index] = os.getpid()
    _WORKER["busy"] = unit
    try:
        if _WORKER["predictor"] is None:
            return _failed(unit, f"the worker could not load the model: {_reason(_WORKER['load_error'])}")
        return run_sequence(unit, _WORKER["config"], _WORKER["predictor"], _count_frame, _WORKER["options"])
    except _Stopped:
        if read_marker(out) is None:
            with contextlib.suppress(Exception):
                _discard(out)
        os._exit(143)
    finally:
        _WORKER["busy"] = None


def _context():
    """spawn: each worker is a fresh interpreter and a direct child of the job.

    Not fork (the job's process holds threads: tqdm's monitor, the pool's manager). Not
    forkserver: its workers are children of the server, which hands them its liveness
    pipe, so after a SIGKILL of the job neither the server nor the workers notice, and
    the workers would go on writing into OUT while a --resume redoes the same sequences.
    """
    return multiprocessing.get_context("spawn")


def _stop_pool(executor: ProcessPoolExecutor, grace_s: float = 20.0) -> None:
    """Terminate the pool's processes (SIGTERM: a busy worker deletes its unfinished folder)."""
    procs = list((getattr(executor, "_processes", None) or {}).values())
    for p in procs:
        with contextlib.suppress(Exception):
            p.terminate()
    deadline = time.monotonic() + grace_s
    for p in procs:
        p.join(max(0.0, deadline - time.monotonic()))
        if p.is_alive():
            with contextlib.suppress(Exception):
                p.kill()
                p.join(5)
    executor.shutdown(wait=True, cancel_futures=True)  # the processes are gone: returns at once


class LocalEngine:
    """A process pool (spawn); each worker loads the predictor once (initializer)."""

    name = "local"
    # exit codes of pool processes that did not crash: idle or stopped by SIGTERM (ours or the pool's)
    _NOT_CRASHED = (None, 0, 143, -signal.SIGTERM)

    def __init__(self, config: BatchConfig, options: dict, workers: int):
        self.config, self.options, self.workers = config, options, workers
        self._ctx = _context()
        self._frames = self._ctx.Value("q", 0)
        self._executor: ProcessPoolExecutor | None = None

    def live_frames(self) -> int:
        """Frames read so far by the workers (finished sequences or not)."""
        return self._frames.value

    def close(self) -> None:
        """Stop the pool if it still runs (interrupted): busy workers delete their unfinished folders."""
        if self._executor is not None:
            _stop_pool(self._executor)
            self._executor = None

    def results(self, units: list[WorkUnit]) -> Iterator[dict | None]:
        """Yields each unit's result as it completes, and None about twice a second (progress).

        A worker process that dies (segfault, OOM kill) breaks the pool: the sequence it was
        predicting is reported as failed, the others are submitted again to a new pool.
        """
        crashes: dict[int, int] = {}
        barren = 0  # pools in a row that broke before any unit started
        todo = list(units)
        while todo:
            started = self._ctx.Array("q", max(u.index for u in todo) + 1, lock=False)  # unit -> worker pid
            executor = self._executor = ProcessPoolExecutor(
                max_workers=min(self.workers, len(todo)),
                mp_context=self._ctx,
                initializer=_init_worker,
                initargs=(self.config, self.options, self._frames, started, os.getpid()),
            )
            pending = {executor.submit(_work, u): u for u in todo}
            processes = dict(getattr(executor, "_processes", None) or {})
            lost: list[WorkUnit] = []
            while pending:
                done, _ = wait(pending, timeout=0.5, return_when=FIRST_COMPLETED)
                for future in done:
                    unit = pending.pop(future)
                    try:
                        result = future.result()
                    except BrokenProcessPool:
                        lost.append(unit)
                        continue
                    except Exception as exc:  # noqa: BLE001 - e.g. a result that could not be pickled
                        result = _failed(unit, f"worker error: {_reason(exc)}")
                    yield result
                if not done:
                    yield None
            executor.shutdown(wait=True)
            self._executor = None
            processes.update(getattr(executor, "_processes", None) or {})
            exit_codes = {pid: p.exitcode for pid, p in processes.items()}
            todo = []
            barren = barren + 1 if lost and not any(started[u.index] for u in lost) else 0
            if barren >= 2:  # the workers cannot even start: report, do not loop
                for unit in sorted(lost, key=lambda u: u.index):
                    yield _failed(
                        unit,
                        "the worker processes died before they could start "
                        f"(exit codes {sorted({str(c) for c in exit_codes.values()})})",
                    )
                return
            for unit in sorted(lost, key=lambda u: u.index):
                pid = started[unit.index]
                if pid:  # it had started: it ran in the process that died, or beside it
                    code = exit_codes.get(pid)
                    crashes[unit.index] = crashes.get(unit.index, 0) + 1
                    if code not in self._NOT_CRASHED or crashes[unit.index] >= 2:
                        folder = Path(self.config.out_dir) / unit.name
                        if read_marker(folder) is None:  # the dead worker could not clean up
                            with contextlib.suppress(Exception):
                                _discard(folder)
                        yield _failed(
                            unit,
                            "the worker process died while predicting this sequence"
                            + (f" (exit code {code})" if code not in (None, 143) else ""),
                        )
                        continue
                todo.append(unit)


def _failed(unit: WorkUnit, reason: str) -> dict:
    return {
        "index": unit.index,
        "sequence": unit.name,
        "input": unit.path,
        "status": "failed",
        "frames": 0,
        "wall_s": 0.0,
        "failures": [{"sequence": unit.name, "input": unit.path, "frame": None, "reason": reason}],
    }


# ----------------------------------------------------------------------------- the job
class _NoEngine:
    address = None

    def results(self, units):
        return iter(())

    def live_frames(self) -> int:
        return 0

    def close(self) -> None:
        pass


@contextlib.contextmanager
def _job_lock(out_dir: Path):
    """An exclusive lock on OUT/.lock for the job's lifetime (released by the OS if the job dies)."""
    try:
        import fcntl
    except ImportError:  # Windows: no lock
        yield
        return
    fd = os.open(out_dir / LOCK_NAME, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            raise InputError(
                out_dir, "another batch job is writing to this folder", "wait for it to finish, or pass another --out"
            ) from None
        yield
    finally:
        os.close(fd)


def _write_failures(path: Path, records: list[dict]) -> None:
    with atomic_write(path) as tmp:
        tmp.write_text("".join(json.dumps(r) + "\n" for r in records))


@dataclass
class _Progress:
    total: int
    enabled: bool
    frames_done: int = 0
    bar: object = field(default=None)

    def __post_init__(self):
        from tqdm import tqdm

        self.bar = tqdm(total=self.total, unit="seq", desc="sequences", disable=not self.enabled, dynamic_ncols=True)
        self.t0 = time.perf_counter()

    def tick(self, live_frames: int | None = None, done: int = 0, failed: int = 0) -> None:
        frames = self.frames_done if live_frames is None else max(live_frames, self.frames_done)
        elapsed = time.perf_counter() - self.t0
        self.bar.set_postfix_str(
            f"frames={frames}, {frames / elapsed if elapsed > 0 else 0:.1f} frames/s, failed={failed}", refresh=True
        )
        if done:
            self.bar.update(done)

    def close(self):
        self.bar.close()


@contextlib.contextmanager
def _signals_deferred() -> Iterator[list]:
    """Ctrl-C and SIGTERM only noted (not raised) inside: stopping the workers and writing the
    summary must not be cut short by a second signal. Yields a list that gets the signals caught."""
    caught: list[int] = []
    if threading.current_thread() is not threading.main_thread():
        yield caught
        return
    previous = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    for sig in previous:
        signal.signal(sig, lambda signum, frame: caught.append(signum))
    try:
        yield caught
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def check_out(out_dir: Path, units: list[WorkUnit]) -> None:
    """GeoNetError (exit 2) when OUT is, holds or is inside an input: batch writes (and
    deletes its own sequence folders) in OUT, and must never touch an input."""
    out_real = Path(os.path.realpath(out_dir))
    for unit in units:
        root = Path(os.path.realpath(_sequence_root(Path(unit.path))))
        if out_real == root or root in out_real.parents or out_real in root.parents:
            how = "is" if out_real == root else ("is inside" if root in out_real.parents else "holds")
            raise InputError(
                out_dir,
                f"--out {how} the input {unit.path}; batch never writes where its inputs are",
                "choose an --out outside every input",
            )


def _resume_plan(units, out_dir: Path, options: dict, own_calib: bool, log):
    """(todo, skipped results, redone records) of a resume: a sequence is skipped only if its
    ``.done`` matches its outputs and its inputs; a ``.done`` made with other options is refused."""
    todo, skipped, redone = [], [], []
    for unit in units:
        folder = out_dir / unit.name
        marker = read_marker(folder)
        if marker is None:
            todo.append(unit)
            continue
        if marker.get("options") != options or marker.get("input") != unit.path:
            what = (
                "input"
                if marker.get("input") != unit.path
                else "set of options (model, precision, tasks, batch size or camera)"
            )
            raise InputError(
                folder,
                f"was made with another {what} than this job has",
                "resume with the options of the first run, or pass another --out",
            )
        why = _stale(marker, unit, folder, own_calib)
        if why:
            log(f"geonet-infer batch: note: {unit.name}: redoing it, {why}")
            redone.append({"sequence": unit.name, "reason": why})
            todo.append(unit)
            continue
        skipped.append(
            {
                "index": unit.index,
                "sequence": unit.name,
                "input": unit.path,
                "status": "skipped",
                "frames": marker.get("frames", 0),
                "failures": marker.get("failures", []),
                "wall_s": 0.0,
            }
        )
    return todo, skipped, redone


def model_tasks(model_dir, graphs, tasks: Iterable[str] | None, log) -> tuple[str, ...]:
    """The tasks to run, resolved as ``predict`` does (:func:`geonet_infer.predictor.resolve_tasks`):
    given tasks the model cannot do are refused before any work; with ``None`` every task it can do,
    the others named in one line."""
    tasks, skipped = resolve_tasks(graphs, tasks, model_dir)
    if skipped:
        log(f"geonet-infer batch: skipping {describe_skipped(skipped)} in {model_dir}; running {', '.join(tasks)}")
    return tasks


def run_batch(
    inputs,
    out_dir,
    *,
    engine: str = "local",
    workers: int | None = None,
    threads: int | None = None,
    model: str | None = None,
    precision: str = "fp32",
    backend: str = "onnxruntime",
    tasks: tuple[str, ...] | None = None,
    batch_size: int = 4,
    camera: Camera | None = None,
    vis: bool = True,
    resume: bool = False,
    ray_address: str | None = None,
    progress: bool = True,
    log=None,
) -> dict:
    """Run a batch job (see the module docstring); returns the summary (also OUT/summary.json).

    ``summary["exit_code"]``: 0 all good, 1 something failed (see failures.jsonl), 3 the
    operating system refused a write into OUT, 130 interrupted.
    Raises GeoNetError for bad usage (missing input, unknown model, an OUT that overlaps an
    input or holds files batch did not make, a resume with other options, a locked OUT);
    OSError after writing the summary when the OS refused a write (the job stops);
    KeyboardInterrupt after stopping the workers and writing the summary
    (``"interrupted": true``) when interrupted (Ctrl-C, or SIGTERM turned into it by the CLI);
    a later ``resume=True`` finishes.
    """
    from geonet_infer.manifest import load_manifest, model_notice
    from geonet_infer.models import resolve_model

    log = log or (lambda msg: print(msg, file=sys.stderr))
    if engine not in ENGINES:
        raise InputError(None, f"unknown engine {engine!r}", f"choose one of {', '.join(ENGINES)}")
    if batch_size < 1:
        raise InputError(None, f"batch size must be >= 1, got {batch_size}")
    check_counts(workers, threads)
    units = plan_units(expand_inputs(inputs))
    model_dir = resolve_model(model)
    manifest = load_manifest(model_dir)
    graphs = manifest.graph_names(precision)  # bad --model / --precision: exit 2 before any work
    tasks = model_tasks(model_dir, graphs, tasks, log)
    out_dir = Path(os.path.abspath(out_dir))
    check_out(out_dir, units)
    _claim(out_dir)

    probe = BatchConfig(
        out_dir=str(out_dir),
        model=model,
        precision=precision,
        backend=backend,
        tasks=tasks,
        batch_size=batch_size,
        camera=camera,
        vis=vis,
    )
    options = probe.options()
    with _job_lock(out_dir):
        foreign = [u for u in units if (out_dir / u.name).exists() and not _owned(out_dir / u.name)]
        for unit in foreign:
            if not _is_empty(out_dir / unit.name):
                raise _not_ours(out_dir / unit.name)
        runner, stream = _NoEngine(), iter(())
        n_workers = n_threads = 0
        limits: list[str] = []
        skipped, redone, todo = [], [], list(units)
        results: dict[int, dict] = {}
        bar = None
        interrupted = False
        os_error = None
        n_done = n_failed = 0
        started = time.perf_counter()
        failures_path = out_dir / FAILURES_NAME
        try:
            if resume:
                todo, skipped, redone = _resume_plan(units, out_dir, options, camera is None, log)
                results.update({r["index"]: r for r in skipped})
            _write_failures(failures_path, [f for r in skipped for f in r["failures"]])
            # nothing left to do (everything complete already): no workers, no cluster
            if todo and engine == "ray":
                from geonet_infer.batch_ray import RayEngine

                runner = RayEngine.start(probe, options, len(todo), workers, threads, ray_address, log)
                n_workers, n_threads = runner.workers, runner.threads
            elif todo:
                cpus = usable_cpus()
                capped_w, capped_t, limits = cap_workers(
                    workers,
                    threads,
                    cpus=cpus,
                    mem_available=memory_available(),
                    per_worker=worker_memory_bytes(manifest, precision),
                    n_units=len(todo),
                )
                for note in limits:
                    log(f"geonet-infer batch: warning: {note}")
                n_workers, n_threads = plan_workers(len(todo), capped_w, capped_t)
                if n_workers * n_threads > cpus:
                    log(f"geonet-infer batch: note: {n_workers} workers x {n_threads} threads > {cpus} usable CPUs")
                runner = LocalEngine(
                    BatchConfig(**{**asdict(probe), "camera": camera, "threads": n_threads}), options, n_workers
                )
            bar = _Progress(len(todo), progress)
            started = time.perf_counter()
            stream = runner.results(todo)
            with open(failures_path, "a") as failures_file:
                for result in stream:
                    if result is None:
                        bar.tick(runner.live_frames(), failed=n_failed)
                        continue
                    results[result["index"]] = result
                    if result["failures"]:
                        failures_file.write("".join(json.dumps(r) + "\n" for r in result["failures"]))
                        failures_file.flush()
                    n_done += result["status"] == "done"
                    n_failed += result["status"] == "failed"
                    bar.frames_done += result["frames"]
                    bar.tick(runner.live_frames(), done=1, failed=n_failed)
                    if result.get("os_error"):
                        os_error = OSError(*result["os_error"])
                        break
        except KeyboardInterrupt:
            interrupted = True
        except BaseException:
            with _signals_deferred():
                _stop(bar, stream, runner)
            raise
        with _signals_deferred() as caught:
            _stop(bar, stream, runner)
            interrupted = interrupted or bool(caught)
            wall = time.perf_counter() - started
            ordered = [results[u.index] for u in units if u.index in results]
            records = [r for res in ordered for r in res["failures"]]
            _write_failures(failures_path, records)  # final: in input order (appends came in completion order)
            frames = sum(r["frames"] for r in ordered if r["status"] == "done")
            summary = {
                "engine": engine,
                "workers": n_workers,
                "threads_per_worker": n_threads,
                "workers_requested": workers,
                "threads_per_worker_requested": threads,
                "limits": limits,
                "usable_cpus": usable_cpus(),
                "ray_address": getattr(runner, "address", None),
                "out": str(out_dir),
                "resume": resume,
                "interrupted": interrupted,
                "sequences": {
                    "total": len(units),
                    "done": n_done,
                    "failed": n_failed,
                    "skipped": len(skipped),
                    "not_run": len(units) - n_done - n_failed - len(skipped),
                },
                "redone": redone,
                "frames": frames,
                "frames_failed": sum(1 for r in records if r["frame"] is not None),
                "failures": len(records),
                "failures_file": FAILURES_NAME,
                "os_error": None if os_error is None else f"{os_error.filename}: {os_error.strerror}",
                "wall_s": wall,
                "frames_per_s": frames / wall if wall > 0 and frames else 0.0,
                "tasks": list(tasks),
                "batch_size": batch_size,
                "model": options["model"],
                "model_notice": model_notice(manifest),  # synthetic-only model: how it does on real video
                "precision": precision,
                "backend": backend,
                "camera": "per input (its own calibration, if any)" if camera is None else camera.source,
                "per_sequence": [
                    {
                        "sequence": r["sequence"],
                        "input": r["input"],
                        "status": r["status"],
                        "frames": r["frames"],
                        "failures": len(r["failures"]),
                        "wall_s": round(r["wall_s"], 3),
                    }
                    for r in ordered
                ],
                "versions": {"geonet_infer": __version__, "python": platform.python_version()},
            }
            if interrupted:
                summary["exit_code"] = 130
            elif os_error is not None:
                summary["exit_code"] = 3
            else:
                summary["exit_code"] = 1 if records or n_failed else 0
            with atomic_write(out_dir / SUMMARY_NAME) as tmp:
                tmp.write_text(json.dumps(summary, indent=2) + "\n")
    if interrupted:
        raise KeyboardInterrupt
    if os_error is not None:
        raise os_error
    return summary


def _stop(bar, stream, runner) -> None:
    """Close the progress bar, the result stream and the engine (workers stopped, unfinished folders removed)."""
    if bar is not None:
        bar.close()
    with contextlib.suppress(Exception):
        getattr(stream, "close", lambda: None)()
    with contextlib.suppress(Exception):
        runner.close()

"""What a batch job is made of: work units (one per sequence), the folders batch owns in OUT, and
one sequence predicted into its folder (:func:`run_sequence`, the same for every runner).
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from geonet_infer import __version__, ownership
from geonet_infer.engines import usable_cpus
from geonet_infer.errors import GeoNetError, InputError
from geonet_infer.io.atomic import atomic_write
from geonet_infer.io.calib import Camera, read_camera
from geonet_infer.io.frames import FrameSource, open_frames
from geonet_infer.manifest import file_sha256
from geonet_infer.output.layout import OUTPUT_MARKER, SUMMARY_NAME
from geonet_infer.output.predict import predict_to_dir
from geonet_infer.predictor import TASKS

MARKER_NAME = ".done"
OWNER_NAME = ".geonet-batch"
FAILURES_NAME = "failures.jsonl"
LOCK_NAME = ".lock"
LIST_SUFFIX = ".txt"
CALIB_SEPARATOR = "|"  # in an input list: INPUT | ITS CALIBRATION
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
    calib: str = ""  # absolute: its calibration from the input list ("": none given there)


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
    outputs: tuple[str, ...] | None = None  # --outputs names (geonet_infer.output.layout); None: the default
    flow_method: str = "network"  # or "dis" (geonet_infer.classical)
    pose_method: str = "network"  # or "orbvo"

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
        options = {
            "model": str(resolve_model(self.model).resolve()),
            "precision": self.precision,
            "backend": self.backend,
            "tasks": list(self.tasks),
            "batch_size": self.batch_size,
            "camera": cam,
            "vis": self.vis,
        }
        # only when not the networks: a .done written before these options existed stays resumable
        methods = {"flow_method": self.flow_method, "pose_method": self.pose_method}
        chosen = {} if self.outputs is None else {"outputs": sorted(self.outputs)}  # likewise
        return options | {k: v for k, v in methods.items() if v != "network"} | chosen


def read_input_list(path: Path) -> list[Path]:
    """The inputs listed in a text file (:func:`read_input_pairs`, without their calibrations)."""
    return [p for p, _ in read_input_pairs(path)]


def read_input_pairs(path: Path) -> list[tuple[Path, Path | None]]:
    """(input, its calibration or None) listed in a text file, one input a line, optionally followed
    by ``|`` and its calibration file (``clip_a.mp4 | camera_a.txt``); blank lines and ``#`` comments
    skipped; relative paths are relative to the list file's folder."""
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(
            path,
            f"cannot read this input list ({exc.__class__.__name__})",
            "pass a text file with one input path a line",
        ) from None

    def located(text: str) -> Path:
        p = Path(text.strip()).expanduser()
        return p if p.is_absolute() else path.parent / p

    out: list[tuple[Path, Path | None]] = []
    for number, line in enumerate(text.splitlines(), 1):
        line = line.strip()
        if line and not line.startswith("#"):
            item, bar, calib = line.partition(CALIB_SEPARATOR)
            if bar and not (item.strip() and calib.strip()):
                raise InputError(path, f"line {number}: {line!r}", f"write INPUT {CALIB_SEPARATOR} CALIBRATION")
            out.append((located(item), located(calib) if bar else None))
    return out


def expand_inputs(inputs) -> list[Path]:
    """INPUTS as given: ``.txt`` files replaced by the paths they list (:func:`expand_input_pairs`)."""
    return [p for p, _ in expand_input_pairs(inputs)]


def expand_input_pairs(inputs) -> list[tuple[Path, Path | None]]:
    """INPUTS as given, each with the calibration its list pairs it with (or None): ``.txt`` files
    replaced by what they list (:func:`read_input_pairs`); every path must exist.

    Raises GeoNetError naming the first missing path (and how many are missing).
    """
    pairs: list[tuple[Path, Path | None]] = []
    for given in map(Path, inputs):
        if given.suffix.lower() == LIST_SUFFIX and given.is_file():
            listed = read_input_pairs(given)
            bad = [p for p, _ in listed if p.suffix.lower() == LIST_SUFFIX and p.is_file()]
            if bad:
                raise InputError(
                    bad[0], f"listed in {given}, but input lists do not nest", "list the sequences themselves"
                )
            pairs += listed
        else:
            pairs.append((given, None))
    paths = [p for p, _ in pairs] + [c for _, c in pairs if c is not None]
    missing = [p for p in paths if not p.exists()]
    if missing:
        more = f" (and {len(missing) - 1} more missing)" if len(missing) > 1 else ""
        raise InputError(
            missing[0], f"not found{more}", "pass sequence folders, videos, KITTI drives or a .txt file listing them"
        )
    if not pairs:
        raise InputError(None, "no inputs", "pass sequence folders, videos, KITTI drives or a .txt list")
    return pairs


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


def sequence_root(path: Path) -> Path:
    """The folder or file a sequence is named after (a KITTI drive for ``.../image_02/data``)."""
    p = Path(os.path.abspath(path))
    if p.is_dir() and p.name == _KITTI[1] and p.parent.name == _KITTI[0]:
        return p.parent.parent
    if p.is_dir() and p.name == _KITTI[0] and (p / _KITTI[1]).is_dir():
        return p.parent
    return p


def plan_units(paths, calibs=None) -> list[WorkUnit]:
    """One unit per distinct input (the same real path twice = once), in input order; ``calibs``:
    each input's calibration from its list, or None (:func:`expand_input_pairs`).

    Names are the sequences' names. Inputs that share a name are each called
    ``<name>__<folder it is in>``; if that still collides, the later ones get ``__2``,
    ``__3``, ... in input order. So the names depend only on the inputs and their order.
    """
    seen, distinct, calib_of = set(), [], []
    for p, calib in zip(paths, calibs or [None] * len(paths)):
        real = os.path.realpath(p)
        if real not in seen:
            seen.add(real)
            distinct.append(Path(os.path.abspath(p)))
            calib_of.append("" if calib is None else os.path.abspath(calib))
    base = [_safe_name(sequence_name(p)) for p in distinct]
    names = [
        f"{n}__{sequence_root(p).parent.name or 'root'}" if base.count(n) > 1 else n for p, n in zip(distinct, base)
    ]
    final: list[str] = []
    for n in names:
        candidate, k = n, 1
        while candidate in final or (candidate != n and candidate in names):
            k += 1
            candidate = f"{n}__{k}"
        final.append(candidate)
    return [WorkUnit(i, n, str(p), c) for i, (n, p, c) in enumerate(zip(final, distinct, calib_of))]


def needs_own_calib(path) -> bool:
    """Whether the input has no calibration of its own: no ``<name>.calib.txt`` beside it
    (:func:`~geonet_infer.io.frames.find_side_calib`) and not a KITTI drive with its file."""
    from geonet_infer.io.frames import find_kitti_calib, find_side_calib

    root = sequence_root(path)
    if find_side_calib(root) is not None:
        return False
    if not (root.is_dir() and (root / _KITTI[0] / _KITTI[1]).is_dir()):
        return True
    return find_kitti_calib(root) is None


# ----------------------------------------------------------------------------- one sequence
def describe_error(exc: BaseException) -> str:
    if isinstance(exc, GeoNetError):
        return str(exc)
    return f"{exc.__class__.__name__}: {exc}".strip()


def owned(folder: Path) -> bool:
    return (folder / OWNER_NAME).is_file()


def is_empty(folder: Path) -> bool:
    return folder.is_dir() and next(folder.iterdir(), None) is None


def not_ours(folder: Path) -> GeoNetError:
    return InputError(
        folder,
        f"holds files that geonet-infer batch did not make (no {OWNER_NAME} in it); it is left alone",
        "choose another --out (a new or empty folder, or one an earlier batch made)",
    )


def claim(folder: Path) -> None:
    """Make ``folder`` (or take an empty one) and mark it as batch's; refuse a folder with others' files."""
    if folder.exists() and not folder.is_dir():
        raise NotADirectoryError(errno.ENOTDIR, "exists and is not a folder", str(folder))
    if owned(folder):
        return
    if folder.exists() and not is_empty(folder):
        raise not_ours(folder)
    folder.mkdir(parents=True, exist_ok=True)
    _mark(folder)


def _mark(folder: Path) -> None:
    """Write batch's ownership marker into ``folder``: a plain write, no temp file, so a marker cut
    short by a crash still says who made the folder."""
    (folder / OWNER_NAME).write_text(json.dumps({"made_by": "geonet-infer batch", "version": __version__}) + "\n")


def discard(folder: Path) -> None:
    """Remove what batch made in a sequence folder: its ``.done``, the files its run listed (the folder's
    ``.geonet-predict``, :mod:`geonet_infer.ownership`; an older batch's ``.done`` list), then the markers
    and the folder if nothing else is left. Files a user added stay, and so does the folder with its
    markers. A folder batch did not make is left alone (GeoNetError) unless it is empty."""
    if not folder.exists():
        return
    if not owned(folder):
        if is_empty(folder):
            folder.rmdir()
            return
        raise not_ours(folder)
    listed = set(_listed(folder))
    with contextlib.suppress(OSError, ValueError, AttributeError):  # an older batch listed its outputs here
        listed |= set(json.loads((folder / MARKER_NAME).read_text())["outputs"])
    (folder / MARKER_NAME).unlink(missing_ok=True)  # first: a folder half cleared is never complete
    ownership.remove_listed(folder, sorted(listed))
    markers = (OUTPUT_MARKER, OWNER_NAME)  # kept while anything else is there (a user's file, a late write)
    if all(p.name in markers for p in folder.iterdir()):
        for name in markers:
            (folder / name).unlink(missing_ok=True)
        folder.rmdir()


def _listed(folder: Path) -> list[str]:
    """The files the sequence's run listed as its own (none when it listed nothing yet)."""
    if not (folder / OUTPUT_MARKER).is_file():
        return []
    return ownership.read_marker(folder / OUTPUT_MARKER)["files"]


def _input_files(source: FrameSource, unit: WorkUnit, own_calib: bool) -> list[Path]:
    """The files a sequence's outputs are made from: its frames (or video), and the calibration used:
    the one its list pairs it with, else (``own_calib``: no --calib for all) its own."""
    files = list(getattr(source, "files", None) or [Path(source.path)])
    if unit.calib:
        files.append(Path(unit.calib))
    elif own_calib and source.default_calib is not None:
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
    """{relative path: [size, sha256]} of every file the sequence's run listed and wrote (a user's files
    in the folder are not outputs)."""
    return {
        rel: [p.stat().st_size, file_sha256(p)]
        for rel, p in sorted(
            (p.relative_to(folder).as_posix(), p) for p in ownership.listed_paths(folder, _listed(folder))
        )
        if p.is_file()
    }


def stale(marker: dict, unit: WorkUnit, folder: Path, own_calib: bool) -> str | None:
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
        now = _fingerprint(unit.path, _input_files(open_frames(unit.path), unit, own_calib))
    except (GeoNetError, OSError) as exc:
        return f"its input cannot be read now ({describe_error(exc)})"
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
    frame None for a failed one), check (the output check summed up, as in the sequence's
    summary.json without its per-pair list; None without flow), wall_s, and os_error (errno,
    strerror, filename) when the operating system refused a write into OUT (the job stops on
    it). A failed sequence leaves no folder behind. A folder batch did not make is never
    touched (the sequence fails).
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
        discard(out)  # the files of an interrupted run, or of an earlier job
        source = open_frames(unit.path)
        camera = read_camera(unit.calib).validate(unit.calib) if unit.calib else config.camera
        if camera is None and source.default_calib is not None:
            camera = read_camera(source.default_calib).validate(source.default_calib)
        inputs = _fingerprint(unit.path, _input_files(source, unit, config.camera is None))
        if on_frame is not None:
            source = _CountingSource(source, on_frame)  # type: ignore[assignment]  # a FrameSource proxy
        writing = True
        out.mkdir(exist_ok=True)  # it may hold a user's files, which stay
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
            outputs=config.outputs,
            flow_method=config.flow_method,
            pose_method=config.pose_method,
            exclusive=True,  # lists its files before writing them: what discard removes
            claimed_by=(OWNER_NAME, MARKER_NAME),
        )
        failures = [
            {"sequence": unit.name, "input": unit.path, "frame": f["frame"], "reason": f["reason"]}
            for f in summary["failures"]
        ]
        check = summary["check"] and {k: v for k, v in summary["check"].items() if k not in ("method", "per_pair")}
        camera_of = summary["camera"] and {  # the K it ran with (per input in a job of several cameras)
            "K": summary["camera"]["K_input_resolution"],
            "source": summary["camera"]["source"],
        }
        marker = {
            "sequence": unit.name,
            "input": unit.path,
            "camera": camera_of,
            "frames": summary["frames"],
            "failures": failures,
            "check": check,
            "options": options if options is not None else config.options(),
            "inputs": inputs,
            "outputs": _record_outputs(out),
        }
        with atomic_write(out / MARKER_NAME) as tmp:
            tmp.write_text(json.dumps(marker) + "\n")
        result.update(status="done", frames=summary["frames"], failures=failures, check=check, camera=camera_of)
    except Exception as exc:  # noqa: BLE001 - any failure is recorded and the job goes on
        if writing and isinstance(exc, OSError):  # disk full, read-only, ...: every sequence would fail alike
            result["os_error"] = [exc.errno, exc.strerror or str(exc), exc.filename or str(out)]
        with contextlib.suppress(Exception):
            discard(out)
        result["failures"] = [{"sequence": unit.name, "input": unit.path, "frame": None, "reason": describe_error(exc)}]
    result["wall_s"] = time.perf_counter() - started
    return result


def read_marker(folder: Path) -> dict | None:
    try:
        marker = json.loads((folder / MARKER_NAME).read_text())
        return marker if isinstance(marker, dict) else None
    except (OSError, ValueError, RecursionError):  # RecursionError: JSON nested too deep
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
        assert threads is not None
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
def failed_result(unit: WorkUnit, reason: str) -> dict:
    return {
        "index": unit.index,
        "sequence": unit.name,
        "input": unit.path,
        "status": "failed",
        "frames": 0,
        "wall_s": 0.0,
        "failures": [{"sequence": unit.name, "input": unit.path, "frame": None, "reason": reason}],
    }

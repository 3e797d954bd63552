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

from geonet_infer import __version__
from geonet_infer.batch.inputs import (  # noqa: F401  (re-exported: this module's names before the split)
    _RESERVED,
    CALIB_SEPARATOR,
    FAILURES_NAME,
    LIST_SUFFIX,
    LOCK_NAME,
    MARKER_NAME,
    OWNER_NAME,
    WorkUnit,
    _safe_name,
    expand_input_pairs,
    expand_inputs,
    needs_own_calib,
    plan_units,
    read_input_list,
    read_input_pairs,
    sequence_name,
    sequence_root,
)
from geonet_infer.batch.sizing import (  # noqa: F401  (re-exported: this module's names before the split)
    MAX_WORKERS,
    WORKER_BASE_BYTES,
    WORKER_GRAPH_FACTOR,
    cap_workers,
    check_counts,
    memory_available,
    plan_workers,
    worker_memory_bytes,
)
from geonet_infer.core.predictor import TASKS
from geonet_infer.errors import GeoNetError, InputError
from geonet_infer.io.atomic import atomic_write, leftover_temps
from geonet_infer.io.calib import Camera, read_camera
from geonet_infer.io.frames import FrameSource, open_frames
from geonet_infer.limits import DEFAULT_BATCH_SIZE
from geonet_infer.models.manifest import file_sha256
from geonet_infer.output import ownership
from geonet_infer.output.layout import OUTPUT_MARKER
from geonet_infer.output.predict import predict_to_dir


@dataclass(frozen=True)
class BatchConfig:
    """What every worker needs (picklable: it travels to processes and Ray actors).

    camera: from --calib / --intrinsics for every sequence; None = each input's own
    calibration (its layout's: :mod:`geonet_infer.io.layouts`), else the focal estimated from
    the footage (``estimate_intrinsics``), else the assumed intrinsics.
    """

    out_dir: str
    model: str | None = None
    precision: str = "fp32"
    backend: str = "onnxruntime"
    threads: int = 1
    tasks: tuple[str, ...] = TASKS
    batch_size: int = DEFAULT_BATCH_SIZE
    camera: Camera | None = None
    vis: bool = True  # depth colour maps and flow colour wheels
    outputs: tuple[str, ...] | None = None  # --outputs names (geonet_infer.output.layout); None: the default
    flow_method: str = "network"  # or "dis" (geonet_infer.classical)
    pose_method: str = "network"  # or "orbvo"
    estimate_intrinsics: bool = False  # --intrinsics estimate: each input's focal from its footage

    def options(self) -> dict:
        """What decides the outputs (stored in each ``.done``). The model is named by its graphs' sha256
        (``graphs``), not its folder: a resume after the model changed redoes the sequence
        (:func:`model_changed`); other options that differ are refused."""
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
            "graphs": graph_hashes(self.model, self.precision),
            "precision": self.precision,
            "backend": self.backend,
            "tasks": list(self.tasks),
            "batch_size": self.batch_size,
            "camera": cam,
            "vis": self.vis,
        }
        if self.estimate_intrinsics:  # recorded only when on: resuming an earlier job's folders stays possible
            options["estimate_intrinsics"] = True
        # only when not the networks: a .done written before these options existed stays resumable
        methods = {"flow_method": self.flow_method, "pose_method": self.pose_method}
        chosen = {} if self.outputs is None else {"outputs": sorted(self.outputs)}  # likewise
        return options | {k: v for k, v in methods.items() if v != "network"} | chosen


MODEL_KEYS = ("graphs", "model")  # how a .done names the model: its graphs' sha256 (before: its folder's path)


def graph_hashes(model: str | None, precision: str) -> dict[str, str]:
    """``precision/graph`` -> sha256 of every graph the run may use (all precisions for ``auto``)."""
    from geonet_infer.models import resolve_model
    from geonet_infer.models.manifest import load_manifest

    manifest = load_manifest(resolve_model(model), verify_files=False)
    sets = {p: g for p, g in manifest.graphs.items() if precision in (p, "auto")}
    return {f"{p}/{name}": entry.sha256 for p, graphs in sets.items() for name, entry in sorted(graphs.items())}


def model_changed(marker_options: dict, options: dict) -> str | None:
    """Why the model of a ``.done`` is not this job's (its graphs differ, or it names a folder only), or None."""
    before = marker_options.get("graphs")
    if not isinstance(before, dict):
        return f"its {MARKER_NAME} names the model by its folder, not by its graphs"
    if before != options["graphs"]:
        changed = sorted(
            k for k in before.keys() | options["graphs"].keys() if before.get(k) != options["graphs"].get(k)
        )
        return f"the model changed since the run ({', '.join(changed)} differ)"
    return None


def without_model(options: dict) -> dict:
    return {k: v for k, v in options.items() if k not in MODEL_KEYS}


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
    ``.geonet-predict``, :mod:`geonet_infer.output.ownership`; an older batch's ``.done`` list), then the markers
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
    for name in (*markers, MARKER_NAME):  # a marker's temp, from a writer stopped (SIGTERM, SIGKILL) mid-write
        for leftover in leftover_temps(folder / name):
            leftover.unlink()
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
        if camera is None and config.estimate_intrinsics:
            from geonet_infer.core.self_calibration import camera_from_footage

            frames = (frame.rgb for frame in source if frame.rgb is not None)
            camera, _ = camera_from_footage(frames)  # a refusal is in the assumed camera's source
        if camera is None:
            camera = source.own_camera()  # its layout's calibration (KITTI, EuRoC, TUM) or its side file
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

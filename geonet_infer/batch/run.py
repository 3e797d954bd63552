"""``run_batch``: plan the job, start a runner (:data:`RUNNERS`), collect results, write the summary."""

from __future__ import annotations

import contextlib
import json
import os
import platform
import sys
import time
import warnings
from collections.abc import Collection, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from geonet_infer import __version__
from geonet_infer.batch.local import LocalRunner
from geonet_infer.batch.ray import RayRunner
from geonet_infer.batch.units import (
    FAILURES_NAME,
    LOCK_NAME,
    BatchConfig,
    WorkUnit,
    check_counts,
    claim,
    expand_input_pairs,
    is_empty,
    model_changed,
    needs_own_calib,
    not_ours,
    owned,
    plan_units,
    read_marker,
    sequence_root,
    stale,
    without_model,
)
from geonet_infer.classical import check_methods, classical_tasks
from geonet_infer.core.predictor import TASKS, describe_skipped, resolve_tasks
from geonet_infer.core.tasks import needs_intrinsics
from geonet_infer.engines import usable_cpus
from geonet_infer.engines.cpu import isa_line
from geonet_infer.errors import InputError
from geonet_infer.io.atomic import atomic_write, signals_noted
from geonet_infer.io.calib import Camera
from geonet_infer.io.camera import ASSUMED_RULE
from geonet_infer.limits import DEFAULT_BATCH_SIZE, check_batch_size
from geonet_infer.output import ownership
from geonet_infer.output.layout import SUMMARY_NAME

# ----------------------------------------------------------------------------- the job
# name -> runner class. A runner has ``start(config, options, n_units, workers, threads, *, manifest,
# address, log)`` (a classmethod returning it, sized: ``workers``, ``threads``, ``limits``, ``address``),
# ``results(units)`` (each unit's result dict as it completes, None as a progress tick),
# ``live_frames()`` and ``close()``.
RUNNERS: dict[str, type[LocalRunner] | type[RayRunner]] = {LocalRunner.name: LocalRunner, RayRunner.name: RayRunner}


class _NoRunner:
    address = None

    def results(self, units):
        return iter(())

    def live_frames(self) -> int:
        return 0

    def close(self) -> None:
        pass


def _job_lock(out_dir: Path) -> ownership.PidLock:
    """OUT/.lock for the job's lifetime: the lock predict takes on its OUT (one rule,
    :mod:`geonet_infer.output.ownership`)."""
    return ownership.PidLock(
        out_dir / LOCK_NAME, "another geonet-infer batch job", "wait for it to finish, or pass another --out"
    )


def _write_failures(path: Path, records: list[dict]) -> None:
    with atomic_write(path) as tmp:
        tmp.write_text("".join(json.dumps(r) + "\n" for r in records))


@dataclass
class _Progress:
    total: int
    enabled: bool
    frames_done: int = 0
    bar: Any = field(default=None)  # a tqdm bar, made in __post_init__ (tqdm is imported lazily)

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


def check_out(out_dir: Path, units: list[WorkUnit]) -> None:
    """GeoNetError (exit 2) when OUT is, holds or is inside an input: batch writes (and
    deletes its own sequence folders) in OUT, and must never touch an input."""
    out_real = Path(os.path.realpath(out_dir))
    for unit in units:
        root = Path(os.path.realpath(sequence_root(Path(unit.path))))
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
        recorded = marker.get("options")
        before: dict = recorded if isinstance(recorded, dict) else {}
        if without_model(before) != without_model(options) or marker.get("input") != unit.path:
            what = (
                "input"
                if marker.get("input") != unit.path
                else "set of options (precision, engine, tasks, batch size, camera, flow or pose method, outputs)"
            )
            raise InputError(
                folder,
                f"was made with another {what} than this job has",
                "resume with the options of the first run, or pass another --out",
            )
        why = model_changed(before, options) or stale(marker, unit, folder, own_calib)
        if why:
            log(f"geonet-infer batch: note: {unit.name}: redoing it, {why}")
            redone.append({"sequence": unit.name, "reason": why})
            todo.append(unit)
            continue
        skipped.append(_result_of_marker(unit, marker, "skipped"))
    return todo, skipped, redone


def model_tasks(model_dir, graphs, tasks: Iterable[str] | None, log, classical: Iterable[str] = ()) -> tuple[str, ...]:
    """The tasks to run, resolved as ``predict`` does (:func:`geonet_infer.core.predictor.resolve_tasks`):
    given tasks the model cannot do are refused before any work; with ``None`` every task it can do,
    the others named in one line. ``classical``: tasks a classical method makes (DIS, ORB-VO)."""
    tasks, skipped = resolve_tasks(graphs, tasks, model_dir, classical=classical)
    if skipped:
        log(f"geonet-infer batch: skipping {describe_skipped(skipped)} in {model_dir}; running {', '.join(tasks)}")
    return tasks


def run_batch(
    inputs,
    out_dir,
    *,
    runner: str = "local",
    workers: int | None = None,
    threads: int | None = None,
    model: str | None = None,
    precision: str = "fp32",
    backend: str = "onnxruntime",
    tasks: tuple[str, ...] | None = None,
    batch_size: int = DEFAULT_BATCH_SIZE,
    camera: Camera | None = None,
    vis: bool = True,
    outputs: Collection[str] | None = None,
    flow_method: str = "network",
    pose_method: str = "network",
    estimate_intrinsics: bool = False,
    resume: bool = False,
    ray_address: str | None = None,
    progress: bool = True,
    log=None,
    engine: str | None = None,
) -> dict:
    """Run a batch job (see the package docstring); returns the summary (also OUT/summary.json).

    ``runner``: a name of :data:`RUNNERS` ("local" process pool, "ray" Ray Data); ``engine=`` is
    its deprecated 0.x name. ``outputs``: the --outputs names each sequence writes
    (:mod:`geonet_infer.output.layout`; None: the default set). ``flow_method`` / ``pose_method``:
    "network", or "dis" / "orbvo" (:mod:`geonet_infer.classical`), for every sequence.

    ``summary["exit_code"]``: 0 all good, 1 something failed (see failures.jsonl), 3 the
    operating system refused a write into OUT, 130 interrupted.
    Raises GeoNetError for bad usage (missing input, unknown model, an OUT that overlaps an
    input or holds files batch did not make, a resume with other options, a locked OUT);
    OSError after writing the summary when the OS refused a write (the job stops);
    KeyboardInterrupt after stopping the workers and writing the summary
    (``"interrupted": true``) when interrupted (Ctrl-C, or SIGTERM turned into it by the CLI);
    a later ``resume=True`` finishes.
    """
    from geonet_infer.models import resolve_model
    from geonet_infer.models.manifest import load_manifest, model_notice

    log = log or (lambda msg: print(msg, file=sys.stderr))
    if engine is not None:  # the 0.x name of ``runner``
        warnings.warn("run_batch(engine=...) is deprecated; pass runner=", DeprecationWarning, stacklevel=2)
        runner = engine
    runner_name = runner
    if runner_name not in RUNNERS:
        raise InputError(None, f"unknown runner {runner_name!r}", f"choose one of {', '.join(RUNNERS)}")
    check_batch_size(batch_size, "--batch-size")
    check_counts(workers, threads)
    pairs = expand_input_pairs(inputs)
    units = plan_units([p for p, _ in pairs], [c for _, c in pairs])
    model_dir = resolve_model(model)
    manifest = load_manifest(model_dir)
    graphs = manifest.graph_names(precision)  # bad --model / --precision: exit 2 before any work
    check_methods(flow_method, pose_method)
    tasks = model_tasks(model_dir, graphs, tasks, log, classical_tasks(tasks or TASKS, flow_method, pose_method))
    needing = needs_intrinsics(tasks, flow_method, pose_method)  # inputs without a calibration of their own
    lacking = [u.path for u in units if not u.calib and needs_own_calib(u.path)] if needing and camera is None else []
    if lacking and not estimate_intrinsics:  # they run with the assumed intrinsics (each summary.json records it)
        more = f" (and {len(lacking) - 1} more)" if len(lacking) > 1 else ""
        log(f"note: {lacking[0]}{more}: no calibration; intrinsics assumed ({ASSUMED_RULE})")
    out_dir = Path(os.path.abspath(out_dir))
    check_out(out_dir, units)
    claim(out_dir)

    probe = BatchConfig(
        out_dir=str(out_dir),
        model=model,
        precision=precision,
        backend=backend,
        tasks=tasks,
        batch_size=batch_size,
        camera=camera,
        vis=vis,
        outputs=None if outputs is None else tuple(sorted(outputs)),
        flow_method=flow_method,
        pose_method=pose_method,
        estimate_intrinsics=estimate_intrinsics,
    )
    options = probe.options()
    with _job_lock(out_dir):
        foreign = [u for u in units if (out_dir / u.name).exists() and not owned(out_dir / u.name)]
        for unit in foreign:
            if not is_empty(out_dir / unit.name):
                raise not_ours(out_dir / unit.name)
        active: LocalRunner | RayRunner | _NoRunner = _NoRunner()
        stream: Iterator[dict | None] = iter(())
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
            if todo:
                started_runner = RUNNERS[runner_name].start(
                    probe, options, len(todo), workers, threads, manifest=manifest, address=ray_address, log=log
                )
                n_workers, n_threads, limits = started_runner.workers, started_runner.threads, started_runner.limits
                active = started_runner
            bar = _Progress(len(todo), progress)
            started = time.perf_counter()
            stream = active.results(todo)
            with open(failures_path, "a") as failures_file:
                for result in stream:
                    if result is None:
                        bar.tick(active.live_frames(), failed=n_failed)
                        continue
                    results[result["index"]] = result
                    if result["failures"]:
                        failures_file.write("".join(json.dumps(r) + "\n" for r in result["failures"]))
                        failures_file.flush()
                    n_done += result["status"] == "done"
                    n_failed += result["status"] == "failed"
                    bar.frames_done += result["frames"]
                    bar.tick(active.live_frames(), done=1, failed=n_failed)
                    if result.get("os_error"):
                        os_error = OSError(*result["os_error"])
                        break
        except KeyboardInterrupt:
            interrupted = True
        except BaseException:
            with signals_noted():  # stopping the workers is not cut short by a second signal
                _stop(bar, stream, active)
            raise
        with signals_noted() as caught:  # nor is the summary
            _stop(bar, stream, active)
            interrupted = interrupted or bool(caught)
            # A worker can finish a sequence (its .done marker written) after the job stopped listening:
            # it is done on disk, and --resume skips it, so the summary counts it too, frames and row
            # alike (counted as done alone, an interrupted Ray job said "done 2" beside 20 frames).
            for u in todo:
                marker = None if u.index in results else read_marker(out_dir / u.name)
                if marker is not None:
                    results[u.index] = _result_of_marker(u, marker, "done")
                    n_done += 1
            wall = time.perf_counter() - started
            ordered = [results[u.index] for u in units if u.index in results]
            records = [r for res in ordered for r in res["failures"]]
            _write_failures(failures_path, records)  # final: in input order (appends came in completion order)
            frames = sum(r["frames"] for r in ordered if r["status"] == "done")
            summary = {
                "engine": runner_name,  # the key's 0.x name, kept: summary.json is read by scripts
                "workers": n_workers,
                "threads_per_worker": n_threads,
                "workers_requested": workers,
                "threads_per_worker_requested": threads,
                "limits": limits,
                "usable_cpus": usable_cpus(),
                "ray_address": getattr(active, "address", None),
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
                "model": str(Path(model_dir).resolve()),
                "graphs": options["graphs"],  # sha256 of each graph: what a --resume compares
                "model_notice": model_notice(manifest),  # synthetic-only model: how it does on real video
                "precision": precision,
                "backend": backend,  # per graph engine, precision and why: each sequence's summary.json
                "isa": isa_line(),
                "camera": "per input (its own calibration, if any)" if camera is None else camera.source,
                "per_sequence": [_sequence_row(r) for r in ordered],
                "versions": {"geonet_infer": __version__, "python": platform.python_version()},
                "exit_code": _exit_code(interrupted, os_error, bool(records or n_failed)),
            }
            with atomic_write(out_dir / SUMMARY_NAME) as tmp:
                tmp.write_text(json.dumps(summary, indent=2) + "\n")
    if interrupted:
        raise KeyboardInterrupt
    if os_error is not None:
        raise os_error
    return summary


def _result_of_marker(unit: WorkUnit, marker: dict, status: str) -> dict:
    """The result a sequence complete on disk stands for, from its ``.done`` marker."""
    return {
        "index": unit.index,
        "sequence": unit.name,
        "input": unit.path,
        "status": status,
        "frames": marker.get("frames", 0),
        "failures": marker.get("failures", []),
        "check": marker.get("check"),
        "camera": marker.get("camera"),
        "wall_s": 0.0,
    }


def _sequence_row(result: dict) -> dict:
    """One sequence's line in summary.json."""
    return {
        "sequence": result["sequence"],
        "input": result["input"],
        "status": result["status"],
        "frames": result["frames"],
        "failures": len(result["failures"]),
        "check": result.get("check"),  # does the flow explain the next frame? (geonet_infer.core.check)
        "camera": result.get("camera"),  # K at the input resolution and its source file (None: no camera)
        "wall_s": round(result["wall_s"], 3),
    }


def _exit_code(interrupted: bool, os_error: OSError | None, failed: bool) -> int:
    """130 interrupted, 3 the OS refused a write into OUT, 1 something failed, else 0."""
    if interrupted:
        return 130
    if os_error is not None:
        return 3
    return 1 if failed else 0


def _stop(bar, stream, active) -> None:
    """Close the progress bar, the result stream and the runner (workers stopped, unfinished folders removed)."""
    if bar is not None:
        bar.close()
    with contextlib.suppress(Exception):
        getattr(stream, "close", lambda: None)()
    with contextlib.suppress(Exception):
        active.close()

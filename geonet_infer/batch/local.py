"""The ``local`` runner of ``geonet-infer batch``: a process pool (spawn) on this machine; each
worker loads the predictor once and runs :func:`geonet_infer.batch.units.run_sequence`.
"""

from __future__ import annotations

import contextlib
import ctypes
import multiprocessing
import os
import signal
import sys
import threading
import time
from collections.abc import Iterator
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import asdict
from pathlib import Path

from geonet_infer.batch.units import (
    BatchConfig,
    WorkUnit,
    cap_workers,
    describe_error,
    discard,
    failed_result,
    memory_available,
    plan_workers,
    read_marker,
    run_sequence,
    worker_memory_bytes,
)
from geonet_infer.engines import usable_cpus

_WORKER: dict = {}


class _Stopped(BaseException):
    """Raised in a busy local worker by SIGTERM (the parent stops the job)."""


def _on_sigterm(signum, frame):
    # Once only: a SIGTERM sent to the whole group is followed by the job's own (stopping the pool); a
    # second _Stopped would cut the clean-up short, and escape to the pool's loop, which runs the next sequence.
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
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
    from geonet_infer.core.predictor import load

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
    try:
        return _run(unit)
    except _Stopped:  # also when it came in _run's own clean-up: the worker never takes another sequence
        out = Path(_WORKER["config"].out_dir) / unit.name
        if read_marker(out) is None:
            with contextlib.suppress(Exception):
                discard(out)
        os._exit(143)


def _run(unit: WorkUnit) -> dict:
    _WORKER["started"][unit.index] = os.getpid()
    _WORKER["busy"] = unit
    try:
        if _WORKER["predictor"] is None:
            return failed_result(unit, f"the worker could not load the model: {describe_error(_WORKER['load_error'])}")
        return run_sequence(unit, _WORKER["config"], _WORKER["predictor"], _count_frame, _WORKER["options"])
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


class LocalRunner:
    """A process pool (spawn); each worker loads the predictor once (initializer)."""

    name = "local"
    # exit codes of pool processes that did not crash: idle or stopped by SIGTERM (ours or the pool's)
    _NOT_CRASHED = (None, 0, 143, -signal.SIGTERM)

    def __init__(self, config: BatchConfig, options: dict, workers: int):
        self.config, self.options, self.workers = config, options, workers
        self.threads = config.threads
        self.limits: list[str] = []  # why the requested workers or threads were lowered
        self.address = None
        self._ctx = _context()
        self._frames = self._ctx.Value("q", 0)
        self._executor: ProcessPoolExecutor | None = None

    @classmethod
    def start(
        cls,
        config: BatchConfig,
        options: dict,
        n_units: int,
        workers: int | None,
        threads: int | None,
        *,
        manifest,
        address: str | None = None,
        log,
    ) -> LocalRunner:
        """A pool sized for ``n_units`` sequences: capped by the usable CPUs and the memory one worker
        needs (:func:`cap_workers`); the pool starts with :meth:`results`."""
        cpus = usable_cpus()
        capped_w, capped_t, limits = cap_workers(
            workers,
            threads,
            cpus=cpus,
            mem_available=memory_available(),
            per_worker=worker_memory_bytes(manifest, config.precision),
            n_units=n_units,
        )
        for note in limits:
            log(f"geonet-infer batch: warning: {note}")
        n_workers, n_threads = plan_workers(n_units, capped_w, capped_t)
        if n_workers * n_threads > cpus:
            log(f"geonet-infer batch: note: {n_workers} workers x {n_threads} threads > {cpus} usable CPUs")
        runner = cls(
            BatchConfig(**{**asdict(config), "camera": config.camera, "threads": n_threads}), options, n_workers
        )
        runner.limits = limits
        return runner

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
                        result = failed_result(unit, f"worker error: {describe_error(exc)}")
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
                    yield failed_result(
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
                                discard(folder)
                        yield failed_result(
                            unit,
                            "the worker process died while predicting this sequence"
                            + (f" (exit code {code})" if code not in (None, 143) else ""),
                        )
                        continue
                todo.append(unit)

"""How many workers and threads a batch job runs: CPUs, memory per worker, the caps."""

from __future__ import annotations

import contextlib
from pathlib import Path

from geonet_infer.engines import usable_cpus
from geonet_infer.errors import InputError

MAX_WORKERS = 1024  # workers or threads per worker above this are a typo, not a machine
# Peak memory of one local worker, estimated as a base plus a multiple of the model's graph files
# (weights, onnxruntime's copies and arenas). Measured: 447 MB for the bundled small_synth model
# (20 MB of fp32 graphs), 128x416 frames, batch size 4, all tasks; the estimate gives 461 MB.
WORKER_BASE_BYTES = 256 * 1024**2
WORKER_GRAPH_FACTOR = 10


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

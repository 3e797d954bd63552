"""A small latency harness: warm-up, GC off while timing, percentiles, block interleaving, RSS.

numpy and the standard library only (the runtime never needs torch). Used by
``geonet-infer bench`` and by ``benchmarks/peers.py``.

Method (the one behind ``../shared/reference/cpu_latency_anchors.md``):

* every case is warmed up first (``warmup`` untimed calls);
* cases are then timed **block-interleaved**: in each round every case (in a
  rotating order) gets ``block`` back-to-back timed calls, so slow drift of a
  shared or virtual machine is spread over all cases instead of hitting one;
* before each block, optionally, the process waits until it is quiet (its own
  CPU time stops growing: thread pools that spin after a run would otherwise
  steal a core from the next case) and re-warms the case with untimed calls for
  at least ``rewarm_ms`` (a 2-vCPU guest adds vCPU wake-up time to the first
  call after an idle gap);
* each sample is the wall time of one synchronous call (``perf_counter_ns``),
  with Python's garbage collector disabled;
* statistics: p50/p90/p99 (linear interpolation), mean, sample std, min, max.
"""

from __future__ import annotations

import gc
import math
import os
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field

import numpy as np

try:  # Unix only
    import resource
except ImportError:  # pragma: no cover - Windows
    resource = None  # type: ignore[assignment]  # peak_rss_mib reports None then

PERCENTILES = (50, 90, 99)


@dataclass(frozen=True)
class Stats:
    """Latency statistics of one case, in ms per call.

    ``items_per_call`` is what one call processes (the batch, or the frames of a
    sequence); ``fps`` = items_per_call * 1000 / mean_ms (throughput).
    """

    n: int
    p50_ms: float
    p90_ms: float
    p99_ms: float
    mean_ms: float
    std_ms: float
    min_ms: float
    max_ms: float
    fps: float
    items_per_call: int = 1

    def as_dict(self) -> dict:
        return asdict(self)

    def scaled(self, factor: float) -> Stats:
        """The same statistics with every time multiplied by ``factor`` (e.g. 1 / frames: per-frame ms)."""
        return Stats(
            n=self.n,
            p50_ms=self.p50_ms * factor,
            p90_ms=self.p90_ms * factor,
            p99_ms=self.p99_ms * factor,
            mean_ms=self.mean_ms * factor,
            std_ms=self.std_ms * factor,
            min_ms=self.min_ms * factor,
            max_ms=self.max_ms * factor,
            fps=self.fps,
            items_per_call=self.items_per_call,
        )


def summarize(samples_ns: Sequence[int], items_per_call: int = 1) -> Stats:
    """Statistics of per-call wall times in nanoseconds."""
    if len(samples_ns) == 0:
        raise ValueError("no samples to summarize")
    if items_per_call < 1:
        raise ValueError(f"items_per_call must be >= 1, got {items_per_call}")
    ms = np.asarray(samples_ns, dtype=np.float64) / 1e6
    p50, p90, p99 = (float(v) for v in np.percentile(ms, PERCENTILES))
    mean = float(ms.mean())
    std = float(ms.std(ddof=1)) if ms.size > 1 else 0.0
    return Stats(
        n=int(ms.size),
        p50_ms=p50,
        p90_ms=p90,
        p99_ms=p99,
        mean_ms=mean,
        std_ms=std,
        min_ms=float(ms.min()),
        max_ms=float(ms.max()),
        fps=items_per_call * 1000.0 / mean if mean > 0 else math.inf,
        items_per_call=items_per_call,
    )


class gc_disabled:
    """Context manager: Python's cyclic GC off inside (restored to its previous state after)."""

    def __enter__(self):
        self._was_enabled = gc.isenabled()
        gc.collect()
        gc.disable()
        return self

    def __exit__(self, *exc):
        if self._was_enabled:
            gc.enable()


def wait_quiet(max_cpu_ms: float = 0.5, window_ms: float = 5.0, timeout_ms: float = 500.0) -> float:
    """Wait until this process used < ``max_cpu_ms`` CPU (all its threads) in a ``window_ms`` window.

    ORT's intra-op workers (with spinning on), libgomp and TBB keep spinning for
    milliseconds after a call; on 2 cores that steals a core from the next call.
    Returns the ms waited (at most about ``timeout_ms``; then it gives up).
    """
    start = time.perf_counter_ns()
    while True:
        cpu0 = time.process_time_ns()
        time.sleep(window_ms / 1e3)
        if (time.process_time_ns() - cpu0) / 1e6 < max_cpu_ms:
            break
        if (time.perf_counter_ns() - start) / 1e6 > timeout_ms:
            break
    return (time.perf_counter_ns() - start) / 1e6


@dataclass
class Case:
    """One thing to time: ``fn()`` makes one synchronous call processing ``items_per_call`` items."""

    name: str
    fn: Callable[[], object]
    items_per_call: int = 1
    samples_ns: list[int] = field(default_factory=list)
    warmup_ms: float = 0.0  # wall time of the warm-up calls (the first one includes one-off costs)
    first_call_ms: float = 0.0

    def stats(self) -> Stats:
        return summarize(self.samples_ns, self.items_per_call)


def _call_ns(fn: Callable[[], object]) -> int:
    t0 = time.perf_counter_ns()
    fn()
    return time.perf_counter_ns() - t0


def time_interleaved(
    cases: Sequence[Case],
    *,
    warmup: int = 3,
    iters: int = 20,
    block: int = 4,
    quiet: bool = True,
    rewarm_ms: float = 50.0,
    progress: Callable[[str], None] | None = None,
) -> list[Case]:
    """Time every case ``iters`` times, block-interleaved (see the module docstring).

    Args:
        cases: the callables; their ``samples_ns`` are filled in place (and returned).
        warmup: untimed calls per case before any timing (>= 0).
        iters: timed calls per case (>= 1).
        block: timed back-to-back calls per case per round (the last round may be shorter).
        quiet: wait for this process to be quiet before each block.
        rewarm_ms: before each block, untimed calls for at least this long (>= 1 call); 0 = none.
        progress: called with a short message per case and round (e.g. print to stderr).
    """
    if iters < 1:
        raise ValueError(f"iters must be >= 1, got {iters}")
    if warmup < 0:
        raise ValueError(f"warmup must be >= 0, got {warmup}")
    if block < 1:
        raise ValueError(f"block must be >= 1, got {block}")
    for case in cases:
        case.samples_ns = []
        t0 = time.perf_counter_ns()
        for i in range(warmup):
            ns = _call_ns(case.fn)
            if i == 0:
                case.first_call_ms = ns / 1e6
        case.warmup_ms = (time.perf_counter_ns() - t0) / 1e6
    rounds = -(-iters // block)
    for r in range(rounds):
        n = min(block, iters - r * block)
        shift = r % len(cases) if cases else 0
        for case in list(cases[shift:]) + list(cases[:shift]):
            if progress:
                progress(f"round {r + 1}/{rounds}: {case.name}")
            if quiet:
                wait_quiet()
            if rewarm_ms > 0:
                t0 = time.perf_counter_ns()
                while True:
                    case.fn()
                    if (time.perf_counter_ns() - t0) / 1e6 >= rewarm_ms:
                        break
            with gc_disabled():
                for _ in range(n):
                    case.samples_ns.append(_call_ns(case.fn))
    return list(cases)


def measure(fn: Callable[[], object], *, warmup: int = 3, iters: int = 20, items_per_call: int = 1) -> Stats:
    """Time one callable: ``warmup`` untimed calls, then ``iters`` timed back-to-back calls (GC off)."""
    case = Case("case", fn, items_per_call)
    time_interleaved([case], warmup=warmup, iters=iters, block=iters, quiet=False, rewarm_ms=0)
    return case.stats()


# ----------------------------------------------------------------------------- memory
def peak_rss_mib() -> float | None:
    """Peak resident set size of this process so far (``getrusage``; monotonic), MiB; None without it."""
    if resource is None:
        return None
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / 2**20 if sys.platform == "darwin" else peak / 2**10  # bytes on macOS, KiB on Linux


def current_rss_mib() -> float | None:
    """Current resident set size (``/proc/self/statm``), MiB; None where /proc is missing."""
    try:
        with open("/proc/self/statm") as f:
            pages = int(f.read().split()[1])
        return pages * os.sysconf("SC_PAGE_SIZE") / 2**20
    except (OSError, ValueError, IndexError):
        return None


def load_average() -> list[float] | None:
    """1, 5 and 15 minute load averages (None where unavailable): was the machine quiet?"""
    try:
        return [round(v, 2) for v in os.getloadavg()]
    except (OSError, AttributeError):
        return None

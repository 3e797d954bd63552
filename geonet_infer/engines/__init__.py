"""Inference engines behind the Predictor: one ONNX file -> ``run(feeds) -> {output name: array}``.

One module per engine, collected by name in :data:`ENGINES` (order matters: the first is
the default and the always-installed reference):

* ``onnxruntime`` (:mod:`.onnxruntime`, always installed): sessions from
  :func:`geonet_infer.engines.onnxruntime.make_session`.
* ``openvino`` (:mod:`.openvino`, extra ``geonet-infer[openvino]``): the same ONNX files
  compiled by OpenVINO's CPU plugin, f32 inference precision forced.
* ``auto`` (not an engine): times every installed engine on each graph at load and keeps
  the fastest per graph (:func:`pick_fastest`); onnxruntime alone when no other is installed.

What the CLI (``--backend`` choices, ``info``, ``bench``) reads, without importing any backend
library itself::

    for cls in ENGINES.values():
        cls.name            # "openvino": the registry key and the --backend value
        cls.available()     # False when its optional package is not installed
        cls.version()       # its package's version, or None when not installed
        cls.install_hint    # "pip install 'geonet-infer[openvino]'"
        cls.requires        # "the OpenVINO runtime": what is missing when available() is False
        cls.summary         # the engine in --backend's help text

and an engine (``make_engine(path, name, threads, streams)`` or ``pick_fastest(path, threads, streams=)``) has
``name``, ``input_names``, ``output_names``, ``run(feeds)``, ``only(outputs)``, ``io()``,
``input_shapes()`` and ``describe()`` (:class:`Engine`).

Adding an engine is one new module plus one registry line. A TensorRT engine, say, would be
``engines/tensorrt.py``::

    class TensorRtEngine:
        name = "tensorrt"
        summary = "tensorrt (pip install 'geonet-infer[tensorrt]', NVIDIA GPUs)"
        requires = "TensorRT"
        install_hint = "pip install 'geonet-infer[tensorrt]'"

        @staticmethod
        def available() -> bool: ...   # try: import tensorrt -- lazily, never at module top

        @staticmethod
        def version() -> str | None: ...

        def __init__(self, path, threads, streams=1):  # raise BackendUnavailableError(None, ..., install_hint)
            ...                             # when not available(); ModelError for a bad file
        # run / only / io / input_shapes / describe as in the Engine protocol

and in this file ``ENGINES[TensorRtEngine.name] = TensorRtEngine`` (next to the others):
``--backend tensorrt``, ``auto``, ``info`` and ``bench`` then offer it.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from functools import partial
from pathlib import Path
from typing import Protocol

import numpy as np

from geonet_infer.engines.onnxruntime import OrtEngine, make_session, make_session_options, ort_io
from geonet_infer.engines.openvino import OpenVinoEngine, openvino_available, openvino_version
from geonet_infer.engines.timing import Case, time_interleaved
from geonet_infer.errors import GeoNetError, InputError
from geonet_infer.models.manifest import AUTO, IoSpec, Manifest, check_graph_io

__all__ = [
    "AUTO",
    "BACKENDS",
    "ENGINES",
    "Engine",
    "OpenVinoEngine",
    "OrtEngine",
    "check_graphs",
    "make_engine",
    "openvino_available",
    "openvino_version",
    "pick_fastest",
    "timing_feeds",
    "usable_cpus",
]


def usable_cpus() -> int:
    """CPUs this process may run on: its affinity mask, capped by a cgroup v2/v1 CPU quota.

    ``os.cpu_count()`` reports the host's CPUs, which oversubscribes a container
    limited by a quota or a cpuset (onnxruntime issues #29510, #10273).
    """
    try:
        cpus = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        cpus = os.cpu_count() or 1
    quota = _cgroup_quota()
    return max(1, min(cpus, quota)) if quota else max(1, cpus)


def check_threads(value, name: str = "threads") -> int:
    """Threads per graph: at most the CPUs this process may use (oversubscribed onnxruntime pools spin
    against each other: 5000 threads ran 300 s for 6 frames and took 100 s to load)."""
    cpus = usable_cpus()
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise InputError(None, f"{name} must be a positive integer, got {value!r}", f"e.g. {cpus}")
    if value > cpus:
        raise InputError(
            None,
            f"{name} {value} is more than the {cpus} CPUs this process may use",
            f"pass {cpus} or fewer (or leave it out: the default is {cpus})",
        )
    return value


def _cgroup_quota() -> int | None:
    """CPUs allowed by the cgroup CPU quota (rounded up), or None if unlimited/unknown."""
    try:  # cgroup v2: "max 100000" or "150000 100000"
        quota, period = Path("/sys/fs/cgroup/cpu.max").read_text().split()[:2]
        if quota != "max":
            return -(-int(quota) // int(period))
        return None
    except (OSError, ValueError):
        pass
    try:  # cgroup v1
        quota_us = int(Path("/sys/fs/cgroup/cpu/cpu.cfs_quota_us").read_text())
        period_us = int(Path("/sys/fs/cgroup/cpu/cpu.cfs_period_us").read_text())
        return -(-quota_us // period_us) if quota_us > 0 and period_us > 0 else None
    except (OSError, ValueError):
        return None


class Engine(Protocol):
    """One ONNX graph loaded by one backend. Feeds and outputs are float32 arrays keyed by the
    graph's input/output names; the batch dimension is free."""

    name: str
    summary: str
    requires: str
    install_hint: str
    input_names: list[str]
    output_names: list[str]

    def __init__(self, path: str | Path, threads: int | None, streams: int = 1) -> None:
        """``threads`` per call; ``streams``: calls the engine runs at once from as many Python threads
        (throughput mode; onnxruntime sessions take concurrent calls as they are)."""

    @staticmethod
    def available() -> bool: ...

    @staticmethod
    def version() -> str | None: ...

    def run(self, feeds: dict[str, np.ndarray]) -> dict[str, np.ndarray]: ...

    def only(self, outputs: Sequence[str]) -> Engine:
        """The same graph on the same threads computing only ``outputs`` and what they need (a graph
        engine runs every node whatever outputs a call asks for)."""

    def io(self) -> tuple[list[IoSpec], list[IoSpec]]: ...

    def input_shapes(self) -> dict[str, list]: ...

    def describe(self) -> dict: ...


# name -> engine class; the first is the default backend and what "auto" falls back to
ENGINES: dict[str, type[Engine]] = {
    OrtEngine.name: OrtEngine,
    OpenVinoEngine.name: OpenVinoEngine,
}
BACKENDS = (*ENGINES, AUTO)  # what load(backend=) and --backend accept
# auto takes another candidate than the reference (the first engine, FP32) only when its fastest call
# beats the reference's by more than this: at load, on random inputs, a tie within a few % can still go
# either way on real frames (ORT DepthNet INT8 vs FP32 here: 1-8 % apart at load, INT8 6 % slower end to end)
REFERENCE_MARGIN = 0.05


def make_engine(path: str | Path, backend: str, threads: int | None, streams: int = 1) -> Engine:
    """The engine ``backend`` (a key of :data:`ENGINES`) for one graph file.

    Raises InputError for an unknown name, BackendUnavailableError (from the engine) when its
    package is not installed, ModelError when the file is missing or unreadable.
    """
    if backend not in ENGINES:
        raise InputError(None, f"unknown backend {backend!r}", f"choose one of {', '.join(BACKENDS)}")
    return ENGINES[backend](path, threads, streams)


def timing_feeds(engine: Engine, seed: int = 0) -> dict[str, np.ndarray]:
    """Batch-1 inputs of realistic range for timing a graph: images ~N(0, 0.5), depth 10 m, zero pose,
    a pinhole K with fx = fy = W centred on the image."""
    rng = np.random.default_rng(seed)
    shapes = {
        name: [d if isinstance(d, int) and d > 0 else 1 for d in shape] for name, shape in engine.input_shapes().items()
    }
    h, w = next(s[-2:] for s in shapes.values() if len(s) == 4)
    feeds = {}
    for name, shape in shapes.items():
        if name == "intrinsics":
            value = np.broadcast_to(np.array([[w, 0, w / 2], [0, w, h / 2], [0, 0, 1]]), shape)
        elif name == "depth":
            value = np.full(shape, 10.0)
        elif name == "pose":
            value = np.zeros(shape)
        else:
            value = rng.normal(0.0, 0.5, shape)
        feeds[name] = np.ascontiguousarray(value, dtype=np.float32)
    return feeds


def _first_line(exc: Exception) -> str:
    return str(exc).splitlines()[0][:200]


def pick_fastest(
    files: str | Path | dict[str, Path],
    threads: int | None,
    skip: dict[str, str] | None = None,
    engines: list[str] | None = None,
    streams: int = 1,
) -> tuple[Engine, dict]:
    """The fastest engine for one graph on this machine (batch 1), and the record behind the choice.
    ``streams``: what each engine is made with (:class:`Engine`); the timing is one call at a time.

    ``files``: the graph's file, or {precision: file} (``precision="auto"``: the precision is chosen
    too; the first precision is the reference). ``engines``: the engine names to consider (default:
    every one of :data:`ENGINES`; the first given is the reference). Candidates are labelled by engine
    name, or "engine precision" when several precisions are given; ``skip`` maps a label to why it is
    not accurate on this CPU. Every installed candidate is timed against the reference, interleaved.

    The choice is the lowest ``min_ms_batch1``, unless it beats the reference's by at most
    :data:`REFERENCE_MARGIN` (then the reference runs). The record is ``{"chosen": engine name, "precision": ...,
    "min_ms_batch1": {label: ms}, "p50_ms_batch1": {label: ms}}``, or
    ``{"chosen": reference, "precision": ..., "reason": ...}`` when nothing else can be timed or one
    candidate fails to load or run (then the reference runs). "skipped" lists the candidates left out.
    Timing noise only matters when two are within a few %.
    """
    skip = skip or {}
    by_precision = files if isinstance(files, dict) else {"": Path(files)}
    names = engines or list(ENGINES)
    labels = {
        (engine, precision): engine if len(by_precision) == 1 else f"{engine} {precision}"
        for precision in by_precision
        for engine in names
    }
    (first_engine, first_precision), *others = labels
    fallback = ENGINES[first_engine](by_precision[first_precision], threads, streams)
    skipped = sorted({f"{e} not installed" for e, _ in others if not ENGINES[e].available()})
    skipped += [f"{labels[c]}: {skip[labels[c]]}" for c in others if ENGINES[c[0]].available() and labels[c] in skip]
    others = [c for c in others if ENGINES[c[0]].available() and labels[c] not in skip]

    def record(engine: str, precision: str, **rest) -> dict:
        return {"chosen": engine, **({"precision": precision} if precision else {}), **rest}

    if not others:
        return fallback, record(first_engine, first_precision, reason="; ".join(skipped))
    try:
        candidates = {labels[first_engine, first_precision]: fallback}
        candidates.update({labels[e, p]: ENGINES[e](by_precision[p], threads, streams) for e, p in others})
        feeds = timing_feeds(fallback)
        cases = [Case(label, partial(engine.run, feeds)) for label, engine in candidates.items()]
        # interleaved blocks, so all see the same background load; no quiet-wait at load time
        time_interleaved(cases, warmup=3, iters=12, block=4, quiet=False, rewarm_ms=0)
    except GeoNetError:
        raise
    except Exception as exc:  # noqa: BLE001 -- any failure of another candidate means: use the reference
        failed = ", ".join(labels[c] for c in others)
        return fallback, record(first_engine, first_precision, reason=f"{failed} failed: {_first_line(exc)}")
    p50 = {case.name: case.stats().p50_ms for case in cases}
    # the fastest call of each: other work on the machine only ever adds time, so the minimum is the
    # least disturbed estimate of each candidate's own cost (the median follows the load)
    fastest = {case.name: case.stats().min_ms for case in cases}
    best = min(fastest, key=lambda label: fastest[label])
    reference = labels[first_engine, first_precision]
    if fastest[best] > (1 - REFERENCE_MARGIN) * fastest[reference]:
        best = reference  # within timing noise of the reference: keep it (FP32 on onnxruntime, the exact one)
    engine, precision = next(c for c, label in labels.items() if label == best)
    result = record(
        engine,
        precision,
        min_ms_batch1={k: round(v, 3) for k, v in fastest.items()},
        p50_ms_batch1={k: round(v, 3) for k, v in p50.items()},
    )
    if skipped:
        result["skipped"] = skipped
    return candidates[best], result


def check_graphs(manifest: Manifest) -> None:
    """Load every graph file the manifest lists in onnxruntime (no optimisation: only its declared
    inputs and outputs are read) and compare them with the manifest (:func:`check_graph_io`)."""
    seen = set()
    for precision, graphs in manifest.graphs.items():
        for name, entry in graphs.items():
            path = manifest.path(name, precision)
            if (path, entry) in seen:
                continue
            seen.add((path, entry))
            session = make_session(path, make_session_options(threads=1, opt_level="disable"))
            check_graph_io(entry, path, *ort_io(session))

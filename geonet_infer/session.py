"""The one onnxruntime session factory of the package (export checks, tests and the runtime use it).

CPU facts behind the defaults (``../shared/reference/onnx_notes.md`` section 2):

* ``intra_op_num_threads=0`` (ORT default) sizes the pool to the host's physical
  cores and pins threads; setting a number disables pinning. GeoNet runs several
  sessions one after another per frame, so each may use all cores.
* Spinning is ORT's default and burns CPU between runs; it slows co-located
  work (numpy pre-processing, other sessions). Off by default here.
* ``inter_op_num_threads`` only matters for ``ORT_PARALLEL``; we keep sequential
  execution and 1 inter-op thread.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import onnxruntime as ort

from geonet_infer.errors import InputError, ModelError

OPT_LEVELS = {
    "disable": ort.GraphOptimizationLevel.ORT_DISABLE_ALL,
    "basic": ort.GraphOptimizationLevel.ORT_ENABLE_BASIC,
    "extended": ort.GraphOptimizationLevel.ORT_ENABLE_EXTENDED,
    "all": ort.GraphOptimizationLevel.ORT_ENABLE_ALL,
}


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


def make_session_options(
    threads: int | None = None, spinning: bool = False, opt_level: str = "all"
) -> ort.SessionOptions:
    """SessionOptions for CPU inference.

    Args:
        threads: intra-op threads; None = ORT's default (one per physical core).
        spinning: let idle pool threads spin (lower latency, burns CPU).
        opt_level: "disable" | "basic" | "extended" | "all" (graph optimisations).
    """
    if opt_level not in OPT_LEVELS:
        raise InputError(None, f"unknown optimisation level {opt_level!r}", f"choose one of {', '.join(OPT_LEVELS)}")
    if threads is not None and (not isinstance(threads, int) or threads < 1):
        raise InputError(None, f"threads must be a positive integer or None, got {threads!r}")
    so = ort.SessionOptions()
    so.graph_optimization_level = OPT_LEVELS[opt_level]
    so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    so.inter_op_num_threads = 1
    if threads is not None:
        so.intra_op_num_threads = threads
    flag = "1" if spinning else "0"
    so.add_session_config_entry("session.intra_op.allow_spinning", flag)
    so.add_session_config_entry("session.inter_op.allow_spinning", flag)
    so.log_severity_level = 3  # errors only; warnings about unused initialisers are noise
    return so


def make_session(
    path: str | Path, options: ort.SessionOptions | None = None, providers: Sequence[str] = ("CPUExecutionProvider",)
) -> ort.InferenceSession:
    """Load an ONNX graph; errors name the file.

    Raises GeoNetError if the file is missing or onnxruntime cannot load it,
    or if a requested execution provider did not become active.
    """
    path = Path(path)
    if not path.is_file():
        raise ModelError(path, "ONNX model not found", "export models with `python -m export`")
    try:
        session = ort.InferenceSession(
            str(path), sess_options=options or make_session_options(), providers=list(providers)
        )
    except Exception as exc:  # ORT raises Fail / InvalidProtobuf / InvalidGraph / RuntimeException
        raise ModelError(
            path,
            f"onnxruntime cannot load this model ({exc.__class__.__name__}: {str(exc).splitlines()[0][:300]})",
            "the file is corrupt or was written by an incompatible exporter; re-export it",
        ) from exc
    missing = [p for p in providers if p not in session.get_providers()]
    if missing:
        raise ModelError(
            path, f"execution provider(s) {missing} not active", f"available: {ort.get_available_providers()}"
        )
    return session

"""Moved to :mod:`geonet_infer.bench` (issue 42): cases, report and environment.

This alias goes in the next release; each use of an old name warns (DeprecationWarning). The
project's speed targets (``SPEED_TARGETS``, ``speed_targets``) left the runtime for
``benchmarks/speed_milestones.py`` in the source tree.
"""

from geonet_infer._moved import forward

__getattr__ = forward(
    __name__,
    "geonet_infer.bench.cases",
    "geonet_infer.bench.report",
    "geonet_infer.bench.environment",
    renamed={"TASKS": "BENCH_TASKS"},
)

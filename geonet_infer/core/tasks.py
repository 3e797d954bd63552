"""The runtime's tasks, and what each needs: one place for the names and the rules.

``TASKS`` are what a model predicts for a sequence (``--tasks``, ``Predictor.resolve_tasks``); the
benchmark's timed cases (``geonet_infer.bench.cases.BENCH_TASKS``) and the eval's scored tasks
(``geonet_infer.eval.datasets.EVAL_TASKS``) are other lists, named apart.
"""

from __future__ import annotations

from collections.abc import Iterable

from geonet_infer.errors import InputError

TASKS = ("depth", "pose", "flow")


def parse_tasks(text: str) -> tuple[str, ...]:
    tasks = tuple(t.strip() for t in text.split(",") if t.strip())
    unknown = [t for t in tasks if t not in TASKS]
    if unknown or not tasks:
        raise InputError(None, f"unknown task(s) {unknown or text!r}", f"choose from {','.join(TASKS)}")
    return tasks


def needs_intrinsics(tasks: Iterable[str], flow_method: str = "network", pose_method: str = "network") -> list[str]:
    """What of ``tasks`` needs the camera intrinsics K: the network's flow (its rigid flow is made
    from depth, pose and K) and ORB-VO's poses; DIS flow, depth and PoseNet's poses do not. Where
    none are given or found, those run with the assumed intrinsics (:data:`geonet_infer.io.camera.ASSUMED_RULE`).
    The one rule for every caller (predict, batch, the API)."""
    tasks = set(tasks)
    needing = ["flow"] if "flow" in tasks and flow_method == "network" else []
    return needing + (["ORB-VO poses"] if "pose" in tasks and pose_method == "orbvo" else [])

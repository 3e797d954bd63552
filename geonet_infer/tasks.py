"""The runtime's tasks, and what each needs: one place for the names and the rules.

``TASKS`` are what a model predicts for a sequence (``--tasks``, ``Predictor.resolve_tasks``); the
benchmark's timed cases (``geonet_infer.bench.cases.BENCH_TASKS``) and the eval's scored tasks
(``geonet_infer.eval.datasets.EVAL_TASKS``) are other lists, named apart.
"""

from __future__ import annotations

from collections.abc import Iterable

from geonet_infer.errors import InputError

TASKS = ("depth", "pose", "flow")
API_K_HINT = "pass K (3x3) or a Camera"  # the hint of the API's intrinsics errors (the CLI's name its flags)


def parse_tasks(text: str) -> tuple[str, ...]:
    tasks = tuple(t.strip() for t in text.split(",") if t.strip())
    unknown = [t for t in tasks if t not in TASKS]
    if unknown or not tasks:
        raise InputError(None, f"unknown task(s) {unknown or text!r}", f"choose from {','.join(TASKS)}")
    return tasks


def needs_intrinsics(tasks: Iterable[str], flow_method: str = "network", pose_method: str = "network") -> list[str]:
    """What of ``tasks`` needs the camera intrinsics K: the network's flow (its rigid flow is made
    from depth, pose and K) and ORB-VO's poses; DIS flow, depth and PoseNet's poses do not. The one
    rule for every check (predict, batch, the API)."""
    tasks = set(tasks)
    needing = ["flow"] if "flow" in tasks and flow_method == "network" else []
    return needing + (["ORB-VO poses"] if "pose" in tasks and pose_method == "orbvo" else [])


def no_intrinsics(needing: list[str], where, hint: str, what: str = "none were found") -> InputError:
    """The one error for :func:`needs_intrinsics`' outputs without K ("flow needs camera intrinsics ...")."""
    verb = "needs" if len(needing) == 1 and not needing[0].endswith("poses") else "need"
    return InputError(where, f"{' and '.join(needing)} {verb} camera intrinsics and {what}", hint)

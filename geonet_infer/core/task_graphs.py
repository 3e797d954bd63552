"""Which graphs each task needs, and the tasks a model directory can do: the one resolution of
``tasks`` for the API, ``predict`` and each batch job."""

from __future__ import annotations

from collections.abc import Iterable

from geonet_infer.classical import (
    CLASSICAL_GRAPHS,
)
from geonet_infer.core.tasks import TASKS
from geonet_infer.errors import InputError, ModelError

# The graphs each task needs. A model directory may hold only some (a converted depth or pose
# release, `python -m export --graphs`). "flow" is GeoNet's full flow; the API's flow methods
# also run on RIGID_FLOW_GRAPHS alone and then return the rigid flow (residual None).
TASK_GRAPHS = {
    "depth": ("depthnet",),
    "pose": ("posenet",),
    "flow": ("depthnet", "posenet", "rigidflow", "resflownet"),
}
RIGID_FLOW_GRAPHS = ("depthnet", "posenet", "rigidflow")
METRIC_TASK = "metric scale (camera height)"  # fits the ground to depth: needs DepthNet


def missing_graphs(task: str, graphs: Iterable[str], classical: Iterable[str] = ()) -> tuple[str, ...]:
    """The graphs ``task`` needs that are not among ``graphs`` (empty: the task can run); a task in
    ``classical`` is made by a classical method (:data:`geonet_infer.classical.CLASSICAL_GRAPHS`)."""
    present = set(graphs)
    needed = CLASSICAL_GRAPHS[task] if task in tuple(classical) else TASK_GRAPHS[task]
    return tuple(g for g in needed if g not in present)


def require_graphs(task: str, needed: Iterable[str], graphs: Iterable[str], model_dir) -> None:
    """GeoNetError (one line naming the missing graphs and ``model_dir``) unless every graph
    ``task`` needs is among the model's ``graphs``."""
    graphs = tuple(graphs)
    missing = [g for g in needed if g not in graphs]
    if not missing:
        return
    leave = f"leave {task} out of the tasks" if task in TASKS else "drop the camera height"
    hint = f"{leave}, or use a model directory that holds {', '.join(missing)}"
    if "resflownet" in missing:
        hint += " (exported from a stage 'flow' checkpoint or the released geonet_resflownet)"
    raise ModelError(
        model_dir,
        f"{'task ' if task in TASKS else ''}{task} needs the {' and '.join(missing)} "
        f"graph{'s' if len(missing) > 1 else ''}, which this model lacks (it holds {', '.join(graphs)})",
        hint + f"; `geonet-infer info --model {model_dir}` lists what a model can do",
    )


def resolve_tasks(
    graphs: Iterable[str],
    tasks: Iterable[str] | None,
    model_dir,
    *,
    metric: bool = False,
    classical: Iterable[str] = (),
) -> tuple[tuple[str, ...], dict[str, tuple[str, ...]]]:
    """(tasks to run in canonical order, {task skipped: the graphs it lacks}) for a model holding ``graphs``.

    ``tasks=None``: every task the model can do, the others skipped; given tasks are all
    required (GeoNetError naming a missing graph) and none is skipped. ``metric``: a camera
    height will be given (it needs DepthNet whatever the tasks). ``classical``: tasks made by a
    classical method (DIS flow, ORB-VO poses: :mod:`geonet_infer.classical`), needing fewer graphs.
    """
    classical = tuple(classical)
    graphs = tuple(graphs)
    if metric:
        require_graphs(METRIC_TASK, TASK_GRAPHS["depth"], graphs, model_dir)
    if tasks is not None:
        tasks = list(tasks)
        unknown = [t for t in tasks if t not in TASKS]
        if unknown:
            raise InputError(None, f"unknown task(s) {unknown}", f"choose from {','.join(TASKS)}")
        for task in tasks:
            require_graphs(task, CLASSICAL_GRAPHS[task] if task in classical else TASK_GRAPHS[task], graphs, model_dir)
        return tuple(t for t in TASKS if t in tasks), {}
    skipped = {t: missing_graphs(t, graphs, classical) for t in TASKS if missing_graphs(t, graphs, classical)}
    if len(skipped) == len(TASKS):
        raise ModelError(
            model_dir,
            f"this model can do none of {', '.join(TASKS)} (it holds {', '.join(graphs)})",
            "export depthnet or posenet into it with `python -m export --graphs`",
        )
    return tuple(t for t in TASKS if t not in skipped), skipped


def describe_skipped(skipped: dict[str, tuple[str, ...]]) -> str:
    """'pose (no posenet graph), flow (no posenet, resflownet graphs)' for the notes of predict and batch."""
    return ", ".join(
        f"{task} (no {', '.join(graphs)} graph{'s' if len(graphs) > 1 else ''})" for task, graphs in skipped.items()
    )

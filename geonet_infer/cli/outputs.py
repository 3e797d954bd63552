"""``--outputs`` of ``predict`` and ``batch``: which files of the layout a run writes, and the tasks they need."""

from __future__ import annotations

import argparse

from geonet_infer.core.tasks import TASKS, parse_tasks
from geonet_infer.errors import InputError
from geonet_infer.output.layout import COMPACT_OUTPUTS, DEFAULT_OUTPUTS, OUTPUT_NAMES, chosen_outputs, output_tasks


def add_outputs_arg(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--outputs",
        default=None,
        metavar="LIST",
        help=f"comma list of the files to write, of {','.join(OUTPUT_NAMES)} (each one's file is in the "
        f"list of outputs above; default: {','.join(DEFAULT_OUTPUTS)}, as before this option; "
        f"the compact set is {','.join(COMPACT_OUTPUTS)}). Without --tasks, only the tasks these "
        "files need run. camera.txt and summary.json are always written, point clouds with --point-cloud",
    )


def tasks_and_outputs(args: argparse.Namespace) -> tuple[tuple[str, ...] | None, frozenset[str] | None]:
    """(--tasks, --outputs) as predict_to_dir takes them: without --tasks, --outputs names the tasks
    (and depth, pose for --point-cloud); with both, an output whose task does not run is an error."""
    tasks = None if args.tasks is None else parse_tasks(args.tasks)
    if args.outputs is None:
        return tasks, None
    outputs = chosen_outputs(args.outputs, vis=not args.no_vis)
    needed = set(output_tasks(outputs))
    point_cloud = getattr(args, "point_cloud", None)
    if tasks is None:
        needed |= {"depth"} if point_cloud else set()
        needed |= {"pose"} if point_cloud == "world" else set()
        return tuple(t for t in TASKS if t in needed), outputs
    lacking = [t for t in TASKS if t in needed and t not in tasks]
    if lacking:
        names = sorted(n for n in outputs if set(output_tasks([n])) & set(lacking))
        raise InputError(
            None,
            f"--outputs {','.join(names)} need(s) the task(s) {','.join(lacking)}, not in --tasks",
            "add them to --tasks, or leave those outputs out",
        )
    return tasks, outputs

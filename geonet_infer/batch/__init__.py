"""Batch inference: many sequences, one output folder, a runner: a local process pool or Ray Data.

``geonet-infer batch`` is a thin CLI over :func:`run_batch`. Every sequence goes through
:func:`geonet_infer.output.predict.predict_to_dir`, so ``OUT/<sequence>/`` has exactly the layout
of ``geonet-infer predict``; next to the sequences::

    OUT/.geonet-batch            ownership marker: batch made this folder (also in each OUT/<sequence>/)
    OUT/<sequence>/...           predict's layout (depth/, flow/, flow_vis/, poses_*.txt, summary.json)
    OUT/<sequence>/.done         completion record, written (atomically) after all the sequence's files:
                                 each output's size and sha256, and the inputs' names, sizes and mtimes
    OUT/failures.jsonl           one JSON object a line: {"sequence", "input", "frame" (or null), "reason"}
    OUT/summary.json             sequences done/failed/skipped, frames, frames/s, runner, workers, threads;
                                 per sequence its output check (summed up; per pair in its own summary.json)
    OUT/.lock                    the running job's pid (a second job on the same OUT stops with exit 2; one
                                 left by a killed job is taken over), removed when the job ends

Nothing is lost: batch only writes into a folder it made (or an empty one), refuses an OUT
that is, holds or is inside an input, and only ever deletes a sequence folder carrying its
ownership marker. Files are written under temporary names and renamed (``io.atomic``); a
sequence without ``.done`` is incomplete, and ``resume=True`` redoes it (its folder is
deleted first), and redoes a complete one whose outputs or inputs no longer match its
``.done``, while skipping the others. A failure (unreadable input or calibration, bad
frame, any exception in a worker, a worker process that died) is recorded and the job goes
on; the operating system refusing a write into OUT (disk full, read-only) stops the job
(exit 3). Work units are whole sequences: the frames of a sequence depend on each other
(pose and flow pair frame t with t + 1, and each frame's depth is reused).


Modules, each importing only the ones before it::

    units.py    work units, the folders batch owns in OUT, one sequence -> its folder (run_sequence)
    local.py    the "local" runner: a process pool on this machine
    ray.py      the "ray" runner: Ray Data with an actor pool (extra geonet-infer[ray])
    run.py      run_batch: plan, start a runner (RUNNERS), collect results, write the summary

A new runner is one module with a class like :class:`LocalRunner` (``name``, ``start``,
``results``, ``live_frames``, ``close``) plus one line in :data:`RUNNERS`.
"""

from geonet_infer.batch.local import LocalRunner
from geonet_infer.batch.ray import RayRunner, size_pool
from geonet_infer.batch.run import RUNNERS, check_out, model_tasks, run_batch
from geonet_infer.batch.units import (
    FAILURES_NAME,
    LIST_SUFFIX,
    MARKER_NAME,
    OWNER_NAME,
    WORKER_BASE_BYTES,
    BatchConfig,
    WorkUnit,
    cap_workers,
    expand_input_pairs,
    expand_inputs,
    needs_own_calib,
    plan_units,
    plan_workers,
    read_input_list,
    read_input_pairs,
    read_marker,
    run_sequence,
    sequence_name,
    worker_memory_bytes,
)

__all__ = [
    "FAILURES_NAME",
    "LIST_SUFFIX",
    "MARKER_NAME",
    "OWNER_NAME",
    "RUNNERS",
    "WORKER_BASE_BYTES",
    "BatchConfig",
    "LocalRunner",
    "RayRunner",
    "WorkUnit",
    "cap_workers",
    "check_out",
    "expand_input_pairs",
    "expand_inputs",
    "model_tasks",
    "needs_own_calib",
    "plan_units",
    "plan_workers",
    "read_input_list",
    "read_input_pairs",
    "read_marker",
    "run_batch",
    "run_sequence",
    "sequence_name",
    "size_pool",
    "worker_memory_bytes",
]

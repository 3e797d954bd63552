"""summary.json's latency table: where the wall time of a ``predict`` run went, per frame, adding up.

The main thread does one thing after another (read a frame, the networks, the ground-plane fit,
wait for the writer, encode the result video, ...): those stages add up to the wall time, and what
no stage timed is shown as ``untimed``. The writer threads (pictures, PNG encoding, file writes,
point clouds) run while the main thread goes on: their time is shown apart, as overlapped, and is
not part of the sum; the main thread's share of it is ``write_wait`` (blocked on a full queue).
In throughput mode the cascade runs on threads of its own too: its stages are shown apart as
``workers_<stage>``, and the main thread's share is ``cascade_wait``.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Iterator

from geonet_infer.classical import CLASSICAL_STAGES
from geonet_infer.core.spec import CASCADE_THREADS, STAGES

# the main thread's stages, in table order
SEQUENTIAL = (
    *[s for s in STAGES if s != "write"],
    "ground_fit",  # --camera-height: the ground-plane fit of each frame and the scaling by it
    *CLASSICAL_STAGES,
    "finite_check",  # every output checked finite (and depth not degenerate) before it is written
    "colour_scale",  # the pictures' steady colour scale, from the first frames (--colour-scale)
    "cascade_wait",  # throughput mode: waiting for the cascade threads' next batch
    "write_wait",  # blocked on the writer threads (their queue is full)
    "video",  # encoding the --video-out frames
    "rerun",  # logging the --rerun recording
    "world_cloud",  # placing the points of --point-cloud world and writing points_world.ply
    "finish",  # camera.txt and the pose files
)
OVERLAPPED = ("write", "write_cpu")  # the writer threads: wall time and CPU time, alongside the others
MEANINGS = {
    "write_wait": "main thread blocked on the writer",
    "cascade_wait": "main thread waiting for the cascade threads",
    "untimed": "not timed by a stage",
    "total": "wall time per frame",
    "write": "writer threads, overlapped: not in the total",
    "write_cpu": "their CPU time",
}


def meaning(stage: str) -> str:
    """What a row of the latency table is, where it needs saying ("" otherwise)."""
    if stage.startswith(CASCADE_THREADS):
        return "cascade threads, overlapped: not in the total"
    return MEANINGS.get(stage, "")


@contextlib.contextmanager
def timed(totals: dict[str, float], stage: str) -> Iterator[None]:
    """Add the block's wall time (ms) to ``totals[stage]``."""
    t0 = time.perf_counter()
    try:
        yield
    finally:
        totals[stage] += (time.perf_counter() - t0) * 1e3


def latency_table(totals: dict[str, float], frames: int, wall_s: float) -> tuple[dict, dict]:
    """(``timings_ms_per_frame``, ``overlapped_ms_per_frame``) from the run's summed ms per stage.

    The first adds up: its stages plus ``untimed`` are ``total``, the wall time per frame; the cascade
    threads' ``workers_<stage>`` (throughput mode) are overlapped."""
    n = max(frames, 1)
    sequential = {s: totals[s] / n for s in SEQUENTIAL if totals.get(s)}
    wall = wall_s * 1e3 / n
    sequential["untimed"] = wall - sum(sequential.values())
    sequential["total"] = wall
    workers = {s: ms / n for s, ms in totals.items() if s.startswith(CASCADE_THREADS) and ms}
    return sequential, {**workers, **{s: totals[s] / n for s in OVERLAPPED if totals.get(s)}}

"""The output folder of ``predict`` (and of each sequence of ``batch``): the ONE description of its files.

What a run lists as its own before writing (:mod:`geonet_infer.ownership`), summary.json's
``outputs`` and ``predict --help`` are all read off :data:`LAYOUT`.
"""

from __future__ import annotations

import textwrap
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from geonet_infer.errors import InputError

SUMMARY_NAME = "summary.json"
CAMERA_NAME = "camera.txt"
WORLD_CLOUD_NAME = "points_world.ply"
POSE_FILES = ("poses_kitti.txt", "poses_tum.txt")
OUTPUT_MARKER = ".geonet-predict"  # JSON: the files the run that owns OUT may write
OUTPUT_LOCK = ".geonet-predict.lock"  # the pid of the run writing into OUT now
FRAME = "{frame}"  # in a path of LAYOUT: one file per frame, named after it


@dataclass(frozen=True)
class Output:
    """One file (or one per frame) of the layout."""

    path: str  # relative to OUT; FRAME in it: one per frame
    when: str  # a key of _WRITTEN_WHEN
    what: str  # for --help


LAYOUT = (  # in the order summary.json lists them
    Output(
        CAMERA_NAME, "camera", "the intrinsics at the input resolution (P_rect_02, KITTI raw form; --calib reads it)"
    ),
    Output(f"points/{FRAME}.ply", "points", "the frame's points in its camera's frame (--point-cloud)"),
    Output(WORLD_CLOUD_NAME, "world", "every frame's points placed by the poses (--point-cloud world)"),
    Output(
        f"depth/{FRAME}.npy",
        "depth",
        "float32 depth at the input resolution (relative scale; metres with --camera-height)",
    ),
    Output(f"depth/{FRAME}.png", "depth_vis", "colour map (near = bright)"),
    Output(f"flow/{FRAME}.png", "flow", "KITTI 16-bit flow PNG, frame -> next frame"),
    Output(f"flow_vis/{FRAME}.png", "flow_vis", "flow colour wheel"),
    Output(POSE_FILES[0], "pose", "3x4 camera-to-world per frame (first frame = identity)"),
    Output(POSE_FILES[1], "pose", "time tx ty tz qx qy qz qw per frame"),
    Output(
        SUMMARY_NAME,
        "always",
        "counts, failures, per-stage timings, model, camera, the method behind each output "
        "(--flow-method, --pose-method), per-frame metric scales, and the output check: per pair of "
        "frames, does the flow (and the rigid flow from depth and pose) explain the next frame better "
        "than no motion at all?",
    ),
)


def _written(output: Output, tasks: Iterable[str], vis: bool, point_cloud: str | None, camera: bool) -> bool:
    """Whether a run with these settings writes ``output``."""
    tasks = set(tasks)
    return {
        "always": True,
        "camera": camera,
        "points": bool(point_cloud) and "depth" in tasks,
        "world": point_cloud == "world" and "depth" in tasks,
        "depth": "depth" in tasks,
        "depth_vis": "depth" in tasks and vis,
        "flow": "flow" in tasks,
        "flow_vis": "flow" in tasks and vis,
        "pose": "pose" in tasks,
    }[output.when]


def frame_files(name: str, tasks: Iterable[str], vis: bool, point_cloud: str | None = None) -> set[str]:
    """The files (relative to OUT) frame ``name`` may get."""
    return {
        o.path.replace(FRAME, name)
        for o in LAYOUT
        if FRAME in o.path and _written(o, tasks, vis, point_cloud, camera=False)
    }


def run_files(tasks: Iterable[str], point_cloud: str | None, camera: bool) -> set[str]:
    """The files (relative to OUT) written once per run, summary.json included."""
    return {o.path for o in LAYOUT if FRAME not in o.path and _written(o, tasks, True, point_cloud, camera)}


def listed_outputs(tasks: Iterable[str], vis: bool, point_cloud: str | None, camera: bool) -> list[str]:
    """summary.json's ``outputs``: the files of the run as patterns (``depth/*.npy``), summary.json left out."""
    tasks = tuple(tasks)
    return [
        o.path.replace(FRAME, "*")
        for o in LAYOUT
        if o.path != SUMMARY_NAME and _written(o, tasks, vis, point_cloud, camera)
    ]


def describe(width: int = 100) -> str:
    """The layout as ``predict --help`` shows it, one entry per file."""
    lines = []
    for o in LAYOUT:
        name = o.path.replace(FRAME, "<frame>")
        text = textwrap.wrap(o.what, width - 25)
        lines.append(f"  {name:<22} {text[0]}")
        lines += [" " * 25 + more for more in text[1:]]
    return "\n".join(lines)


def output_path(out_dir: Path, subdir: str, name: str, suffix: str) -> Path:
    """``out_dir/subdir/name+suffix``, refusing names that would leave ``out_dir``."""
    path = out_dir / subdir / f"{name}{suffix}"
    root = out_dir.resolve()
    if root not in path.resolve().parents or "/" in name or "\\" in name or name in ("", ".", ".."):
        raise InputError(path, f"frame name {name!r} would write outside {out_dir}", "rename the input file")
    return path

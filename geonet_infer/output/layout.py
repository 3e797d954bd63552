"""The output folder of ``predict`` (and of each sequence of ``batch``): the ONE description of its files.

What a run lists as its own before writing (:mod:`geonet_infer.output.ownership`), what the writer writes
(by each entry's ``--outputs`` name), summary.json's ``outputs`` and ``written``, and ``predict --help``
are all read off :data:`LAYOUT`.
"""

from __future__ import annotations

import textwrap
from collections.abc import Collection, Iterable
from dataclasses import dataclass
from pathlib import Path

from geonet_infer.errors import InputError
from geonet_infer.io.depth import DEPTH_SCALE

SUMMARY_NAME = "summary.json"
CAMERA_NAME = "camera.txt"
WORLD_CLOUD_NAME = "points_world.ply"
POSE_FILES = ("poses_kitti.txt", "poses_tum.txt")
OUTPUT_MARKER = ".geonet-predict"  # JSON: the files the run that owns OUT may write
OUTPUT_LOCK = ".geonet-predict.lock"  # the pid of the run writing into OUT now
FRAME = "{frame}"  # in a path of LAYOUT: one file per frame, named after it
DEPTH_PNG_MAX = 65535 / DEPTH_SCALE  # the deepest value a KITTI depth PNG holds (255.996)


@dataclass(frozen=True)
class Output:
    """One file (or one per frame) of the layout."""

    path: str  # relative to OUT; FRAME in it: one per frame
    when: str  # a key of _WRITTEN_WHEN
    what: str  # for --help
    name: str | None = None  # its name in --outputs; None: not chosen there (written whenever `when` holds)


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
        "depth-npy",
    ),
    Output(f"depth/{FRAME}.png", "depth", "colour map (near = bright)", "depth-vis"),
    Output(
        f"depth16/{FRAME}.png",
        "depth",
        f"KITTI depth PNG: 16-bit round(depth * {DEPTH_SCALE:g}), 0 = no value; depths beyond "
        f"{DEPTH_PNG_MAX:.3f} (65535 / {DEPTH_SCALE:g}) are clipped to it, so use --camera-height (metres) "
        "or check the range of relative depth",
        "depth-png16",
    ),
    Output(
        f"depth16/{FRAME}.npy",
        "depth",
        "float16 depth (half of depth-npy's bytes, ~3 significant digits)",
        "depth-npy16",
    ),
    Output(f"flow/{FRAME}.png", "flow", "KITTI 16-bit flow PNG, frame -> next frame", "flow-png"),
    Output(f"flow_vis/{FRAME}.png", "flow", "flow colour wheel", "flow-vis"),
    Output(POSE_FILES[0], "pose", "3x4 camera-to-world per frame (first frame = identity)", "poses"),
    Output(POSE_FILES[1], "pose", "time tx ty tz qx qy qz qw per frame", "poses"),
    Output(
        SUMMARY_NAME,
        "always",
        "counts, failures, per-stage timings, model, camera, the method behind each output "
        "(--flow-method, --pose-method), per-frame metric scales, the files written with their bytes per "
        "frame, and the output check: per pair of frames, does the flow (and the rigid flow from depth and "
        "pose) explain the next frame better than no motion at all?",
    ),
)
POINTS = next(o for o in LAYOUT if o.when == "points")  # the per-frame point clouds (--point-cloud)
OUTPUT_NAMES = tuple(dict.fromkeys(o.name for o in LAYOUT if o.name))  # --outputs, in layout order
VIS_OUTPUTS = ("depth-vis", "flow-vis")  # the pictures (--no-vis leaves them out)
DEFAULT_OUTPUTS = ("depth-npy", "depth-vis", "flow-png", "flow-vis", "poses")  # what predict always wrote
COMPACT_OUTPUTS = ("depth-png16", "flow-png", "poses")  # the smallest set that keeps every task's data


def chosen_outputs(text: str | Iterable[str] | None, vis: bool = True) -> frozenset[str]:
    """The --outputs names a run writes: ``text`` ("depth-png16,flow-png" or names; None = the default
    set), without the pictures when ``vis`` is False."""
    if text is None:
        names: tuple[str, ...] = DEFAULT_OUTPUTS
    elif isinstance(text, str):
        names = tuple(n.strip() for n in text.split(",") if n.strip())
    else:
        names = tuple(text)
    unknown = [n for n in names if n not in OUTPUT_NAMES]
    if unknown or not names:
        raise InputError(None, f"unknown output(s) {unknown or text!r}", f"choose from {','.join(OUTPUT_NAMES)}")
    return frozenset(n for n in names if vis or n not in VIS_OUTPUTS)


def output_tasks(outputs: Iterable[str]) -> tuple[str, ...]:
    """The tasks the named outputs need, in layout order (depth, flow, pose)."""
    outputs = set(outputs)
    return tuple(dict.fromkeys(o.when for o in LAYOUT if o.name in outputs))


def _written(
    output: Output, tasks: Iterable[str], outputs: Collection[str], point_cloud: str | None, camera: bool
) -> bool:
    """Whether a run with these settings writes ``output``."""
    tasks = set(tasks)
    if output.name is not None and output.name not in outputs:
        return False
    return {
        "always": True,
        "camera": camera,
        "points": bool(point_cloud) and "depth" in tasks,
        "world": point_cloud == "world" and "depth" in tasks,
        "depth": "depth" in tasks,
        "flow": "flow" in tasks,
        "pose": "pose" in tasks,
    }[output.when]


def frame_outputs(tasks: Iterable[str], outputs: Collection[str], point_cloud: str | None = None) -> list[Output]:
    """The per-frame entries of LAYOUT a run with these settings writes."""
    tasks = tuple(tasks)
    return [o for o in LAYOUT if FRAME in o.path and _written(o, tasks, outputs, point_cloud, camera=False)]


def frame_files(name: str, tasks: Iterable[str], outputs: Collection[str], point_cloud: str | None = None) -> set[str]:
    """The files (relative to OUT) frame ``name`` may get."""
    return {o.path.replace(FRAME, name) for o in frame_outputs(tasks, outputs, point_cloud)}


def run_files(
    tasks: Iterable[str], point_cloud: str | None, camera: bool, outputs: Collection[str] = DEFAULT_OUTPUTS
) -> set[str]:
    """The files (relative to OUT) written once per run, summary.json included."""
    tasks = tuple(tasks)
    return {o.path for o in LAYOUT if FRAME not in o.path and _written(o, tasks, outputs, point_cloud, camera)}


def listed_outputs(tasks: Iterable[str], outputs: Collection[str], point_cloud: str | None, camera: bool) -> list[str]:
    """summary.json's ``outputs``: the files of the run as patterns (``depth/*.npy``), summary.json left out."""
    tasks = tuple(tasks)
    return [pattern(o) for o in LAYOUT if o.path != SUMMARY_NAME and _written(o, tasks, outputs, point_cloud, camera)]


def pattern(output: Output) -> str:
    """The entry's files as a glob pattern relative to OUT (``depth/*.npy``)."""
    return output.path.replace(FRAME, "*")


def frame_path(out_dir: Path, output: Output, name: str) -> Path:
    """Where frame ``name``'s file of ``output`` goes (:func:`output_path`'s checks)."""
    subdir, _, file = output.path.rpartition("/")
    return output_path(out_dir, subdir, name, file.removeprefix(FRAME))


def written_summary(out_dir: Path, frame_bytes: dict[str, int], run: Iterable[str], frames: int) -> dict:
    """summary.json's ``written``: the bytes of each entry the run wrote (per-frame entries from
    ``frame_bytes``, per pattern; the run's files ``run`` from the disk), each per frame, and in all."""
    entries = {}
    for o in LAYOUT:
        if FRAME in o.path:
            size = frame_bytes.get(pattern(o))
        else:
            size = (out_dir / o.path).stat().st_size if o.path in run and (out_dir / o.path).is_file() else None
        if size is not None and o.path != SUMMARY_NAME:
            entries[pattern(o)] = {"bytes": size, "bytes_per_frame": round(size / max(frames, 1))}
    total = sum(e["bytes"] for e in entries.values())
    return {"files": entries, "bytes": total, "bytes_per_frame": round(total / max(frames, 1))}


def describe(width: int = 100) -> str:
    """The layout as ``predict --help`` shows it, one entry per file."""
    lines = []
    for o in LAYOUT:
        name = o.path.replace(FRAME, "<frame>")
        default = " (default)" if o.name in DEFAULT_OUTPUTS else ""
        text = textwrap.wrap(o.what if o.name is None else f"[{o.name}{default}] {o.what}", width - 25)
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

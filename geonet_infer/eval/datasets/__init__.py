"""Evaluation data layouts: which files make one scored item, and their ground truth.

One module per layout, each a :class:`~geonet_infer.eval.datasets.base.Layout` subclass (what the
folder looks like, its items, its default depth crop, its intrinsics), collected in
:data:`REGISTRY`, from which ``--layout``'s choices, :func:`detect_layout` and
:func:`load_dataset` are built. Adding a layout is one new module plus one registry line; for
TUM RGB-D depth, say, ``datasets/tum_rgbd.py``::

    class TumRgbd(Layout):
        name = "tum-rgbd"
        tasks = ("depth",)

        @staticmethod
        def detect(task, root):
            return (root / "rgb.txt").is_file() and (root / "depth.txt").is_file()

        @classmethod
        def items(cls, task, root, *, sequences, stride, multiview):
            ...  # DepthItem per rgb frame matched to its depth PNG (gt_kind "png")
            return Found(items, f"TUM RGB-D {root.name}")

        @classmethod
        def depth_intrinsics(cls, item):
            return np.array([[525.0, 0, 319.5], [0, 525.0, 239.5], [0, 0, 1]])

and ``TumRgbd`` added to ``REGISTRY`` below: ``geonet-infer eval --task depth --layout tum-rgbd``
(and ``auto``) then know it.

Readers only list and load files; scoring lives in :mod:`geonet_infer.eval.evaluation`.
Every problem (missing file, count mismatch, size mismatch) raises
:class:`~geonet_infer.errors.GeoNetError` naming the file or folder.

Layouts (``--layout``; ``auto`` picks from the folder's content, see :func:`detect_layout`):

depth
  ``synth``       our generator's folders: ``[ROOT/]seq_NNNN/image/*.png`` + ``depth/*.png``
                  (KITTI depth PNG, uint16 / 256 m, 0 = none), same names.
  ``kitti-raw``   a KITTI raw drive: ``image_02/data/*.png`` with ground truth either as
                  sparse depth PNGs (``proj_depth/groundtruth/image_02/*.png``, the KITTI depth
                  benchmark layout) or as Velodyne scans ``velodyne_points/data/*.bin``
                  projected on the fly with ``calib_cam_to_cam.txt`` + ``calib_velo_to_cam.txt``
                  (in the drive folder or up to two levels above, as KITTI's date folder).
  ``kitti-object``  the KITTI object benchmark: ``[training/]image_2/``, ``velodyne/*.bin`` and
                  ``calib/*.txt`` (P2, R0_rect, Tr_velo_to_cam per frame); each scan projected with
                  its own frame's calibration by the KITTI raw code.
  ``kitti-disparity``  KITTI 2015 stereo: ``[training/]image_2/NNNNNN_10.png`` + ``disp_occ_0/``
                  (or ``disp_noc_0/``) 16-bit disparity PNGs (value / 256 px, 0 = none); depth =
                  fx·baseline/disparity with fx and baseline from ``calib_cam_to_cam/NNNNNN.txt``
                  or the options ``fx``, ``baseline`` (``--fx``, ``--baseline``); the notes say which.
flow
  ``synth``       ``seq_NNNN/image``, ``flow_noc``, ``flow_occ`` (KITTI flow PNG), ``calib.txt``;
                  item t = triplet [t-1, t, t+1], GT t -> t+1 (name of frame t).
  ``kitti``       KITTI 2015 (``image_2/``, ``calib_cam_to_cam/``) or 2012 (``colored_0/``,
                  ``calib/``), here or in ``training/``: ``NNNNNN_10.png`` -> ``NNNNNN_11.png``,
                  GT ``flow_noc/NNNNNN_10.png`` and ``flow_occ/NNNNNN_10.png``. The cascade's 3-frame snippet takes
                  ``NNNNNN_09.png`` from the multi-view extension (same folder, or ``multiview``
                  DIR/<image folder>/) as GeoNet's official test does. **Fallback** where ``_09``
                  is missing: the pair [_10, _11], which the runtime pads to [_10, _10, _11]
                  exactly as at the start of a video (the frame before is replaced by the
                  target itself); each item records which snippet it used.
  ``middlebury``  ``other-data[-gray]/<Seq>/frame10.png, frame11.png`` + ``other-gt-flow/<Seq>/
                  flow10.flo`` (values > 1e9 = unknown). No occlusion masks, so Noc = All.
                  No intrinsics: the cascade needs ``intrinsics`` passed in.
pose
  ``synth``       ``seq_NNNN/image`` + ``poses.txt`` (one camera-to-world pose per frame) + ``calib.txt``.
  ``kitti-odometry``  a sequence folder ``sequences/XX`` with ``image_2/`` (or grey ``image_0/``:
                  whichever gives more 5-frame snippets, colour on a tie; grey frames are read
                  as three equal channels and the notes say so) and ``calib.txt``; poses from
                  ``poses.txt`` in that folder or ``poses/XX.txt`` two levels up (the odometry
                  dev kit layout). Frames are matched to pose lines by the number in their file
                  name, so a subset of frames is fine.
  Items are 5-frame snippets of consecutive frames (the paper's protocol).
"""

from __future__ import annotations

from pathlib import Path

from geonet_infer.errors import InputError
from geonet_infer.eval.datasets.base import (
    EVAL_TASKS,
    FLO_UNKNOWN,
    KITTI_CALIB,
    SNIPPET,
    Dataset,
    DepthItem,
    FlowItem,
    Found,
    Layout,
    PoseItem,
    _limit,
    read_heldout,
    synth_sequences,
)
from geonet_infer.eval.datasets.kitti_disparity import KittiDisparity
from geonet_infer.eval.datasets.kitti_flow import KittiFlow
from geonet_infer.eval.datasets.kitti_object import KittiObject
from geonet_infer.eval.datasets.kitti_odometry import KittiOdometry
from geonet_infer.eval.datasets.kitti_raw import KittiRaw
from geonet_infer.eval.datasets.middlebury import Middlebury
from geonet_infer.eval.datasets.synth import Synth

__all__ = [
    "FLO_UNKNOWN",
    "KITTI_CALIB",
    "LAYOUTS",
    "REGISTRY",
    "SNIPPET",
    "EVAL_TASKS",
    "Dataset",
    "DepthItem",
    "FlowItem",
    "Found",
    "Layout",
    "PoseItem",
    "depth_dataset",
    "detect_layout",
    "flow_dataset",
    "layout_class",
    "load_dataset",
    "pose_dataset",
    "read_heldout",
    "synth_sequences",
]

# name -> layout, in the order --help lists them; detection tries them in this order, fallbacks last
REGISTRY: dict[str, type[Layout]] = {
    cls.name: cls for cls in (Synth, KittiRaw, KittiObject, KittiDisparity, KittiFlow, Middlebury, KittiOdometry)
}
LAYOUTS = {task: tuple(name for name, cls in REGISTRY.items() if task in cls.tasks) for task in EVAL_TASKS}


def layout_class(name: str, task: str | None = None) -> type[Layout]:
    """The layout class ``name`` (InputError for an unknown one, or one that does not serve ``task``)."""
    if name not in REGISTRY or (task is not None and task not in REGISTRY[name].tasks):
        what = f"{task} layout" if task else "layout"
        choices = LAYOUTS[task] if task else tuple(REGISTRY)
        raise InputError(None, f"unknown {what} {name!r}", f"choose one of {', '.join(choices)} or auto")
    return REGISTRY[name]


def detect_layout(task: str, root: Path) -> str:
    """The layout of ``root`` for ``task`` from the folders it holds."""
    root = Path(root)
    if not root.exists():
        raise InputError(root, "data folder not found", "pass --data DIR")
    candidates = [cls for cls in REGISTRY.values() if task in cls.tasks]
    for cls in sorted(candidates, key=lambda cls: cls.fallback):  # stable: registry order, fallbacks last
        if cls.detect(task, root):
            return cls.name
    raise InputError(
        root,
        f"cannot tell the {task} layout of this folder",
        f"pass --layout ({', '.join(LAYOUTS[task])}); see `geonet-infer eval --help`",
    )


def load_dataset(
    task: str,
    root,
    layout: str = "auto",
    *,
    sequences: list[str] | None = None,
    stride: int = 1,
    limit: int | None = None,
    multiview: Path | None = None,
    options: dict | None = None,
) -> Dataset:
    """The items of ``task`` under ``root`` in ``layout`` ("auto": :func:`detect_layout`).

    ``options``: layout options (``--fx``, ``--baseline`` of ``kitti-disparity``); those set (not
    None) go to a layout that lists them in :attr:`Layout.options`, any other layout refuses them.
    """
    if task not in EVAL_TASKS:
        raise InputError(None, f"unknown task {task!r}", f"choose one of {', '.join(EVAL_TASKS)}")
    root = Path(root)
    name = detect_layout(task, root) if layout == "auto" else layout
    cls = layout_class(name, task)
    given = {key: value for key, value in (options or {}).items() if value is not None}
    unused = sorted(set(given) - set(cls.options))
    if unused:
        takers = [n for n, c in REGISTRY.items() if set(unused) <= set(c.options)]
        raise InputError(
            root,
            f"--{unused[0].replace('_', '-')} does not apply to the {name} layout",
            f"it is for the {', '.join(takers)} layout" if takers else "leave it out",
        )
    found = cls.items(
        task, root, sequences=sequences, stride=stride, multiview=multiview if task == "flow" else None, **given
    )
    return Dataset(
        task,
        name,
        root,
        _limit(found.items, limit, root),
        found.description,
        found.notes,
        without_gt=found.without_gt,
        warnings=found.warnings,
        details=found.details,
    )


def depth_dataset(
    root, layout: str = "auto", sequences: list[str] | None = None, stride: int = 1, limit: int | None = None
) -> Dataset:
    return load_dataset("depth", root, layout, sequences=sequences, stride=stride, limit=limit)


def flow_dataset(
    root,
    layout: str = "auto",
    sequences: list[str] | None = None,
    stride: int = 1,
    limit: int | None = None,
    multiview: Path | None = None,
) -> Dataset:
    return load_dataset("flow", root, layout, sequences=sequences, stride=stride, limit=limit, multiview=multiview)


def pose_dataset(
    root, layout: str = "auto", sequences: list[str] | None = None, stride: int = 1, limit: int | None = None
) -> Dataset:
    return load_dataset("pose", root, layout, sequences=sequences, stride=stride, limit=limit)

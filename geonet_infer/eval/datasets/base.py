"""What every evaluation layout shares: the item types, the dataset record, file helpers.

One module per layout (:mod:`.synth`, :mod:`.kitti_raw`, ...) subclasses :class:`Layout`;
:mod:`geonet_infer.eval.datasets` collects them in its registry.
"""

from __future__ import annotations

import functools
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from geonet_infer.errors import InputError
from geonet_infer.eval.velodyne import object_velodyne_to_depth_map, velodyne_to_depth_map
from geonet_infer.io import (
    read_calib_K,
    read_camera,
    read_depth_kitti,
    read_flo,
    read_flow_kitti,
    read_kitti_poses,
)

EVAL_TASKS = ("depth", "flow", "pose")
SNIPPET = 5  # frames per pose snippet (the paper's ATE protocol)
FLO_UNKNOWN = 1e9  # Middlebury: |u| or |v| above this = no ground truth
KITTI_CALIB = ("calib_cam_to_cam.txt", "calib_velo_to_cam.txt")


def _require_dir(path: Path, what: str, hint: str) -> Path:
    if not path.is_dir():
        raise InputError(path, f"{what} not found", hint)
    return path


def _require_file(path: Path, what: str, hint: str = "") -> Path:
    if not path.is_file():
        raise InputError(path, f"{what} not found", hint)
    return path


def _frame_number(path: Path) -> int:
    digits = re.findall(r"\d+", path.stem)
    if not digits:
        raise InputError(
            path, "frame file name holds no frame number", "name frames by index (000000.png, 000001.png, ...)"
        )
    return int(digits[-1])


# ----------------------------------------------------------------------------- synthetic sequences
def synth_sequences(root: Path, sequences: list[str] | None = None) -> list[Path]:
    """Sequence folders of a synthetic set: ``root`` itself if it is one, else its ``seq_*`` folders
    (restricted to ``sequences`` if given, e.g. the names in a ``heldout.txt``)."""
    root = _require_dir(Path(root), "data folder", "pass --data DIR")
    if (root / "image").is_dir():
        return [root]
    if sequences:
        return [
            _require_dir(root / s, "sequence folder", f"{root} should hold the listed sequences") for s in sequences
        ]
    found = sorted(p for p in root.iterdir() if p.is_dir() and (p / "image").is_dir())
    if not found:
        raise InputError(
            root,
            "no sequence folder (with image/) here",
            "pass a folder written by `python -m training.synth` or one of its seq_NNNN folders",
        )
    return found


def read_heldout(path: Path) -> list[str]:
    """Sequence names listed in a ``heldout.txt`` of ``training.prepare`` (first column, unique, sorted)."""
    path = _require_file(Path(path), "held-out list", "written by `python -m training.prepare --kind synth`")
    names = sorted({line.split()[0] for line in path.read_text().splitlines() if line.strip()})
    if not names:
        raise InputError(path, "held-out list is empty", "regenerate it with training.prepare")
    return names


def _matched_files(images: list[Path], folder: Path, what: str, suffix: str = ".png") -> list[Path]:
    """GT files named like the frames; a missing one (count mismatch) names itself."""
    out = []
    for img in images:
        gt = folder / (img.stem + suffix)
        if not gt.is_file():
            have = len(list(folder.glob(f"*{suffix}"))) if folder.is_dir() else 0
            raise InputError(
                gt,
                f"{what} missing ({len(images)} frames, {have} {what} files in {folder.name}/)",
                "every scored frame needs its ground truth file of the same name",
            )
        out.append(gt)
    return out


# ----------------------------------------------------------------------------- depth
@dataclass
class DepthItem:
    """One frame: image path, GT file and how to decode it.

    ``gt_kind``: "png" (KITTI depth PNG, metres), "velodyne" (KITTI raw scan, projected with the
    drive's ``calib_dir``), "velodyne-object" (KITTI object scan, projected with the frame's own
    ``calib`` file) or "disparity" (KITTI disparity PNG, px; depth = ``fx_baseline`` / disparity,
    ``fx_baseline`` = fx in px times the stereo baseline in m).
    """

    name: str
    image: Path
    gt: Path
    gt_kind: str
    calib_dir: Path | None = None
    calib: Path | None = None
    fx_baseline: float | None = None

    def load_gt(self, shape: tuple[int, int]) -> np.ndarray:
        """(H, W) float32 metres, 0 = no ground truth; ``shape`` = the image's (H, W)."""
        if self.gt_kind == "velodyne":
            return velodyne_to_depth_map(self.calib_dir, self.gt, shape, cam=2, vel_depth=True)
        if self.gt_kind == "velodyne-object":
            return object_velodyne_to_depth_map(self.calib, self.gt, shape, vel_depth=True)
        # the disparity PNG has the depth PNG's encoding (uint16 / 256, 0 = none), in px instead of m
        gt = read_depth_kitti(self.gt)
        if gt.shape != tuple(shape):
            raise InputError(
                self.gt,
                f"{'disparity' if self.gt_kind == 'disparity' else 'depth'} ground truth is "
                f"{gt.shape[1]}x{gt.shape[0]}, its image {self.image.name} is {shape[1]}x{shape[0]}",
                "ground truth and image must have the same size",
            )
        if self.gt_kind == "disparity":
            if self.fx_baseline is None or not self.fx_baseline > 0:
                raise InputError(self.gt, "no fx x baseline to turn disparity into depth", "pass --fx and --baseline")
            return np.where(gt > 0, self.fx_baseline / np.maximum(gt, 1e-6), 0.0).astype(np.float32)
        return gt


@dataclass
class Dataset:
    """Items of one task in one layout, plus a one-line description for tables."""

    task: str
    layout: str
    root: Path
    items: list
    description: str
    notes: list[str] = field(default_factory=list)
    # Frames of the layout that have no ground truth file and so are not scored (KITTI raw depth),
    # and the warning that says so.
    without_gt: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    # facts a layout wants in the JSON beside its notes (e.g. the fx and baseline a disparity used)
    details: dict = field(default_factory=dict)

    def describe(self) -> dict:
        out = {
            "task": self.task,
            "layout": self.layout,
            "root": str(self.root),
            "items": len(self.items),
            "description": self.description,
            "notes": list(self.notes),
            "frames_without_gt": list(self.without_gt),
        }
        return out | ({"details": dict(self.details)} if self.details else {})


# ----------------------------------------------------------------------------- flow
@dataclass
class FlowItem:
    """One pair t -> t+1: frames ([t-1,] t, t+1), GT files, calibration file (or K)."""

    name: str
    frames: list[Path]
    gt_noc: Path
    gt_occ: Path
    gt_format: str = "kitti"  # or "flo"
    calib: Path | None = None
    K: np.ndarray | None = None
    snippet: str = ""

    def load_gt(self, which: str) -> tuple[np.ndarray, np.ndarray]:
        """(flow (H, W, 2) float32, valid (H, W) bool) for ``which`` = "noc" or "occ"."""
        path = self.gt_noc if which == "noc" else self.gt_occ
        if self.gt_format == "flo":
            flow = read_flo(path)
            valid = np.isfinite(flow).all(axis=2) & (np.abs(flow) < FLO_UNKNOWN).all(axis=2)
            return np.where(valid[..., None], flow, 0.0).astype(np.float32), valid
        return read_flow_kitti(path)

    def intrinsics(self) -> np.ndarray | None:
        if self.K is not None:
            return self.K
        if self.calib is None:
            return None
        return read_camera(self.calib).K


# ----------------------------------------------------------------------------- pose
@dataclass
class PoseItem:
    """One 5-frame snippet: frame paths, GT camera-to-world poses (5, 4, 4), intrinsics file/key."""

    name: str
    frames: list[Path]
    gt_c2w: np.ndarray
    calib: Path | None = None
    calib_key: str | None = None

    def intrinsics(self) -> np.ndarray | None:
        if self.calib is None:
            return None
        if self.calib_key:
            return read_calib_K(self.calib, self.calib_key)
        return read_camera(self.calib).K


MAX_POSE_COORDINATE = 1e6  # metres (1000 km): past any drive; 1e308 is finite, its square is not


def _finite_poses(path: Path) -> np.ndarray:
    """Ground-truth poses of a file, refused if any holds NaN, infinity or a number over
    :data:`MAX_POSE_COORDINATE` (each would score as "nan ± nan")."""
    poses = read_kitti_poses(path)
    with np.errstate(invalid="ignore"):
        bad = np.flatnonzero(~(np.abs(poses) <= MAX_POSE_COORDINATE).all(axis=(1, 2)))
    if bad.size:
        raise InputError(
            path,
            f"pose line {bad[0] + 1} holds NaN, infinity or a number over {MAX_POSE_COORDINATE:g} "
            f"({bad.size} such line(s))",
            "ground-truth poses must be finite metres: fix or regenerate the file",
        )
    return poses


def _snippets(
    frames: list[Path],
    poses: np.ndarray,
    poses_path: Path,
    stride: int,
    prefix: str,
    calib: Path | None,
    calib_key: str | None,
) -> list[PoseItem]:
    """5-frame snippets of consecutive frame numbers; poses indexed by frame number."""
    numbers = [_frame_number(f) for f in frames]
    if max(numbers) >= len(poses):
        raise InputError(
            poses_path,
            f"{len(poses)} poses, but frame {frames[numbers.index(max(numbers))].name} "
            f"needs pose line {max(numbers) + 1}",
            "poses and frames must come from one sequence",
        )
    by_number = dict(zip(numbers, frames))
    starts = [n for n in sorted(by_number) if all(n + k in by_number for k in range(SNIPPET))][::stride]
    return [
        PoseItem(
            f"{prefix}{n:06d}", [by_number[n + k] for k in range(SNIPPET)], poses[n : n + SNIPPET], calib, calib_key
        )
        for n in starts
    ]


# ----------------------------------------------------------------------------- helpers
def benchmark_root(root: Path, *folders: str) -> Path | None:
    """``root`` if it holds every one of ``folders``, else its ``training/`` if that does, else None.

    The KITTI benchmarks unpack as ``<name>/training/<folders>`` (and ``testing/``, which has no
    ground truth): either level may be passed as ``--data``.
    """
    for base in (root, root / "training"):
        if all((base / f).is_dir() for f in folders):
            return base
    return None


def _limit(items: list, limit: int | None, root: Path) -> list:
    if not items:
        raise InputError(root, "no item to evaluate here", "check --data and --layout")
    return items[:limit] if limit else items


@dataclass
class Found:
    """What a layout finds under a root for one task (before ``--limit``)."""

    items: list
    description: str
    notes: list[str] = field(default_factory=list)
    without_gt: list[str] = field(default_factory=list)  # frames with no ground truth file: not scored
    warnings: list[str] = field(default_factory=list)
    details: dict = field(default_factory=dict)  # see Dataset.details


class Layout:
    """One evaluation layout: a class attribute or method for each fact about it.

    Subclasses set ``name`` (the ``--layout`` value), ``tasks`` (of depth, flow, pose) and
    implement :meth:`detect` and :meth:`items`; depth layouts also :meth:`depth_intrinsics` and
    ``depth_crop``.
    """

    name: str = ""
    tasks: tuple[str, ...] = ()
    help: dict[str, tuple[str, ...]] = {}  # task -> lines describing the layout in `eval --help`
    fallback = False  # detected only when no other layout claims the folder
    depth_crop: str | None = None  # default depth crop ("garg", "eigen" or None: every GT pixel)
    # extra keyword options :meth:`items` takes (e.g. ``("fx", "baseline")``), passed by
    # :func:`~geonet_infer.eval.datasets.load_dataset` only to a layout that names them
    options: tuple[str, ...] = ()

    @staticmethod
    def detect(task: str, root: Path) -> bool:
        """Whether ``root`` (an existing path) looks like this layout for ``task``."""
        raise NotImplementedError

    @classmethod
    def items(cls, task: str, root: Path, *, sequences: list[str] | None, stride: int, multiview: Path | None) -> Found:
        """The scored items of ``task`` under ``root``; InputError naming the file for anything missing."""
        raise NotImplementedError

    @classmethod
    def depth_intrinsics(cls, item: DepthItem) -> np.ndarray:
        """K at the image size of a depth item (scaling by camera height needs it)."""
        raise InputError(
            item.image,
            f"the {cls.name} layout has no camera intrinsics",
            "pass --intrinsics FX,FY,CX,CY",
        )


@functools.lru_cache(maxsize=16)
def _calibration_K(path: Path) -> np.ndarray:
    """K of a calibration file, read once: every frame of a sequence shares it (read-only array)."""
    return read_camera(path).K


def calibration_K_or_error(path: Path) -> np.ndarray:
    """K of the calibration file ``path``, or InputError naming it when it is missing."""
    if path.is_file():
        return _calibration_K(path)
    raise InputError(
        path,
        "no camera intrinsics for this frame",
        "scaling by camera height needs K: add the calibration file or pass --intrinsics FX,FY,CX,CY",
    )

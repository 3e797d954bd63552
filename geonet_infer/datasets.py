"""Evaluation data layouts: which files make one scored item, and their ground truth.

Readers only list and load files; scoring lives in :mod:`geonet_infer.evaluation`.
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
flow
  ``synth``       ``seq_NNNN/image``, ``flow_noc``, ``flow_occ`` (KITTI flow PNG), ``calib.txt``;
                  item t = triplet [t-1, t, t+1], GT t -> t+1 (name of frame t).
  ``kitti``       KITTI 2015 (``image_2/``, ``calib_cam_to_cam/``) or 2012 (``colored_0/``,
                  ``calib/``): ``NNNNNN_10.png`` -> ``NNNNNN_11.png``, GT ``flow_noc/NNNNNN_10.png``
                  and ``flow_occ/NNNNNN_10.png``. The cascade's 3-frame snippet takes
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
  ``kitti-odometry``  a sequence folder ``sequences/XX`` with ``image_2/`` (or grey ``image_0/``)
                  and ``calib.txt``; poses from ``poses.txt`` in that folder or ``poses/XX.txt``
                  two levels up (the odometry dev kit layout). Frames are matched to pose lines
                  by the number in their file name, so a subset of frames is fine.
  Items are 5-frame snippets of consecutive frames (the paper's protocol).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from geonet_infer.errors import GeoNetError, InputError
from geonet_infer.io import (
    list_images,
    read_calib_file,
    read_calib_K,
    read_camera,
    read_depth_kitti,
    read_flo,
    read_flow_kitti,
    read_kitti_poses,
)
from geonet_infer.io.frames import find_up
from geonet_infer.velodyne import velodyne_to_depth_map

TASKS = ("depth", "flow", "pose")
LAYOUTS = {
    "depth": ("synth", "kitti-raw"),
    "flow": ("synth", "kitti", "middlebury"),
    "pose": ("synth", "kitti-odometry"),
}
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
    """One frame: image path, GT file and how to decode it ("png" or "velodyne")."""

    name: str
    image: Path
    gt: Path
    gt_kind: str
    calib_dir: Path | None = None

    def load_gt(self, shape: tuple[int, int]) -> np.ndarray:
        """(H, W) float32 metres, 0 = no ground truth; ``shape`` = the image's (H, W)."""
        if self.gt_kind == "velodyne":
            return velodyne_to_depth_map(self.calib_dir, self.gt, shape, cam=2, vel_depth=True)
        gt = read_depth_kitti(self.gt)
        if gt.shape != tuple(shape):
            raise InputError(
                self.gt,
                f"depth ground truth is {gt.shape[1]}x{gt.shape[0]}, its image "
                f"{self.image.name} is {shape[1]}x{shape[0]}",
                "ground truth and image must have the same size",
            )
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

    def describe(self) -> dict:
        return {
            "task": self.task,
            "layout": self.layout,
            "root": str(self.root),
            "items": len(self.items),
            "description": self.description,
            "notes": list(self.notes),
            "frames_without_gt": list(self.without_gt),
        }


def depth_dataset(
    root, layout: str = "auto", sequences: list[str] | None = None, stride: int = 1, limit: int | None = None
) -> Dataset:
    root = Path(root)
    layout = detect_layout("depth", root) if layout == "auto" else layout
    items: list[DepthItem] = []
    without_gt: list[str] = []
    warnings: list[str] = []
    if layout == "synth":
        seqs = synth_sequences(root, sequences)
        for seq in seqs:
            images = list_images(seq / "image")[::stride]
            for img, gt in zip(images, _matched_files(images, seq / "depth", "depth ground truth")):
                items.append(DepthItem(f"{seq.name}/{img.stem}", img, gt, "png"))
        desc = f"synthetic ({len(seqs)} seq: {', '.join(s.name for s in seqs[:4])}{', ...' if len(seqs) > 4 else ''})"
    elif layout == "kitti-raw":
        image_dir = _require_dir(
            root / "image_02" / "data", "KITTI raw image folder", "pass a drive folder holding image_02/data"
        )
        images = list_images(image_dir)
        png_dir = root / "proj_depth" / "groundtruth" / "image_02"
        velo_dir = root / "velodyne_points" / "data"
        if png_dir.is_dir():
            pairs = [(img, png_dir / img.name) for img in images if (png_dir / img.name).is_file()]
            kind, calib_dir, gt_what = "png", None, "sparse depth PNGs (proj_depth/groundtruth)"
        elif velo_dir.is_dir():
            calib_dir = find_up(root, KITTI_CALIB)
            if calib_dir is None:
                raise InputError(
                    root / KITTI_CALIB[0],
                    "KITTI calibration not found (here or up to two levels up)",
                    "Velodyne ground truth needs calib_cam_to_cam.txt and calib_velo_to_cam.txt of the drive's date",
                )
            pairs = [(img, velo_dir / f"{img.stem}.bin") for img in images if (velo_dir / f"{img.stem}.bin").is_file()]
            kind, gt_what = "velodyne", "Velodyne scans projected to camera 2"
        else:
            raise InputError(
                root,
                "no depth ground truth: neither proj_depth/groundtruth/image_02/ nor velodyne_points/data/",
                "KITTI raw depth needs sparse depth PNGs or Velodyne scans",
            )
        if not pairs:
            raise InputError(
                png_dir if kind == "png" else velo_dir,
                "no frame of image_02/data has ground truth here",
                "ground truth files are named like the frames",
            )
        scored = {img for img, _ in pairs}
        without_gt = [img.stem for img in images if img not in scored]
        if without_gt:
            names = ", ".join(without_gt[:3]) + (", ..." if len(without_gt) > 3 else "")
            warnings.append(
                f"{image_dir}: {len(without_gt)} of {len(images)} frames without ground truth in "
                f"{(png_dir if kind == 'png' else velo_dir).relative_to(root)}/ ({names}): not scored"
            )
        items = [DepthItem(img.stem, img, gt, kind, calib_dir) for img, gt in pairs[::stride]]
        desc = f"KITTI raw {root.name}, {gt_what}"
    else:
        raise _bad_layout("depth", layout)
    return Dataset("depth", layout, root, _limit(items, limit, root), desc, without_gt=without_gt, warnings=warnings)


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


def flow_dataset(
    root,
    layout: str = "auto",
    sequences: list[str] | None = None,
    stride: int = 1,
    limit: int | None = None,
    multiview: Path | None = None,
) -> Dataset:
    root = Path(root)
    layout = detect_layout("flow", root) if layout == "auto" else layout
    items: list[FlowItem] = []
    notes: list[str] = []
    if layout == "synth":
        seqs = synth_sequences(root, sequences)
        for seq in seqs:
            frames = list_images(seq / "image")
            calib = _require_file(seq / "calib.txt", "calibration", "synthetic sequences hold calib.txt")
            targets = frames[1:-1:stride]
            noc = _matched_files(targets, seq / "flow_noc", "flow ground truth (noc)")
            occ = _matched_files(targets, seq / "flow_occ", "flow ground truth (occ)")
            for k, t in enumerate(range(1, len(frames) - 1, stride)):
                items.append(
                    FlowItem(
                        f"{seq.name}/{frames[t].stem}",
                        frames[t - 1 : t + 2],
                        noc[k],
                        occ[k],
                        calib=calib,
                        snippet="t-1, t, t+1",
                    )
                )
        desc = f"synthetic ({len(seqs)} seq: {', '.join(s.name for s in seqs[:4])}{', ...' if len(seqs) > 4 else ''})"
    elif layout == "kitti":
        image_name = "image_2" if (root / "image_2").is_dir() else "colored_0"
        image_dir = _require_dir(
            root / image_name, "KITTI flow image folder", "expected image_2/ (KITTI 2015) or colored_0/ (KITTI 2012)"
        )
        version = "2015" if image_name == "image_2" else "2012"
        calib_dir = root / ("calib_cam_to_cam" if version == "2015" else "calib")
        firsts = sorted(image_dir.glob("*_10.png"))
        if not firsts:
            raise InputError(image_dir, "no NNNNNN_10.png frame", "KITTI flow pairs are NNNNNN_10.png -> NNNNNN_11.png")
        fallback = 0
        for first in firsts[::stride]:
            stem = first.name[: -len("_10.png")]
            second = _require_file(image_dir / f"{stem}_11.png", "second frame of the pair")
            prev = next(
                (
                    p
                    for p in (
                        image_dir / f"{stem}_09.png",
                        multiview / image_name / f"{stem}_09.png" if multiview else None,
                    )
                    if p is not None and p.is_file()
                ),
                None,
            )
            frames = [prev, first, second] if prev else [first, second]
            fallback += prev is None
            noc = _require_file(root / "flow_noc" / f"{stem}_10.png", "flow ground truth (noc)")
            occ = _require_file(root / "flow_occ" / f"{stem}_10.png", "flow ground truth (occ)")
            calib = calib_dir / f"{stem}.txt"
            items.append(
                FlowItem(
                    stem,
                    frames,
                    noc,
                    occ,
                    calib=calib if calib.is_file() else None,
                    snippet="_09, _10, _11" if prev else "_10, _10, _11 (no _09: sequence-start padding)",
                )
            )
        if fallback:
            notes.append(f"{fallback} of {len(items)} pairs have no _09 frame: the cascade saw [_10, _10, _11]")
        desc = f"KITTI {version} layout {root.name}"
    elif layout == "middlebury":
        gt_root = _require_dir(
            root / "other-gt-flow", "Middlebury GT folder", "expected other-gt-flow/<Seq>/flow10.flo"
        )
        for gt in sorted(gt_root.glob("*/flow10.flo"))[::stride]:
            seq = gt.parent.name
            image_dir = next(
                (
                    d
                    for d in (root / "other-data" / seq, root / "other-data-gray" / seq)
                    if (d / "frame11.png").is_file() and (d / "frame10.png").is_file()
                ),
                None,
            )
            if image_dir is None:
                raise InputError(
                    root / "other-data-gray" / seq / "frame11.png",
                    "frame pair for this GT not found",
                    "expected other-data[-gray]/<Seq>/frame10.png and frame11.png",
                )
            items.append(
                FlowItem(
                    seq,
                    [image_dir / "frame10.png", image_dir / "frame11.png"],
                    gt,
                    gt,
                    gt_format="flo",
                    snippet="10, 10, 11 (pair: sequence-start padding)",
                )
            )
        if not items:
            raise InputError(
                gt_root, "no <Seq>/flow10.flo ground truth", "Middlebury GT is other-gt-flow/<Seq>/flow10.flo"
            )
        notes.append("Middlebury has no occlusion masks: Noc = All")
        desc = f"Middlebury {', '.join(i.name for i in items)}"
    else:
        raise _bad_layout("flow", layout)
    return Dataset("flow", layout, root, _limit(items, limit, root), desc, notes)


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


def _finite_poses(path: Path) -> np.ndarray:
    """Ground-truth poses of a file, refused if any holds NaN or infinity (it would score as "nan ± nan")."""
    poses = read_kitti_poses(path)
    bad = np.flatnonzero(~np.isfinite(poses).all(axis=(1, 2)))
    if bad.size:
        raise InputError(
            path,
            f"pose line {bad[0] + 1} holds NaN or infinity ({bad.size} such line(s))",
            "ground-truth poses must be finite: fix or regenerate the file",
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


def pose_dataset(
    root, layout: str = "auto", sequences: list[str] | None = None, stride: int = 1, limit: int | None = None
) -> Dataset:
    root = Path(root)
    layout = detect_layout("pose", root) if layout == "auto" else layout
    items: list[PoseItem] = []
    if layout == "synth":
        seqs = synth_sequences(root, sequences)
        for seq in seqs:
            frames = list_images(seq / "image")
            poses_path = seq / "poses.txt"
            poses = _finite_poses(poses_path)
            if len(poses) != len(frames):
                raise InputError(
                    poses_path,
                    f"{len(poses)} poses for {len(frames)} frames in {seq.name}/image",
                    "one camera-to-world pose per frame",
                )
            items += _snippets(
                frames, poses, poses_path, stride, f"{seq.name}/", _require_file(seq / "calib.txt", "calibration"), None
            )
        desc = f"synthetic ({len(seqs)} seq: {', '.join(s.name for s in seqs[:4])}{', ...' if len(seqs) > 4 else ''})"
    elif layout == "kitti-odometry":
        image_name = next((n for n in ("image_2", "image_0") if (root / n).is_dir()), None)
        if image_name is None:
            raise InputError(
                root / "image_2",
                "KITTI odometry image folder not found",
                "pass a sequences/XX folder holding image_2/ or image_0/",
            )
        frames = list_images(root / image_name)
        poses_path = root / "poses.txt"
        if not poses_path.is_file():
            poses_path = root.parent.parent / "poses" / f"{root.name}.txt"
        if not poses_path.is_file():
            raise InputError(
                root / "poses.txt",
                f"ground-truth poses not found (nor {poses_path})",
                "put poses.txt in the sequence folder or keep the dev kit layout poses/XX.txt",
            )
        calib = _require_file(root / "calib.txt", "calibration", "KITTI odometry sequences hold calib.txt")
        key = "P2" if image_name == "image_2" else "P0"  # each camera's own projection matrix
        if key not in read_calib_file(calib):
            raise InputError(calib, f"missing calibration key '{key}'", f"{image_name}/ frames need {key}")
        items = _snippets(frames, _finite_poses(poses_path), poses_path, stride, "", calib, key)
        if not items:
            raise InputError(
                root / image_name, f"no {SNIPPET} consecutive frames", "the ATE protocol scores 5-frame snippets"
            )
        first, last = _frame_number(frames[0]), _frame_number(frames[-1])
        desc = f"KITTI odometry seq {root.name} ({image_name}, frames {first}–{last})"
    else:
        raise _bad_layout("pose", layout)
    return Dataset("pose", layout, root, _limit(items, limit, root), desc)


# ----------------------------------------------------------------------------- helpers
def _limit(items: list, limit: int | None, root: Path) -> list:
    if not items:
        raise InputError(root, "no item to evaluate here", "check --data and --layout")
    return items[:limit] if limit else items


def _bad_layout(task: str, layout: str) -> GeoNetError:
    return InputError(None, f"unknown {task} layout {layout!r}", f"choose one of {', '.join(LAYOUTS[task])} or auto")


def detect_layout(task: str, root: Path) -> str:
    """The layout of ``root`` for ``task`` from the folders it holds."""
    root = Path(root)
    if not root.exists():
        raise InputError(root, "data folder not found", "pass --data DIR")
    if task == "depth" and (root / "image_02" / "data").is_dir():
        return "kitti-raw"
    if (
        task == "flow"
        and ((root / "image_2").is_dir() or (root / "colored_0").is_dir())
        and (root / "flow_occ").is_dir()
    ):
        return "kitti"
    if task == "flow" and (root / "other-gt-flow").is_dir():
        return "middlebury"
    if (
        task == "pose"
        and (root / "calib.txt").is_file()
        and ((root / "image_2").is_dir() or (root / "image_0").is_dir())
    ):
        return "kitti-odometry"
    if (root / "image").is_dir() or any(p.is_dir() and (p / "image").is_dir() for p in root.iterdir() if root.is_dir()):
        return "synth"
    raise InputError(
        root,
        f"cannot tell the {task} layout of this folder",
        f"pass --layout ({', '.join(LAYOUTS[task])}); see `geonet-infer eval --help`",
    )


def load_dataset(task: str, root, layout: str = "auto", **kwargs) -> Dataset:
    """:func:`depth_dataset`, :func:`flow_dataset` or :func:`pose_dataset` by ``task``."""
    if task not in TASKS:
        raise InputError(None, f"unknown task {task!r}", f"choose one of {', '.join(TASKS)}")
    if task != "flow":
        kwargs.pop("multiview", None)
    return {"depth": depth_dataset, "flow": flow_dataset, "pose": pose_dataset}[task](root, layout, **kwargs)

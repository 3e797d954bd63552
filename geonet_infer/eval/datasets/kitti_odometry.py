"""``kitti-odometry``: a sequence folder ``sequences/XX``, pose.

``image_2/`` (or grey ``image_0/``) and ``calib.txt``; poses from ``poses.txt`` in that folder or
``poses/XX.txt`` two levels up (the odometry dev kit layout). Frames are matched to pose lines by
the number in their file name, so a subset of frames is fine. Items are 5-frame snippets of
consecutive frames (the paper's protocol). Where both camera folders exist, the one with more
snippets is scored (colour on a tie): an extract may hold a few colour frames beside a long grey
run. Grey frames go through the runtime as they are: :func:`geonet_infer.io.read_image` repeats
the one channel three times, and the dataset's notes say so.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from geonet_infer.errors import InputError
from geonet_infer.eval.datasets.base import (
    SNIPPET,
    Found,
    Layout,
    _finite_poses,
    _frame_number,
    _require_file,
    _snippets,
)
from geonet_infer.io import list_images, read_calib_file
from geonet_infer.io.layouts import ODOMETRY_CAMERAS


class KittiOdometry(Layout):
    name = "kitti-odometry"
    help = {  # geonet-infer eval --help: one entry per task, one string per line
        "pose": (
            "sequences/XX with image_2/ or grey image_0/ (the one with more snippets;",
            "grey read as 3 equal channels), calib.txt, and poses.txt there or",
            "poses/XX.txt two levels up; frames matched to poses by number",
        ),
    }
    tasks = ("pose",)

    @staticmethod
    def detect(task: str, root: Path) -> bool:
        return (root / "calib.txt").is_file() and any((root / n).is_dir() for n in ODOMETRY_CAMERAS)

    @classmethod
    def items(cls, task: str, root: Path, *, sequences: list[str] | None, stride: int, multiview: Path | None) -> Found:
        names = [n for n in ODOMETRY_CAMERAS if (root / n).is_dir()]
        if not names:
            raise InputError(
                root / "image_2",
                "KITTI odometry image folder not found",
                "pass a sequences/XX folder holding image_2/ or image_0/",
            )
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
        poses = _finite_poses(poses_path)
        candidates = {}  # camera folder -> (frames, snippets), colour first
        for name in names:
            key = ODOMETRY_CAMERAS[name]  # each camera's own projection matrix
            frames = list_images(root / name)
            candidates[name] = (frames, _snippets(frames, poses, poses_path, stride, "", calib, key))
        image_name = max(names, key=lambda n: len(candidates[n][1]))  # max keeps the first (colour) on a tie
        frames, items = candidates[image_name]
        key = ODOMETRY_CAMERAS[image_name]
        if key not in read_calib_file(calib):
            raise InputError(calib, f"missing calibration key '{key}'", f"{image_name}/ frames need {key}")
        if not items:
            raise InputError(
                root / image_name, f"no {SNIPPET} consecutive frames", "the ATE protocol scores 5-frame snippets"
            )
        notes = []
        for other in names:
            if other != image_name:
                notes.append(
                    f"{other}/ gives {len(candidates[other][1])} snippets, {image_name}/ {len(items)}: "
                    f"{image_name}/ scored"
                )
        if _is_grey(frames[0]):
            notes.append(f"{image_name}/ frames are grey: the model sees each one as three equal channels")
        first, last = _frame_number(frames[0]), _frame_number(frames[-1])
        desc = f"KITTI odometry seq {root.name} ({image_name}, frames {first}–{last})"
        return Found(items, desc, notes)


def _is_grey(path: Path) -> bool:
    """Whether an image file holds one channel (read as stored, not converted)."""
    image = cv2.imdecode(np.fromfile(path, np.uint8), cv2.IMREAD_UNCHANGED)  # bytes read by numpy: any file name
    return image is not None and image.ndim == 2

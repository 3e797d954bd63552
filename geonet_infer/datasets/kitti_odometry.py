"""``kitti-odometry``: a sequence folder ``sequences/XX``, pose.

``image_2/`` (or grey ``image_0/``) and ``calib.txt``; poses from ``poses.txt`` in that folder or
``poses/XX.txt`` two levels up (the odometry dev kit layout). Frames are matched to pose lines by
the number in their file name, so a subset of frames is fine. Items are 5-frame snippets of
consecutive frames (the paper's protocol).
"""

from __future__ import annotations

from pathlib import Path

from geonet_infer.datasets.base import (
    SNIPPET,
    Found,
    Layout,
    PoseItem,
    _finite_poses,
    _frame_number,
    _require_file,
    _snippets,
)
from geonet_infer.errors import InputError
from geonet_infer.io import list_images, read_calib_file


class KittiOdometry(Layout):
    name = "kitti-odometry"
    help = {  # geonet-infer eval --help: one entry per task, one string per line
        "pose": (
            "sequences/XX with image_2/ (or image_0/), calib.txt, and poses.txt",
            "there or poses/XX.txt two levels up; frames matched to poses by number",
        ),
    }
    tasks = ("pose",)

    @staticmethod
    def detect(task: str, root: Path) -> bool:
        return (root / "calib.txt").is_file() and ((root / "image_2").is_dir() or (root / "image_0").is_dir())

    @classmethod
    def items(cls, task: str, root: Path, *, sequences: list[str] | None, stride: int, multiview: Path | None) -> Found:
        items: list[PoseItem] = []
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
        return Found(items, desc)

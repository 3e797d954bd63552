"""``synth``: our generator's folders (``python -m training.synth``), every task.

``[ROOT/]seq_NNNN/`` with ``image/*.png``, ``depth/*.png`` (KITTI depth PNG, uint16 / 256 m,
0 = none), ``flow_noc/``, ``flow_occ/`` (KITTI flow PNG; item t = triplet [t-1, t, t+1], GT
t -> t+1), ``poses.txt`` (one camera-to-world pose per frame) and ``calib.txt``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from geonet_infer.errors import InputError
from geonet_infer.eval.datasets.base import (
    DepthItem,
    FlowItem,
    Found,
    Layout,
    PoseItem,
    _finite_poses,
    _matched_files,
    _require_file,
    _snippets,
    calibration_K_or_error,
    synth_sequences,
)
from geonet_infer.io import list_images


class Synth(Layout):
    name = "synth"
    help = {  # geonet-infer eval --help: one entry per task, one string per line
        "depth": ("training.synth folders: seq_NNNN/image + depth/ (KITTI depth PNG)",),
        "flow": ("seq_NNNN/image, flow_noc/, flow_occ/, calib.txt",),
        "pose": ("seq_NNNN/image + poses.txt + calib.txt",),
    }
    tasks = ("depth", "flow", "pose")
    fallback = True  # any folder with image/ (or seq_*/image/) would pass: tried last
    depth_crop = None  # rendered frames have no bonnet or empty sky band to crop

    @staticmethod
    def detect(task: str, root: Path) -> bool:
        return (root / "image").is_dir() or any(
            p.is_dir() and (p / "image").is_dir() for p in root.iterdir() if root.is_dir()
        )

    @classmethod
    def items(cls, task: str, root: Path, *, sequences: list[str] | None, stride: int, multiview: Path | None) -> Found:
        return {"depth": cls._depth, "flow": cls._flow, "pose": cls._pose}[task](root, sequences, stride)

    @staticmethod
    def _depth(root: Path, sequences: list[str] | None, stride: int) -> Found:
        items: list[DepthItem] = []
        seqs = synth_sequences(root, sequences)
        for seq in seqs:
            images = list_images(seq / "image")[::stride]
            for img, gt in zip(images, _matched_files(images, seq / "depth", "depth ground truth")):
                items.append(DepthItem(f"{seq.name}/{img.stem}", img, gt, "png"))
        desc = f"synthetic ({len(seqs)} seq: {', '.join(s.name for s in seqs[:4])}{', ...' if len(seqs) > 4 else ''})"
        return Found(items, desc)

    @staticmethod
    def _flow(root: Path, sequences: list[str] | None, stride: int) -> Found:
        items: list[FlowItem] = []
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
        return Found(items, desc)

    @staticmethod
    def _pose(root: Path, sequences: list[str] | None, stride: int) -> Found:
        items: list[PoseItem] = []
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
        return Found(items, desc)

    @classmethod
    def depth_intrinsics(cls, item: DepthItem) -> np.ndarray:
        """``calib.txt`` of the frame's sequence (SEQ/image/frame.png)."""
        return calibration_K_or_error(item.image.parents[1] / "calib.txt")

"""``kitti-object``: the KITTI object benchmark layout, depth.

``[training/]image_2/NNNNNN.png`` (left colour camera), ``velodyne/NNNNNN.bin`` (the frame's
Velodyne scan) and ``calib/NNNNNN.txt`` (its own calibration: P0–P3, R0_rect, Tr_velo_to_cam).
Ground truth: the scan projected with ``P2 · R0_rect · Tr_velo_to_cam`` by the KITTI raw code
(:func:`geonet_infer.eval.velodyne.object_velodyne_to_depth_map`: same rounding, same nearest point
per pixel, Velodyne forward distance). The frames are single, unrelated images: depth only.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from geonet_infer.errors import InputError
from geonet_infer.eval.datasets.base import (
    DepthItem,
    Found,
    Layout,
    benchmark_root,
    calibration_K_or_error,
)
from geonet_infer.io import list_images

FOLDERS = ("image_2", "velodyne", "calib")


class KittiObject(Layout):
    name = "kitti-object"
    help = {  # geonet-infer eval --help: one entry per task, one string per line
        "depth": (
            "KITTI object benchmark: [training/]image_2/, velodyne/*.bin, calib/*.txt",
            "(P2, R0_rect, Tr_velo_to_cam per frame), scans projected on the fly",
        ),
    }
    tasks = ("depth",)
    depth_crop = "garg"  # KITTI's camera 2 at full resolution, as the raw drives

    @staticmethod
    def detect(task: str, root: Path) -> bool:
        return benchmark_root(root, *FOLDERS) is not None

    @classmethod
    def items(cls, task: str, root: Path, *, sequences: list[str] | None, stride: int, multiview: Path | None) -> Found:
        base = benchmark_root(root, *FOLDERS)
        if base is None:
            raise InputError(
                root / "image_2",
                "KITTI object layout not found: need image_2/, velodyne/ and calib/ (here or in training/)",
                "pass the object benchmark folder or its training/ folder",
            )
        images = list_images(base / "image_2")
        with_scan = [img for img in images if (base / "velodyne" / f"{img.stem}.bin").is_file()]
        if not with_scan:
            raise InputError(
                base / "velodyne", "no frame of image_2/ has a Velodyne scan here", "scans are named like the frames"
            )
        items = []
        for img in with_scan[::stride]:
            calib = base / "calib" / f"{img.stem}.txt"
            if not calib.is_file():  # every frame has its own calibration: never borrow a neighbour's
                raise InputError(
                    calib, "calibration of this frame not found", "each KITTI object frame has calib/NNNNNN.txt"
                )
            items.append(
                DepthItem(img.stem, img, base / "velodyne" / f"{img.stem}.bin", "velodyne-object", calib=calib)
            )
        without_gt = [img.stem for img in images if img not in set(with_scan)]
        warnings = []
        if without_gt:
            names = ", ".join(without_gt[:3]) + (", ..." if len(without_gt) > 3 else "")
            warnings.append(
                f"{base / 'image_2'}: {len(without_gt)} of {len(images)} frames without a scan in velodyne/ "
                f"({names}): not scored"
            )
        desc = f"KITTI object {root.name}, Velodyne scans projected to camera 2 (per-frame calib)"
        return Found(items, desc, without_gt=without_gt, warnings=warnings)

    @classmethod
    def depth_intrinsics(cls, item: DepthItem) -> np.ndarray:
        """K of ``P2`` in the frame's own ``calib/NNNNNN.txt``."""
        return calibration_K_or_error(item.calib or item.image.parents[1] / "calib" / f"{item.image.stem}.txt")

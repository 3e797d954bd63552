"""``kitti-raw``: a KITTI raw drive, depth.

``image_02/data/*.png`` with ground truth either as sparse depth PNGs
(``proj_depth/groundtruth/image_02/*.png``, the KITTI depth benchmark layout) or as Velodyne
scans ``velodyne_points/data/*.bin`` projected on the fly with ``calib_cam_to_cam.txt`` +
``calib_velo_to_cam.txt`` (in the drive folder or up to two levels above, as KITTI's date folder).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from geonet_infer.errors import InputError
from geonet_infer.eval.datasets.base import (
    KITTI_CALIB,
    DepthItem,
    Found,
    Layout,
    _require_dir,
    calibration_K_or_error,
)
from geonet_infer.io import list_images
from geonet_infer.io.layouts import find_up


class KittiRaw(Layout):
    name = "kitti-raw"
    help = {  # geonet-infer eval --help: one entry per task, one string per line
        "depth": (
            "drive folder: image_02/data + proj_depth/groundtruth/image_02 (uint16/256 PNG)",
            "or velodyne_points/data + calib_cam_to_cam.txt, calib_velo_to_cam.txt",
            "(here or up to two levels up), projected on the fly",
        ),
    }
    tasks = ("depth",)
    depth_crop = "garg"

    @staticmethod
    def detect(task: str, root: Path) -> bool:
        return (root / "image_02" / "data").is_dir()

    @classmethod
    def items(cls, task: str, root: Path, *, sequences: list[str] | None, stride: int, multiview: Path | None) -> Found:
        without_gt: list[str] = []
        warnings: list[str] = []
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
        return Found(items, desc, without_gt=without_gt, warnings=warnings)

    @classmethod
    def depth_intrinsics(cls, item: DepthItem) -> np.ndarray:
        """``P_rect_02`` of ``calib_cam_to_cam.txt`` in the drive folder or up to two levels up."""
        drive = item.image.parents[2]  # DRIVE/image_02/data/frame.png
        found = item.calib_dir or find_up(drive, KITTI_CALIB[:1])
        return calibration_K_or_error((found or drive) / KITTI_CALIB[0])

"""The dataset layouts a sequence folder may have, and the calibration each one keeps: one place, read by
``predict``, ``batch`` (through :func:`geonet_infer.io.frames.open_frames`) and ``eval``'s datasets.

=================  ==========================================  ==================================================
layout             the folder given (any of)                   frames; calibration
=================  ==========================================  ==================================================
``kitti_drive``    a KITTI raw drive, its ``image_02`` or       ``image_02/data``; ``calib_cam_to_cam.txt``
                   ``image_02/data``                            (P_rect_02) in the drive or up to two levels up
``kitti_odometry`` ``sequences/NN``, or its ``image_2`` /       ``image_2`` (colour), unless ``image_0`` holds more;
                   ``image_0``                                  ``calib.txt`` P2 / P0; ``times.txt``
``euroc``          the ``mav0`` folder, ``mav0/cam0`` or the    ``cam0/data``; ``cam0/sensor.yaml`` (intrinsics,
                   sequence folder holding ``mav0``; also       radial-tangential distortion: frames undistorted);
                   ``cam0/data``                                ``cam0/data.csv``
``tum_rgbd``       a TUM RGB-D sequence (``rgb.txt`` + ``rgb/``) ``rgb/``; the TUM table's intrinsics when the
                   or its ``rgb``                               folder's name says the camera (freiburg1/2/3)
=================  ==========================================  ==================================================
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from geonet_infer.io.camera import Camera

KITTI_CALIB_NAME = "calib_cam_to_cam.txt"
KITTI_RAW_IMAGES = Path("image_02") / "data"  # KITTI raw: left colour camera, rectified
ODOMETRY_CAMERAS = {"image_2": "P2", "image_0": "P0"}  # the colour camera first, each with its projection matrix
# TUM RGB-D's published intrinsics of its three Kinects (https://cvg.cit.tum.de/data/datasets/rgbd-dataset/
# file_formats): fx fy cx cy and d0..d4 (OpenCV k1 k2 p1 p2 k3) at 640x480; freiburg3's images are undistorted.
TUM_CAMERAS = {
    "freiburg1": (517.3, 516.5, 318.6, 255.3, (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)),
    "freiburg2": (520.9, 521.0, 325.1, 249.7, (0.2312, -0.7849, -0.0033, -0.0001, 0.9172)),
    "freiburg3": (535.4, 539.2, 320.1, 247.6, None),
}
TUM_SIZE = (640, 480)


@dataclass(frozen=True)
class SequenceLayout:
    """A recognised dataset folder: where its frames are and what calibrates them."""

    kind: str  # kitti_drive | kitti_odometry | euroc | tum_rgbd
    root: Path  # the sequence's folder, named ``name`` (drive, sequences/NN, EuRoC's, the TUM sequence)
    images: Path  # the folder of frames
    name: str  # the sequence's name
    calib: Path | None = None  # its calibration file, if it has one
    calib_key: str | None = None  # the projection matrix of a KITTI file that belongs to these frames
    times: Path | None = None  # the frames' times (times.txt, data.csv, rgb.txt)
    tum_camera: str | None = None  # the TUM table's camera the folder's name says

    def camera(self) -> Camera | None:
        """The calibration that comes with the frames, or None."""
        from geonet_infer.io.calib import read_camera

        if self.calib is not None:
            return read_camera(self.calib, self.calib_key)
        if self.tum_camera is not None:
            fx, fy, cx, cy, dist = TUM_CAMERAS[self.tum_camera]
            K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
            source = f"the TUM RGB-D table's {self.tum_camera} camera (the folder's name {self.root.name!r})"
            coeffs = None if dist is None else np.array(dist)
            return Camera(K, coeffs, TUM_SIZE, source, "calibration file").validate()
        return None

    def frame_times(self, names: list[str]) -> np.ndarray | None:
        """The recording times in seconds of the frames named ``names`` (file stems), from the dataset's own
        table (KITTI odometry ``times.txt`` by frame number, EuRoC ``data.csv`` in ns, TUM ``rgb.txt``),
        so that a TUM pose file lines up with the dataset's ground truth; None where a frame is not in
        the table or the layout has none."""
        if self.times is None:
            return None
        try:
            lines = self.times.read_text(encoding="utf-8", errors="replace").splitlines()
            rows = [line.replace(",", " ").split() for line in lines if line.strip() and not line.startswith("#")]
            if self.kind == "kitti_odometry":
                table = {f"{k:06d}": float(row[0]) for k, row in enumerate(rows)}
            elif self.kind == "euroc":
                table = {Path(row[1]).stem: int(row[0]) / 1e9 for row in rows if len(row) >= 2}
            else:  # tum_rgbd: "time rgb/<name>.png"
                table = {Path(row[1]).stem: float(row[0]) for row in rows if len(row) >= 2}
        except (OSError, ValueError, IndexError):
            return None  # a damaged table: frame indices as times, as for a folder of frames
        if not all(name in table for name in names):
            return None
        return np.array([table[name] for name in names], np.float64)


def find_up(folder: Path, names: tuple[str, ...], levels: int = 2) -> Path | None:
    """The first of ``folder`` and its ``levels`` parents that holds every file in ``names``.

    KITTI raw keeps a date's calibration in ``<date>/``, beside its drive folders; extracts
    often copy it into the drive folder itself.
    """
    for candidate in [folder, *list(folder.parents)[:levels]]:
        if all((candidate / n).is_file() for n in names):
            return candidate
    return None


def find_kitti_calib(drive: Path) -> Path | None:
    """``calib_cam_to_cam.txt`` in the drive folder or up to two levels up (KITTI: ``<date>/``)."""
    folder = find_up(drive, (KITTI_CALIB_NAME,))
    return None if folder is None else folder / KITTI_CALIB_NAME


def _image_count(folder: Path) -> int:
    from geonet_infer.io.images import IMAGE_SUFFIXES

    return sum(1 for f in folder.iterdir() if f.suffix.lower() in IMAGE_SUFFIXES)


def _file(path: Path) -> Path | None:
    return path if path.is_file() else None


def _kitti_drive(p: Path) -> SequenceLayout | None:
    if (p / KITTI_RAW_IMAGES).is_dir():
        drive = p
    elif p.name == KITTI_RAW_IMAGES.name and p.parent.name == KITTI_RAW_IMAGES.parent.name:
        drive = p.parent.parent
    elif p.name == KITTI_RAW_IMAGES.parent.name and (p / KITTI_RAW_IMAGES.name).is_dir():
        drive = p.parent
    else:
        return None
    return SequenceLayout("kitti_drive", drive, drive / KITTI_RAW_IMAGES, drive.name, find_kitti_calib(drive))


def _kitti_odometry(p: Path) -> SequenceLayout | None:
    if p.name in ODOMETRY_CAMERAS and (p.parent / "calib.txt").is_file():
        root, images = p.parent, p
    elif (p / "calib.txt").is_file() and any((p / n).is_dir() for n in ODOMETRY_CAMERAS):
        root = p
        found = [p / n for n in ODOMETRY_CAMERAS if (p / n).is_dir()]
        images = max(found, key=_image_count)  # colour unless grey has more frames (an extract); max keeps the first
    else:
        return None
    return SequenceLayout(
        "kitti_odometry", root, images, root.name, root / "calib.txt", ODOMETRY_CAMERAS[images.name],
        _file(root / "times.txt"),
    )  # fmt: skip


def _euroc(p: Path) -> SequenceLayout | None:
    candidates = [p / "mav0" / "cam0", p / "cam0", p] + ([p.parent] if p.name == "data" else [])
    for cam in candidates:  # the sequence folder, mav0, cam0, cam0/data
        if (cam / "data").is_dir() and (cam / "sensor.yaml").is_file():
            root = cam.parent.parent if cam.parent.name == "mav0" else cam.parent  # the sequence, named
            return SequenceLayout(
                "euroc", root, cam / "data", root.name, cam / "sensor.yaml", None, _file(cam / "data.csv")
            )
    return None


def _tum(p: Path) -> SequenceLayout | None:
    root = p.parent if p.name == "rgb" else p
    if not ((root / "rgb.txt").is_file() and (root / "rgb").is_dir()):
        return None
    match = re.search(r"freiburg(\d)", root.name)
    camera = f"freiburg{match.group(1)}" if match and f"freiburg{match.group(1)}" in TUM_CAMERAS else None
    return SequenceLayout("tum_rgbd", root, root / "rgb", root.name, None, None, root / "rgb.txt", camera)


def find_layout(path: str | Path) -> SequenceLayout | None:
    """The dataset layout of a folder (see the module docstring), or None for a plain folder of frames."""
    p = Path(os.path.abspath(path))  # lexical: keeps a symlinked image_02/data inside its drive layout
    if not p.is_dir():
        return None
    for find in (_kitti_drive, _kitti_odometry, _euroc, _tum):
        layout = find(p)
        if layout is not None:
            return layout
    return None

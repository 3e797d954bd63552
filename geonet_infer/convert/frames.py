"""The frames a conversion is calibrated (INT8) and verified on, as each graph's feeds. No onnx needed."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from geonet_infer.conventions import kitti_like_K, scale_intrinsics
from geonet_infer.core.cascade import InputSpec, calibration_input, check_image, posenet_order
from geonet_infer.errors import GeoNetError, InputError
from geonet_infer.io import list_images, read_calib_K, read_image
from geonet_infer.io.layouts import find_layout


def load_frames(
    folder: str | Path, height: int, width: int, max_frames: int, min_frames: int = 1
) -> tuple[list[np.ndarray], tuple[int, int]]:
    """The first ``max_frames`` consecutive frames, resized (INTER_AREA) to H x W.

    Returns (frames uint8 RGB, original (H, W) of the first frame).
    """
    files = list_images(folder)[:max_frames]
    if len(files) < min_frames:
        raise InputError(
            folder, f"{len(files)} images, calibration needs at least {min_frames}", "add consecutive frames"
        )
    frames, original = [], None
    for f in files:
        rgb = check_image(read_image(f), f)  # what the runtime refuses is no calibration frame either
        original = original or rgb.shape[:2]
        frames.append(cv2.resize(rgb, (width, height), interpolation=cv2.INTER_AREA))
    return frames, original  # type: ignore[return-value]


def calibration_intrinsics(
    folder: str | Path, original_hw: tuple[int, int], height: int, width: int
) -> tuple[np.ndarray, str]:
    """K at H x W for the calibration frames and where it came from.

    The frames' dataset layout first (:mod:`geonet_infer.io.layouts`: KITTI raw and odometry, EuRoC,
    TUM RGB-D, with the calibration predict reads for them), then ``calib.txt`` (key ``K``) in the
    folder or its parent (the synthetic layout ``<seq>/image/*.png`` + ``<seq>/calib.txt``);
    otherwise :func:`~geonet_infer.conventions.kitti_like_K` (only ResFlowNet's calibration inputs
    depend on it).
    """
    folder = Path(folder)
    layout = find_layout(folder)
    camera = None if layout is None else layout.camera()
    if camera is not None:
        size = camera.size or (original_hw[1], original_hw[0])  # a file without a size: the frames'
        K = scale_intrinsics(camera.K, width / size[0], height / size[1])
        return K.astype(np.float32), camera.source
    sx, sy = width / original_hw[1], height / original_hw[0]
    candidates = [(folder / "calib.txt", "K"), (folder.parent / "calib.txt", "K")]
    for path, key in candidates:
        if path.is_file():
            try:
                K = read_calib_K(path, key)
            except GeoNetError:
                continue
            return scale_intrinsics(K, sx, sy).astype(np.float32), f"{path} ({key})"
    return kitti_like_K(height, width).astype(
        np.float32
    ), "assumed KITTI-like (no calib.txt / calib_cam_to_cam.txt found)"


def depth_feeds(frames: Sequence[np.ndarray], spec: InputSpec) -> list[dict]:
    return [{"image": spec.to_network(f)[None]} for f in frames]


def snippets(frames: Sequence[np.ndarray], seq_length: int) -> list[list[np.ndarray]]:
    """Every window of ``seq_length`` consecutive frames (temporal order)."""
    return [list(frames[i : i + seq_length]) for i in range(len(frames) - seq_length + 1)]


def pose_feeds(frames: Sequence[np.ndarray], spec: InputSpec) -> list[dict]:
    """PoseNet inputs [target] + sources (``cascade.posenet_order``) for every window."""
    L = spec.seq_length
    order = posenet_order(L // 2, L)
    return [
        {"snippet": np.concatenate([spec.to_network(window[i]) for i in order])[None]} for window in snippets(frames, L)
    ]


def resflow_feeds(predictor, frames: Sequence[np.ndarray], K: np.ndarray) -> list[dict]:
    """12-channel inputs target -> every source, from the fp32 runtime cascade (``Predictor``)."""
    L = predictor.seq_length
    return [
        {"flow_input": calibration_input(predictor.graph_set, predictor.spec, window, K, source_index=src)}
        for window in snippets(frames, L)
        for src in range(L - 1)
    ]

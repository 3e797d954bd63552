"""INT8 (QDQ) copies of the exported graphs with onnxruntime's static quantiser.

Recipe (onnx_notes.md section 2): ``quant_pre_process`` (shape inference +
ORT basic optimisation), then ``quantize_static`` in QDQ format, per-channel
int8 weights, uint8 activations (x86 recommendation of the 1.32 docstring),
``reduce_range=False`` (right for CPUs with VNNI; pass ``--reduce-range`` for
older AVX2/AVX-512 CPUs without VNNI, where u8*s8 products can saturate),
MinMax calibration by default.

Calibration inputs come from a folder of real or synthetic frames resized to
H x W with ``cv2.INTER_AREA``:

* depthnet: every frame;
* posenet: snippets of ``seq_length`` consecutive frames [target, sources];
* resflownet: 12-channel inputs made by running the *fp32* depthnet, posenet
  and rigidflow graphs on consecutive frames (target -> every source), i.e. the
  distribution ResFlowNet sees at inference.

``rigidflow`` is never quantised: it is geometry (projection, grid sampling),
not convolutions, and its output is measured in pixels.
"""
from __future__ import annotations

import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Sequence

import cv2
import numpy as np
import onnx

from geonet_infer import formats
from geonet_infer.conventions import scale_intrinsics
from geonet_infer.errors import GeoNetInputError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".ppm")
QUANTIZED_GRAPHS = ("depthnet", "posenet", "resflownet")
FP32_ONLY_GRAPHS = ("rigidflow",)
# Fallback intrinsics for a calibration folder without calibration: KITTI's rectified
# camera 02 (fx = fy = 721.5377, cx = 609.5593, cy = 172.854 at 1242 x 375), used as
# fractions of the image size. Only ResFlowNet's calibration inputs depend on it.
KITTI_K_FRACTIONS = (721.5377 / 1242, 609.5593 / 1242, 721.5377 / 375, 172.854 / 375)


@dataclass(frozen=True)
class QuantSettings:
    per_channel: bool = True
    reduce_range: bool = False
    calibrate_method: str = "minmax"  # minmax | entropy | percentile
    max_frames: int = 24  # calibration frames read from the folder

    def describe(self) -> dict:
        return {"method": "onnxruntime quantize_static, QDQ", "activation_type": "uint8", "weight_type": "int8",
                "per_channel": self.per_channel, "reduce_range": self.reduce_range,
                "calibrate_method": self.calibrate_method}


# ----------------------------------------------------------------------------- frames
def list_images(folder: str | Path) -> list[Path]:
    """Sorted image files of a folder; GeoNetInputError naming the folder if there are none."""
    folder = Path(folder)
    if not folder.is_dir():
        raise GeoNetInputError(folder, "calibration folder not found", "pass --calib-data DIR, a folder of frames")
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())
    if not files:
        raise GeoNetInputError(folder, "no images in the calibration folder",
                               f"it needs consecutive frames ({', '.join(IMAGE_SUFFIXES)}), e.g. a KITTI image_02/data folder")
    return files


def load_frames(folder: str | Path, height: int, width: int, max_frames: int,
                min_frames: int = 1) -> tuple[list[np.ndarray], tuple[int, int]]:
    """The first ``max_frames`` consecutive frames, resized (INTER_AREA) to H x W.

    Returns (frames uint8 RGB, original (H, W) of the first frame).
    """
    files = list_images(folder)[:max_frames]
    if len(files) < min_frames:
        raise GeoNetInputError(folder, f"{len(files)} images, calibration needs at least {min_frames}",
                               "add consecutive frames")
    frames, original = [], None
    for f in files:
        rgb = formats.read_image(f)
        original = original or rgb.shape[:2]
        frames.append(cv2.resize(rgb, (width, height), interpolation=cv2.INTER_AREA))
    return frames, original


def calibration_intrinsics(folder: str | Path, original_hw: tuple[int, int], height: int,
                           width: int) -> tuple[np.ndarray, str]:
    """K at H x W for the calibration frames and where it came from.

    Looks for ``calib.txt`` (key ``K``) in the folder or its parent (synthetic
    layout ``<seq>/image/*.png`` + ``<seq>/calib.txt``), then for a KITTI raw
    ``calib_cam_to_cam.txt`` (key ``P_rect_02``) two levels up
    (``<date>/image_02/data``); otherwise KITTI-like fractions of the image size.
    """
    folder = Path(folder)
    sx, sy = width / original_hw[1], height / original_hw[0]
    candidates = [(folder / "calib.txt", "K"), (folder.parent / "calib.txt", "K"),
                  (folder.parent.parent / "calib_cam_to_cam.txt", "P_rect_02"),
                  (folder.parent / "calib_cam_to_cam.txt", "P_rect_02")]
    for path, key in candidates:
        if path.is_file():
            try:
                K = formats.read_calib_K(path, key)
            except GeoNetInputError:
                continue
            return scale_intrinsics(K, sx, sy).astype(np.float32), f"{path} ({key})"
    fx, cx, fy, cy = KITTI_K_FRACTIONS
    K = np.array([[fx * width, 0, cx * width], [0, fy * height, cy * height], [0, 0, 1]], np.float32)
    return K, "assumed KITTI-like (no calib.txt / calib_cam_to_cam.txt found)"


# ----------------------------------------------------------------------------- feeds
def depth_feeds(frames: Sequence[np.ndarray]) -> list[dict]:
    from export.verify import to_network
    return [{"image": to_network(f)} for f in frames]


def snippets(frames: Sequence[np.ndarray], seq_length: int) -> list[list[np.ndarray]]:
    """Every window of ``seq_length`` consecutive frames (temporal order)."""
    return [list(frames[i:i + seq_length]) for i in range(len(frames) - seq_length + 1)]


def pose_feeds(frames: Sequence[np.ndarray], seq_length: int) -> list[dict]:
    from export.verify import to_network
    feeds = []
    mid = seq_length // 2
    for window in snippets(frames, seq_length):
        norm = [to_network(f) for f in window]
        feeds.append({"snippet": np.concatenate([norm[mid]] + norm[:mid] + norm[mid + 1:], axis=1)})
    return feeds


def resflow_feeds(cascade, frames: Sequence[np.ndarray], K: np.ndarray, seq_length: int) -> list[dict]:
    """12-channel inputs target -> every source from the fp32 depth/pose/rigidflow graphs."""
    feeds = []
    for window in snippets(frames, seq_length):
        depth = cascade.depth(window[seq_length // 2])
        poses = cascade.poses(window)
        for src in range(seq_length - 1):
            x, _ = cascade.flow_input(window, K, source_index=src, depth=depth, poses=poses)
            feeds.append({"flow_input": x})
    return feeds


class _ListReader:
    """CalibrationDataReader over a list of feed dicts (duck-typed: get_next / rewind)."""

    def __init__(self, feeds: Iterable[dict]):
        self.feeds = list(feeds)
        self._it = iter(self.feeds)

    def get_next(self):
        return next(self._it, None)

    def rewind(self):
        self._it = iter(self.feeds)


# ----------------------------------------------------------------------------- quantise
def quantize_graph(fp32_path: str | Path, out_path: str | Path, feeds: Sequence[dict],
                   settings: QuantSettings = QuantSettings()) -> None:
    """Pre-process + quantize_static (QDQ) one graph; keeps the fp32 file's metadata_props."""
    from onnxruntime.quantization import CalibrationDataReader, CalibrationMethod, QuantFormat, QuantType, quantize_static
    from onnxruntime.quantization.shape_inference import quant_pre_process

    if not feeds:
        raise GeoNetInputError(None, f"no calibration inputs for {Path(fp32_path).name}",
                               "the calibration folder needs at least seq_length consecutive frames")
    methods = {"minmax": CalibrationMethod.MinMax, "entropy": CalibrationMethod.Entropy,
               "percentile": CalibrationMethod.Percentile}
    if settings.calibrate_method not in methods:
        raise GeoNetInputError(None, f"unknown calibration method {settings.calibrate_method!r}",
                               f"choose one of {', '.join(methods)}")
    fp32_path, out_path = Path(fp32_path), Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)

    class Reader(_ListReader, CalibrationDataReader):
        pass

    work = Path(tempfile.mkdtemp(prefix="quant-", dir=out_path.parent))
    try:
        pre = work / "pre.onnx"
        # ONNX shape inference + ORT optimisation only. ORT's *symbolic* shape inference (meant for
        # transformers) does not complete on these graphs, and on failure it dumps
        # sym_shape_infer_temp.onnx plus external-data files into the current directory.
        quant_pre_process(str(fp32_path), str(pre), skip_symbolic_shape=True)
        quantize_static(
            str(pre), str(work / "q.onnx"), Reader(feeds), quant_format=QuantFormat.QDQ,
            per_channel=settings.per_channel, reduce_range=settings.reduce_range,
            activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8,
            calibrate_method=methods[settings.calibrate_method],
            extra_options={"CalibTensorRangeSymmetric": False})
        model = onnx.load(str(work / "q.onnx"))
        source_meta = {p.key: p.value for p in onnx.load(str(fp32_path), load_external_data=False).metadata_props}
        del model.metadata_props[:]
        for key in sorted(source_meta):
            entry = model.metadata_props.add()
            entry.key = key
            entry.value = "int8" if key == "geonet.precision" else source_meta[key]
        onnx.save_model(model, str(out_path), save_as_external_data=False)
    finally:
        shutil.rmtree(work, ignore_errors=True)

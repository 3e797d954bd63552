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
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import onnx

from geonet_infer.conventions import kitti_like_K, scale_intrinsics
from geonet_infer.errors import GeoNetInputError
from geonet_infer.io import list_images, read_calib_K, read_image
from geonet_infer.preprocess import InputSpec, snippet_indices

FP32_ONLY_GRAPHS = ("rigidflow",)
CALIBRATION_METHODS = ("minmax", "entropy", "percentile")  # onnxruntime CalibrationMethod MinMax/Entropy/Percentile
# Tensors whose consumers stay fp32 in the int8 graph: PoseNet's 4x4 matrices are built from
# the pose vector with Sin/Cos/Concat; quantised, they collapsed to ~identity (no motion).
FLOAT_AFTER = {"posenet": ("pose",)}


@dataclass(frozen=True)
class QuantSettings:
    per_channel: bool = True
    reduce_range: bool = False
    calibrate_method: str = "minmax"  # one of CALIBRATION_METHODS
    max_frames: int = 24  # calibration frames read from the folder

    def describe(self) -> dict:
        return {
            "method": "onnxruntime quantize_static, QDQ",
            "activation_type": "uint8",
            "weight_type": "int8",
            "per_channel": self.per_channel,
            "reduce_range": self.reduce_range,
            "calibrate_method": self.calibrate_method,
        }


# ----------------------------------------------------------------------------- frames
def load_frames(
    folder: str | Path, height: int, width: int, max_frames: int, min_frames: int = 1
) -> tuple[list[np.ndarray], tuple[int, int]]:
    """The first ``max_frames`` consecutive frames, resized (INTER_AREA) to H x W.

    Returns (frames uint8 RGB, original (H, W) of the first frame).
    """
    files = list_images(folder)[:max_frames]
    if len(files) < min_frames:
        raise GeoNetInputError(
            folder, f"{len(files)} images, calibration needs at least {min_frames}", "add consecutive frames"
        )
    frames, original = [], None
    for f in files:
        rgb = read_image(f)
        original = original or rgb.shape[:2]
        frames.append(cv2.resize(rgb, (width, height), interpolation=cv2.INTER_AREA))
    return frames, original


def calibration_intrinsics(
    folder: str | Path, original_hw: tuple[int, int], height: int, width: int
) -> tuple[np.ndarray, str]:
    """K at H x W for the calibration frames and where it came from.

    Looks for ``calib.txt`` (key ``K``) in the folder or its parent (synthetic
    layout ``<seq>/image/*.png`` + ``<seq>/calib.txt``), then for a KITTI raw
    ``calib_cam_to_cam.txt`` (key ``P_rect_02``) two levels up
    (``<date>/image_02/data``); otherwise :func:`~geonet_infer.conventions.kitti_like_K`
    (only ResFlowNet's calibration inputs depend on it).
    """
    folder = Path(folder)
    sx, sy = width / original_hw[1], height / original_hw[0]
    candidates = [
        (folder / "calib.txt", "K"),
        (folder.parent / "calib.txt", "K"),
        (folder.parent.parent / "calib_cam_to_cam.txt", "P_rect_02"),
        (folder.parent / "calib_cam_to_cam.txt", "P_rect_02"),
    ]
    for path, key in candidates:
        if path.is_file():
            try:
                K = read_calib_K(path, key)
            except GeoNetInputError:
                continue
            return scale_intrinsics(K, sx, sy).astype(np.float32), f"{path} ({key})"
    return kitti_like_K(height, width).astype(
        np.float32
    ), "assumed KITTI-like (no calib.txt / calib_cam_to_cam.txt found)"


# ----------------------------------------------------------------------------- feeds
def depth_feeds(frames: Sequence[np.ndarray], spec: InputSpec) -> list[dict]:
    return [{"image": spec.to_network(f)[None]} for f in frames]


def snippets(frames: Sequence[np.ndarray], seq_length: int) -> list[list[np.ndarray]]:
    """Every window of ``seq_length`` consecutive frames (temporal order)."""
    return [list(frames[i : i + seq_length]) for i in range(len(frames) - seq_length + 1)]


def pose_feeds(frames: Sequence[np.ndarray], spec: InputSpec) -> list[dict]:
    """PoseNet inputs [target] + sources (``preprocess.snippet_indices`` order) for every window."""
    L = spec.seq_length
    order = snippet_indices(L // 2, L, L)
    return [
        {"snippet": np.concatenate([spec.to_network(window[i]) for i in order])[None]} for window in snippets(frames, L)
    ]


def resflow_feeds(predictor, frames: Sequence[np.ndarray], K: np.ndarray) -> list[dict]:
    """12-channel inputs target -> every source, from the fp32 runtime cascade (``Predictor``)."""
    L = predictor.seq_length
    return [
        {"flow_input": predictor.resflow_input(window, K, source_index=src)}
        for window in snippets(frames, L)
        for src in range(L - 1)
    ]


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
def downstream_nodes(model: onnx.ModelProto, tensors: Sequence[str]) -> list[str]:
    """Names of every node that (transitively) consumes one of ``tensors``."""
    reached, names = set(tensors), []
    for node in model.graph.node:  # ONNX graphs are topologically sorted
        if reached.intersection(node.input):
            names.append(node.name)
            reached.update(node.output)
    return names


def quantize_graph(
    fp32_path: str | Path,
    out_path: str | Path,
    feeds: Sequence[dict],
    settings: QuantSettings = QuantSettings(),
    float_after: Sequence[str] = (),
) -> None:
    """Pre-process + quantize_static (QDQ) one graph; keeps the fp32 file's metadata_props."""
    from onnxruntime.quantization import (
        CalibrationDataReader,
        CalibrationMethod,
        QuantFormat,
        QuantType,
        quantize_static,
    )
    from onnxruntime.quantization.shape_inference import quant_pre_process

    if not feeds:
        raise GeoNetInputError(
            None,
            f"no calibration inputs for {Path(fp32_path).name}",
            "the calibration folder needs at least seq_length consecutive frames",
        )
    methods = dict(
        zip(CALIBRATION_METHODS, (CalibrationMethod.MinMax, CalibrationMethod.Entropy, CalibrationMethod.Percentile))
    )
    if settings.calibrate_method not in methods:
        raise GeoNetInputError(
            None, f"unknown calibration method {settings.calibrate_method!r}", f"choose one of {', '.join(methods)}"
        )
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
        exclude = downstream_nodes(onnx.load(str(pre)), float_after) if float_after else []
        if float_after and not exclude:
            raise GeoNetInputError(fp32_path, f"no nodes consume {list(float_after)}", "re-export the fp32 graph")
        quantize_static(
            str(pre),
            str(work / "q.onnx"),
            Reader(feeds),
            quant_format=QuantFormat.QDQ,
            per_channel=settings.per_channel,
            reduce_range=settings.reduce_range,
            activation_type=QuantType.QUInt8,
            weight_type=QuantType.QInt8,
            calibrate_method=methods[settings.calibrate_method],
            nodes_to_exclude=exclude,
            extra_options={"CalibTensorRangeSymmetric": False},
        )
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

"""INT8 graphs of a model directory's fp32 ones (QDQ, calibrated on the user's frames), for both writers:
``python -m export`` and ``geonet-infer convert``. Needs the ``onnx`` package (the ``[convert]`` extra)."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from pathlib import Path

from geonet_infer.convert.manifest import FP32_ONLY_GRAPHS, quantization_record
from geonet_infer.errors import BackendUnavailableError
from geonet_infer.models.manifest import GraphEntry, Quantization, file_sha256

CONVERT_EXTRA_HINT = "pip install 'geonet-infer[convert]' (it adds the onnx package, which INT8 calibration needs)"


def import_quantize():
    """The quantizer module; a one-line error naming the extra when ``onnx`` is missing."""
    try:
        from geonet_infer.convert import quantize
    except ImportError as exc:
        raise BackendUnavailableError(
            None, f"--precision int8 needs the onnx package ({exc})", CONVERT_EXTRA_HINT
        ) from None
    return quantize


def quantize_directory(
    folder: Path,
    fp32: dict[str, GraphEntry],
    *,
    arch: str,
    height: int,
    width: int,
    seq_length: int,
    calib_data: Path,
    settings,
    write_interim: Callable[[dict], None],
    log: Callable[[str], None],
) -> tuple[dict[str, GraphEntry], Quantization]:
    """``folder/int8/<graph>.onnx`` for every fp32 graph but the fp32-only ones, and the manifest's
    quantization record (its accuracy delta left to the caller). ``write_interim(graphs)`` writes a
    manifest over the graphs so far: ResFlowNet is calibrated on the fp32 cascade's own rigid flow."""
    qz = import_quantize()
    from geonet_infer.convert.int8_arith import int8_kernels
    from geonet_infer.core.cascade import InputSpec
    from geonet_infer.core.predictor import Predictor

    frames, original = qz.load_frames(calib_data, height, width, settings.max_frames, min_frames=seq_length)
    K, k_source = qz.calibration_intrinsics(calib_data, original, height, width)
    write_interim({"fp32": fp32})
    spec = InputSpec.from_conventions(height, width, seq_length)
    feeds = {"depthnet": qz.depth_feeds(frames, spec), "posenet": qz.pose_feeds(frames, spec)}
    if "resflownet" in fp32:
        feeds["resflownet"] = qz.resflow_feeds(Predictor(folder, "fp32"), frames, K)
    entries, plan_notes = {}, {}
    for graph, entry in fp32.items():
        if graph in FP32_ONLY_GRAPHS:
            entries[graph] = entry  # same file: the int8 set reuses fp32 rigidflow.onnx
            continue
        started = time.perf_counter()
        file = f"int8/{graph}.onnx"
        notes = qz.quantize_graph(folder / entry.file, folder / file, feeds[graph], settings, qz.plan_for(graph, arch))
        if notes:
            plan_notes[graph] = notes
        entries[graph] = dataclasses.replace(
            entry,
            file=file,
            sha256=file_sha256(folder / file),
            precision="int8",
            exporter=f"onnxruntime quantize_static QDQ of {entry.file}",
        )
        size = (folder / file).stat().st_size / 2**20
        log(
            f"  int8 {graph}.onnx  {size:.1f} MiB  ({len(feeds[graph])} calibration inputs, "
            f"{time.perf_counter() - started:.1f} s)"
        )
        for line in notes:
            log(f"    {line}")
    import onnx

    kernels = {  # which x86 INT8 kernels compute each quantised graph exactly (issue 45)
        graph: int8_kernels(onnx.load(str(folder / e.file)))
        for graph, e in entries.items()
        if graph not in FP32_ONLY_GRAPHS
    }
    samples = {g: len(f) for g, f in feeds.items() if g in entries}
    record = quantization_record(
        settings.describe(), str(calib_data), samples, k_source, plan_notes, None, None, kernels
    )
    return entries, record

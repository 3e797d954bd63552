"""Build the manifest of a model directory (schema: ``geonet_infer.models.manifest``), for both writers:
``python -m export`` (torch) and ``geonet-infer convert`` (no torch).

Also the per-graph ``metadata_props`` written into every ONNX file, so a single
graph carries its key conventions even without the manifest.
"""

from __future__ import annotations

import datetime as _dt
import json
from pathlib import Path

from geonet_infer import conventions
from geonet_infer.io.atomic import json_safe
from geonet_infer.models.manifest import (
    SCHEMA_VERSION,
    GraphEntry,
    Manifest,
    Provenance,
    Quantization,
    TensorSpec,
    file_sha256,
)

FP32_ONLY_GRAPHS = ("rigidflow",)  # the geometric op stays fp32: the int8 set's entry is the fp32 file


def graph_notes(graph: str, alpha: float) -> str:
    """One-line I/O contract of ``graph`` for its ``geonet.io`` metadata, with the numbers taken from
    :mod:`geonet_infer.conventions`; ``alpha``: the photometric weight baked into ``rigidflow.onnx``."""
    norm, pose, sampler = conventions.IMAGE_NORM, conventions.POSE, conventions.SAMPLER
    offset = conventions.DispHead.offset
    image = f"normalised RGB (x/255*{norm.scale:g}{norm.offset:+g})"
    warp = f"bilinear, align_corners={sampler.align_corners}, {sampler.padding} padding"
    notes = {
        "depthnet": f"image (B,3,H,W) {image} -> disparity (B,1,H,W) = scale*sigmoid+{offset:g}, "
        "depth = 1/disparity; scale 0 only",
        "posenet": f"snippet (B,3L,H,W) {image}, channels [target, sources in temporal order] -> "
        f"pose (B,L-1,6) [{','.join(pose.vector)}] (x{pose.output_scale:g} inside), "
        f"pose_matrix (B,L-1,4,4) {pose.direction.replace('_', ' ')}, {pose.rotation}",
        "rigidflow": f"depth (B,1,H,W) of the target, pose (B,6) {pose.direction.replace('_', ' ')}, "
        f"intrinsics (B,3,3) at HxW, target/source (B,3,H,W) {image} -> rigid_flow (B,2,H,W) px "
        f"(x then y), warped (B,3,H,W) source sampled at grid+flow ({warp}), error (B,1,H,W) = "
        f"||{alpha:g}*DSSIM+{1 - alpha:.2f}*|warped-target| + 1e-10||_2 over channels",
        "resflownet": "flow_input (B,12,H,W) = [target(3), source(3), warped(3), rigid_flow(2) px, error(1)] -> "
        "residual_flow (B,2,H,W) px, flow = residual_flow + rigid_flow, scale 0",
    }
    return notes[graph]


def versions() -> dict:
    """Versions of what wrote the files, beyond the exporter (``export`` adds torch, onnx, onnxscript)."""
    from importlib import metadata

    import numpy
    import onnxruntime

    try:
        own = metadata.version("geonet-infer")
    except metadata.PackageNotFoundError:  # run from a source tree that is not installed
        own = "source tree"
    return {"geonet-infer": own, "onnxruntime": onnxruntime.__version__, "numpy": numpy.__version__}


def utc_now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).replace(microsecond=0).isoformat()


def graph_metadata(
    graph: str,
    arch: str,
    height: int,
    width: int,
    seq_length: int,
    precision: str,
    random_init: bool,
    photometric_alpha: float,
) -> dict[str, str]:
    """``metadata_props`` of one ONNX file: its I/O contract and the conventions it relies on."""
    conv = conventions.as_dict()
    meta = {
        "geonet.graph": graph,
        "geonet.arch": arch,
        "geonet.precision": precision,
        "geonet.height": str(height),
        "geonet.width": str(width),
        "geonet.seq_length": str(seq_length),
        "geonet.random_init": json.dumps(random_init),
        "geonet.io": graph_notes(graph, photometric_alpha),
        "geonet.schema_version": str(SCHEMA_VERSION),
        "geonet.conventions": json.dumps(conv, sort_keys=True),
    }
    meta["geonet.image_norm"] = json.dumps(conv["image_norm"])  # every graph takes normalised images
    meta["geonet.channel_order"] = conv["channel_order"]
    if graph == "depthnet":
        meta["geonet.disp_head"] = json.dumps(conv["disp_heads"][arch])
    if graph in ("posenet", "rigidflow"):
        meta["geonet.pose"] = json.dumps(conv["pose"])
    if graph == "rigidflow":
        meta["geonet.sampler"] = json.dumps(conv["sampler"])
        meta["geonet.intrinsics"] = json.dumps(conv["intrinsics"])
    return meta


def graph_entry(
    directory: Path,
    file: str,
    io: dict,
    opset: int,
    precision: str,
    exporter: str,
) -> GraphEntry:
    """Manifest entry of ``directory/file`` (hash computed from the file as written); ``io``:
    ``{"inputs": [[name, shape]...], "outputs": [...], "dtype": ...}``."""
    return GraphEntry(
        file=file,
        sha256=file_sha256(directory / file),
        opset=opset,
        precision=precision,
        inputs=tuple(TensorSpec(n, tuple(s), io["dtype"]) for n, s in io["inputs"]),
        outputs=tuple(TensorSpec(n, tuple(s), io["dtype"]) for n, s in io["outputs"]),
        exporter=exporter,
    )


def build_manifest(
    *,
    height: int,
    width: int,
    seq_length: int,
    arch: str,
    random_init: bool,
    graphs: dict,
    prov: Provenance,
    metrics: dict | None,
    quantization: Quantization | None,
    photometric_alpha: float,
) -> Manifest:
    """``photometric_alpha``: the α baked into ``rigidflow.onnx`` (``export.wrappers.photometric_alpha``
    of the exported model), recorded beside the conventions ``geonet_infer.conventions`` defines."""
    return Manifest(
        schema_version=SCHEMA_VERSION,
        height=height,
        width=width,
        seq_length=seq_length,
        arch=arch,
        random_init=random_init,
        precisions=tuple(graphs),
        graphs=graphs,
        conventions={**conventions.as_dict(), conventions.PHOTOMETRIC_ALPHA: photometric_alpha},
        provenance=prov,
        metrics=json_safe(metrics or {}),
        quantization=quantization,
    )


def quantization_record(
    settings_description: dict,
    calibration_data: str,
    samples: dict,
    intrinsics_source: str,
    graph_notes: dict,
    accuracy_delta: dict | None,
    reason: str | None,
    int8_kernels: dict | None = None,
) -> Quantization:
    return Quantization(
        method=settings_description["method"],
        activation_type=settings_description["activation_type"],
        weight_type=settings_description["weight_type"],
        per_channel=settings_description["per_channel"],
        reduce_range=settings_description["reduce_range"],
        calibrate_method=settings_description["calibrate_method"],
        calibration_data=calibration_data,
        calibration_samples=dict(samples),
        calibration_intrinsics=intrinsics_source,
        fp32_graphs=FP32_ONLY_GRAPHS,
        graph_notes={g: list(lines) for g, lines in graph_notes.items()},
        accuracy_delta=json_safe(accuracy_delta),
        accuracy_delta_reason=reason,
        op_types=tuple(settings_description.get("op_types", ())),
        int8_kernels=dict(int8_kernels or {}),
    )

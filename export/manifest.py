"""Build the manifest of an exported model directory (schema: ``geonet_infer.core.manifest``).

Also the per-graph ``metadata_props`` written into every ONNX file, so a single
graph carries its key conventions even without the manifest.
"""

from __future__ import annotations

import datetime as _dt
import json
import math
from pathlib import Path

from export.wrappers import io_spec
from geonet_infer import conventions
from geonet_infer.bench.environment import git_commit
from geonet_infer.core.manifest import (
    SCHEMA_VERSION,
    GraphEntry,
    Manifest,
    Provenance,
    Quantization,
    TensorSpec,
    file_sha256,
)
from training.losses import LossWeights

REPO_ROOT = Path(__file__).resolve().parents[1]


def graph_notes(graph: str) -> str:
    """One-line I/O contract of ``graph`` for its ``geonet.io`` metadata, with the numbers taken from
    :mod:`geonet_infer.conventions` (and the photometric weight from training's ``LossWeights``)."""
    norm, pose, sampler = conventions.IMAGE_NORM, conventions.POSE, conventions.SAMPLER
    offset = conventions.DispHead.offset
    image = f"normalised RGB (x/255*{norm.scale:g}{norm.offset:+g})"
    warp = f"bilinear, align_corners={sampler.align_corners}, {sampler.padding} padding"
    alpha = LossWeights.alpha_recon
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
    import onnx
    import onnxruntime
    import onnxscript
    import torch

    return {
        "torch": torch.__version__,
        "onnx": onnx.__version__,
        "onnxruntime": onnxruntime.__version__,
        "onnxscript": getattr(onnxscript, "__version__", "unknown"),
    }


def utc_now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).replace(microsecond=0).isoformat()


def json_safe(value):
    """Recursively turn non-finite floats into None and tuples into lists (strict JSON)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if hasattr(value, "item") and not isinstance(value, (str, bytes)):  # numpy / torch scalars
        try:
            return json_safe(value.item())
        except (TypeError, ValueError):
            pass
    return value


def graph_metadata(
    graph: str, arch: str, height: int, width: int, seq_length: int, precision: str, random_init: bool
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
        "geonet.io": graph_notes(graph),
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
    graph: str,
    height: int,
    width: int,
    seq_length: int,
    opset: int,
    precision: str,
    exporter: str,
) -> GraphEntry:
    """Manifest entry of ``directory/file`` (hash computed from the file as written)."""
    spec = io_spec(graph, height, width, seq_length)
    return GraphEntry(
        file=file,
        sha256=file_sha256(directory / file),
        opset=opset,
        precision=precision,
        inputs=tuple(TensorSpec(n, tuple(s), spec.dtype) for n, s in spec.inputs),
        outputs=tuple(TensorSpec(n, tuple(s), spec.dtype) for n, s in spec.outputs),
        exporter=exporter,
    )


def provenance(
    arch: str, random_init: bool, exporter: str, checkpoint: str | Path | None = None, ckpt: dict | None = None
) -> Provenance:
    cfg = (ckpt or {}).get("config", {})
    data_dirs = [d for d in (cfg.get("data_dir"), *cfg.get("extra_data_dirs", ())) if d]
    return Provenance(
        architecture=arch,
        random_init=random_init,
        export_date=utc_now(),
        git_commit=git_commit(REPO_ROOT),
        checkpoint=str(checkpoint) if checkpoint else None,
        checkpoint_sha256=file_sha256(checkpoint) if checkpoint else None,
        checkpoint_stage=(ckpt or {}).get("stage"),
        checkpoint_step=(ckpt or {}).get("step"),
        training_command=(ckpt or {}).get("command"),
        data_dir=" + ".join(data_dirs) or None,  # every prepared folder the stage trained on
        exporter=exporter,
        versions=versions(),
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
    photometric_alpha: float = LossWeights.alpha_recon,
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
    from export.quantize import FP32_ONLY_GRAPHS

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
        fp32_graphs=tuple(FP32_ONLY_GRAPHS),
        graph_notes={g: list(lines) for g, lines in graph_notes.items()},
        accuracy_delta=json_safe(accuracy_delta),
        accuracy_delta_reason=reason,
        op_types=tuple(settings_description.get("op_types", ())),
        int8_kernels=dict(int8_kernels or {}),
    )

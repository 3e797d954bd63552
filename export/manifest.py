"""What the torch exporter adds to a model directory's manifest: its provenance (checkpoint, training
command, versions of torch, onnx and onnxscript) and graph entries from the wrappers' I/O contracts.
The manifest itself and the graphs' metadata are built by :mod:`geonet_infer.convert.manifest`,
shared with ``geonet-infer convert``."""

from __future__ import annotations

from pathlib import Path

from export.wrappers import io_spec
from geonet_infer.bench.environment import git_commit
from geonet_infer.convert import manifest as cmf
from geonet_infer.models.manifest import GraphEntry, Provenance, file_sha256

REPO_ROOT = Path(__file__).resolve().parents[1]


def versions() -> dict:
    import onnx
    import onnxscript
    import torch

    return {
        "torch": torch.__version__,
        "onnx": onnx.__version__,
        "onnxscript": getattr(onnxscript, "__version__", "unknown"),
        **cmf.versions(),
    }


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
    """Manifest entry of ``directory/file`` with the I/O of ``graph`` at H x W."""
    spec = io_spec(graph, height, width, seq_length)
    io = {"inputs": spec.inputs, "outputs": spec.outputs, "dtype": spec.dtype}
    return cmf.graph_entry(directory, file, io, opset, precision, exporter)


def provenance(
    arch: str, random_init: bool, exporter: str, checkpoint: str | Path | None = None, ckpt: dict | None = None
) -> Provenance:
    cfg = (ckpt or {}).get("config", {})
    data_dirs = [d for d in (cfg.get("data_dir"), *cfg.get("extra_data_dirs", ())) if d]
    return Provenance(
        architecture=arch,
        random_init=random_init,
        export_date=cmf.utc_now(),
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

"""torch -> ONNX for one graph, plus the structural checks every exported file must pass.

Exporter: ``torch.onnx.export(dynamo=True)`` (torch.export + onnxscript), with
``dynamic_shapes`` marking axis 0 of every input as the batch ``B``. If dynamo
fails for a module, the legacy TorchScript exporter (``dynamo=False`` +
``dynamic_axes``) is tried and the manifest records which one made the file.

Opset 18: the dynamo exporter's torchlib is written at opset 18, so no version
conversion happens; ONNX GridSample has existed since opset 16 and keeps its
old mode spelling (``bilinear``) until opset 19; opset 20 renamed it to
``linear`` and onnxruntime rejects the wrong spelling for the opset at load
time (onnx_notes.md section 3). :func:`check_graph` asserts the spelling.

Batch: ``torch.export`` 0/1-specialises a dimension whose example size is 1
(and GeoNet's batched matmuls add ``B == 1`` guards), so an example batch of 1
would silently give a static graph. :func:`export_graph` therefore traces with
the example repeated to batch 2 and then asserts that axis 0 of every input
and output is symbolic.

Spatial axes: a wrapper whose class sets ``dynamic_spatial = True`` (the rigid-flow
op) is traced with H and W symbolic too, so the pixel grid it builds from its input
shapes (``training.geometry.pixel_grid``) stays Range/Expand nodes; with static H, W
the exporter's optimizer folds the grid into three H x W float initializers (0.64 MB
at 128x416). The file still declares the fixed H x W of its manifest entry
(:func:`_pin_dims`); only the computation inside is shape-generic.
"""

from __future__ import annotations

import contextlib
import io
import logging
import math
import tempfile
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import onnx
import torch

from export.wrappers import IOSpec
from geonet_infer.io.protobuf import encode_varint
from geonet_infer.models.manifest import BATCH_AXIS

OPSET = 18
TRACE_BATCH = 2
EXPORTER_DYNAMO = f"torch {torch.__version__} torch.onnx.export(dynamo=True, opset {OPSET})"
EXPORTER_TORCHSCRIPT = f"torch {torch.__version__} torch.onnx.export(dynamo=False, opset {OPSET})"
# GridSample "mode" values valid at each opset (onnx_notes.md section 3).
GRIDSAMPLE_MODES_OLD = {b"bilinear", b"nearest", b"bicubic"}  # opset 16..19
GRIDSAMPLE_MODES_NEW = {b"linear", b"nearest", b"cubic"}  # opset >= 20
FORBIDDEN_OPS = {"Inverse"}  # com.microsoft::Inverse is not standard ONNX


class ExportCheckError(RuntimeError):
    """An exported graph failed a structural check (names, batch axis, ops, checker)."""


@dataclass(frozen=True)
class ExportedGraph:
    path: Path
    opset: int
    exporter: str
    seconds: float


def _with_trace_batch(example: tuple[torch.Tensor, ...]) -> tuple[torch.Tensor, ...]:
    """Repeat a batch-1 example to TRACE_BATCH rows (see the module docstring)."""
    out = []
    for t in example:
        if t.shape[0] < TRACE_BATCH:
            reps = -(-TRACE_BATCH // t.shape[0])
            t = t.repeat(reps, *([1] * (t.dim() - 1)))[:TRACE_BATCH]
        out.append(t.contiguous())
    return tuple(out)


@contextlib.contextmanager
def _quiet():
    """Silence the exporters' progress prints and expected warnings (torchvision ops, deprecations)."""
    loggers = [logging.getLogger(n) for n in ("torch.onnx", "torch.export", "torch._export", "onnxscript")]
    levels = [lg.level for lg in loggers]
    for lg in loggers:
        lg.setLevel(logging.ERROR)
    try:
        with warnings.catch_warnings(), contextlib.redirect_stdout(io.StringIO()):
            warnings.simplefilter("ignore")
            yield
    finally:
        for lg, level in zip(loggers, levels):
            lg.setLevel(level)


SPATIAL_AXES = {2: "H", 3: "W"}  # axes of a 4-D (B, C, H, W) tensor that ``dynamic_spatial`` frees


def _dynamic_spatial(module) -> bool:
    """Whether ``module`` asks to be traced with symbolic H and W (see the module docstring)."""
    return bool(getattr(module, "dynamic_spatial", False))


def _dynamo_export(module, example, spec: IOSpec, opset: int) -> onnx.ModelProto:
    batch = torch.export.Dim(BATCH_AXIS, min=1)
    input_names = [n for n, _ in spec.inputs]
    dynamic_shapes = {name: {0: batch} for name in input_names}
    if _dynamic_spatial(module):
        # min=2: a 1-pixel axis would be 0/1-specialised, and flow_warp divides by W - 1.
        spatial = {axis: torch.export.Dim(name, min=2) for axis, name in SPATIAL_AXES.items()}
        for name, shape in spec.inputs:
            if len(shape) == 4:
                dynamic_shapes[name].update(spatial)
    program = torch.onnx.export(
        module,
        example,
        dynamo=True,
        opset_version=opset,
        verbose=False,
        input_names=input_names,
        output_names=[n for n, _ in spec.outputs],
        dynamic_shapes=dynamic_shapes,
        optimize=True,
        report=False,
        verify=False,
    )
    return program.model_proto


def _torchscript_export(module, example, spec: IOSpec, opset: int) -> onnx.ModelProto:
    buffer = io.BytesIO()
    dynamic_axes = {n: {0: BATCH_AXIS} for n, _ in [*spec.inputs, *spec.outputs]}
    if _dynamic_spatial(module):
        for name, shape in [*spec.inputs, *spec.outputs]:
            if len(shape) == 4:
                dynamic_axes[name].update(SPATIAL_AXES)
    torch.onnx.export(
        module,
        example,
        buffer,
        dynamo=False,
        opset_version=opset,
        input_names=[n for n, _ in spec.inputs],
        output_names=[n for n, _ in spec.outputs],
        dynamic_axes=dynamic_axes,
        do_constant_folding=True,
    )
    return onnx.load_from_string(buffer.getvalue())


def _name_batch_axis(model: onnx.ModelProto) -> None:
    """Rename the symbolic axis 0 of the graph inputs/outputs to "B" (everywhere it appears)."""
    old = {
        vi.type.tensor_type.shape.dim[0].dim_param
        for vi in [*model.graph.input, *model.graph.output]
        if vi.type.tensor_type.shape.dim and vi.type.tensor_type.shape.dim[0].dim_param
    }
    for vi in [*model.graph.input, *model.graph.output, *model.graph.value_info]:
        for dim in vi.type.tensor_type.shape.dim:
            if dim.dim_param in old:
                dim.dim_param = BATCH_AXIS


def _pin_dims(model: onnx.ModelProto, spec: IOSpec) -> None:
    """Declare the static dims of ``spec`` on a graph traced with symbolic ones.

    Each symbolic dim of a graph input/output that ``spec`` fixes (H and W of a
    ``dynamic_spatial`` trace) becomes that value, in the inputs, outputs and
    ``value_info``; a product of them (``H*W``) becomes the product. The file then
    shows the fixed I/O the manifest records (:func:`check_graph`, the runtime's
    engines), while the nodes still compute the pixel grid from the input shapes.
    """
    values: dict[str, int] = {}
    for want, have in ((spec.inputs, model.graph.input), (spec.outputs, model.graph.output)):
        for (_, shape), vi in zip(want, have):
            for size, dim in zip(shape, vi.type.tensor_type.shape.dim):
                if isinstance(size, int) and dim.dim_param:
                    if values.setdefault(dim.dim_param, size) != size:
                        raise ExportCheckError(f"axis {dim.dim_param!r} is both {values[dim.dim_param]} and {size}")
    for vi in [*model.graph.input, *model.graph.output, *model.graph.value_info]:
        for dim in vi.type.tensor_type.shape.dim:
            factors = dim.dim_param.replace(" ", "").split("*") if dim.dim_param else []
            if factors and all(f in values or f.isdigit() for f in factors):
                dim.dim_value = math.prod(values[f] if f in values else int(f) for f in factors)


def _strip_debug_info(model: onnx.ModelProto) -> None:
    """Drop per-node stack traces and source paths the exporter stores (they leak local paths)."""
    for node in model.graph.node:
        del node.metadata_props[:]
        node.doc_string = ""
    del model.metadata_props[:]
    model.graph.doc_string = ""
    model.doc_string = ""


def _dedupe_initializers(model: onnx.ModelProto) -> int:
    """Merge initializers with identical dtype, shape and bytes; returns how many were dropped.

    The dynamo exporter folds each constant subexpression into its own initializer, so
    one tensor can be stored several times (the rigid-flow graph once stored the same
    128x416 pixel grids three times; it now computes them, see ``dynamic_spatial``).
    ORT would merge duplicates at load; this keeps the files small.
    """
    first: dict[tuple, str] = {}
    rename: dict[str, str] = {}
    keep = []
    for init in model.graph.initializer:
        key = (init.data_type, tuple(init.dims), init.raw_data) if init.raw_data else None
        if key is not None and key in first:
            rename[init.name] = first[key]
        else:
            if key is not None:
                first[key] = init.name
            keep.append(init)
    if not rename:
        return 0
    del model.graph.initializer[:]
    model.graph.initializer.extend(keep)
    for node in _all_nodes(model.graph):
        for i, name in enumerate(node.input):
            if name in rename:
                node.input[i] = rename[name]
    graph_outputs = {o.name for o in model.graph.output}
    if graph_outputs & set(rename):
        raise ExportCheckError("a deduplicated initializer is a graph output")
    return len(rename)


def set_metadata(model: onnx.ModelProto, metadata: dict[str, str]) -> None:
    """Replace the model's ``metadata_props`` by ``metadata`` (sorted, string values)."""
    del model.metadata_props[:]
    for key in sorted(metadata):
        entry = model.metadata_props.add()
        entry.key, entry.value = key, str(metadata[key])


def export_graph(
    module: torch.nn.Module,
    example: tuple[torch.Tensor, ...],
    spec: IOSpec,
    path: str | Path,
    metadata: dict[str, str] | None = None,
    opset: int = OPSET,
    producer_version: str | None = None,
) -> ExportedGraph:
    """Export ``module`` (eval mode) to ``path`` with the I/O of ``spec`` and a dynamic batch axis.

    The example may have any batch size (batch 1 is repeated to 2 for tracing).
    The file is written in one piece (no external data) and then checked with
    :func:`check_graph`; an :class:`ExportCheckError` means it is unusable.
    """
    path = Path(path)
    module = module.eval()
    example = _with_trace_batch(example)
    started = time.perf_counter()
    with _quiet(), torch.no_grad():
        try:
            model = _dynamo_export(module, example, spec, opset)
            exporter = EXPORTER_DYNAMO
        except Exception as dynamo_error:  # noqa: BLE001 - fall back, then re-raise both
            try:
                model = _torchscript_export(module, example, spec, opset)
                exporter = EXPORTER_TORCHSCRIPT
            except Exception as legacy_error:
                raise ExportCheckError(
                    f"both exporters failed for {path.name}: dynamo: {dynamo_error!r}; torchscript: {legacy_error!r}"
                ) from legacy_error
    _name_batch_axis(model)
    if _dynamic_spatial(module):
        _pin_dims(model, spec)
    _strip_debug_info(model)
    _dedupe_initializers(model)
    if metadata:
        set_metadata(model, metadata)
    model.producer_name = "geonet export"
    model.producer_version = producer_version or torch.__version__
    path.parent.mkdir(parents=True, exist_ok=True)
    save_streamed(model, path)
    del model  # the checks reload the file: two copies of a 220 MB graph at once are not needed
    check_graph(path, spec, opset)
    return ExportedGraph(path, opset, exporter, time.perf_counter() - started)


def _length_delimited(field: int, payload: bytes) -> bytes:
    return encode_varint(field << 3 | 2) + encode_varint(len(payload)) + payload


def _copy_fields(src, dst, skip: str) -> None:
    for fd, value in src.ListFields():
        if fd.name == skip:
            continue
        if hasattr(value, "extend"):  # repeated
            getattr(dst, fd.name).extend(value)
        elif hasattr(value, "CopyFrom"):  # a message
            getattr(dst, fd.name).CopyFrom(value)
        else:
            setattr(dst, fd.name, value)


def save_streamed(model: onnx.ModelProto, path: str | Path) -> None:
    """``onnx.save_model`` (one file, no external data) without its two whole-model buffers.

    Serialising a 220 MB model at once holds it three times (the message, protobuf's buffer,
    the bytes): the peak of a resnet50 export. Here the model without its initializers is written
    first, then each initializer in a ``graph`` record of its own; protobuf merges repeated records
    of a message field, so every reader (onnx, onnxruntime) parses the same model.
    """
    head = onnx.ModelProto()
    _copy_fields(model, head, skip="graph")
    _copy_fields(model.graph, head.graph, skip="initializer")
    graph_field = onnx.ModelProto.DESCRIPTOR.fields_by_name["graph"].number
    init_field = onnx.GraphProto.DESCRIPTOR.fields_by_name["initializer"].number
    try:
        with open(path, "wb") as f:
            f.write(head.SerializeToString())
            for init in model.graph.initializer:
                f.write(_length_delimited(graph_field, _length_delimited(init_field, init.SerializeToString())))
    except OSError as exc:  # a full disk says which file it stopped
        raise OSError(exc.errno, exc.strerror, str(path)) from None


def _dims(value_info) -> list:
    return [
        d.dim_param if d.dim_param else (d.dim_value if d.HasField("dim_value") else "?")
        for d in value_info.type.tensor_type.shape.dim
    ]


def check_graph(
    path: str | Path, spec: IOSpec | None = None, opset: int | None = None, strict_shapes: bool = True
) -> onnx.ModelProto:
    """Structural checks of an exported file; raises ExportCheckError on the first failure.

    * ``onnx.checker.check_model(full_check=True)`` and strict shape inference;
    * (with ``spec``) input/output names, ranks, static dims and a symbolic "B" axis 0 match;
    * no ``Inverse`` op; GridSample ``mode`` spelled as the model's opset requires.
    """
    path = Path(path)
    try:
        onnx.checker.check_model(str(path), full_check=True)
    except Exception as exc:
        raise ExportCheckError(f"{path.name}: onnx.checker failed: {exc}") from exc
    if strict_shapes:
        # On the file, in C++: inferring on a loaded model copies it through Python four times
        # (+0.9 GB for a resnet50 graph, the peak of a whole export).
        with tempfile.TemporaryDirectory() as tmp:
            try:
                onnx.shape_inference.infer_shapes_path(
                    str(path), str(Path(tmp) / "inferred.onnx"), check_type=True, strict_mode=True, data_prop=True
                )
            except Exception as exc:
                raise ExportCheckError(f"{path.name}: strict shape inference failed: {exc}") from exc
    model = onnx.load(str(path))
    model_opset = next((o.version for o in model.opset_import if o.domain in ("", "ai.onnx")), None)
    if opset is not None and model_opset != opset:
        raise ExportCheckError(f"{path.name}: opset {model_opset}, expected {opset}")
    if spec is not None:
        for kind, want, have in (
            ("input", spec.inputs, model.graph.input),
            ("output", spec.outputs, model.graph.output),
        ):
            got = [(vi.name, _dims(vi)) for vi in have]
            expected = [(n, list(s)) for n, s in want]
            if got != expected:
                raise ExportCheckError(f"{path.name}: {kind}s {got}, expected {expected}")
    for node in _all_nodes(model.graph):
        if node.op_type in FORBIDDEN_OPS:
            raise ExportCheckError(f"{path.name}: contains a {node.domain or 'ai.onnx'}::{node.op_type} node")
        if node.op_type == "GridSample":
            mode = next(
                (a.s for a in node.attribute if a.name == "mode"), b"linear" if model_opset >= 20 else b"bilinear"
            )
            allowed = GRIDSAMPLE_MODES_NEW if model_opset >= 20 else GRIDSAMPLE_MODES_OLD
            if mode not in allowed:
                raise ExportCheckError(f"{path.name}: GridSample mode {mode!r} is invalid at opset {model_opset}")
    return model


def _all_nodes(graph: onnx.GraphProto):
    for node in graph.node:
        yield node
        for attr in node.attribute:
            if attr.type == onnx.AttributeProto.GRAPH:
                yield from _all_nodes(attr.g)
            for sub in attr.graphs:
                yield from _all_nodes(sub)


def op_types(path: str | Path) -> set[str]:
    """Every op type used in a graph (subgraphs included)."""
    return {n.op_type for n in _all_nodes(onnx.load(str(path)).graph)}

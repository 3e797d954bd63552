"""The manifest's schema: its constants, limits and dataclasses (:class:`Manifest` and its parts). Loading and
checking a model directory: :mod:`geonet_infer.models.manifest`."""

from __future__ import annotations

import hashlib
import math
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

from geonet_infer import conventions
from geonet_infer.conventions import MANIFEST_NAME  # noqa: F401  (re-exported: the schema's file name)
from geonet_infer.errors import ModelError

MANIFEST_FORMAT = "geonet-onnx-models"
SCHEMA_VERSION = conventions.SCHEMA_VERSION
PRECISIONS = ("fp32", "int8")
# --backend auto / --precision auto: chosen per graph at load by timing (geonet_infer.engines.pick_fastest)
AUTO = "auto"
PRECISION_CHOICES = (*PRECISIONS, AUTO)  # what load(precision=) and --precision accept
BATCH_AXIS = "B"  # symbolic batch dimension in shapes
REEXPORT_HINT = "re-export the model directory with `python -m export`"
# Limits on what a manifest may ask for: frames are resized to height x width and snippets of
# seq_length frames are stacked before any graph runs, so an absurd number here would be an
# absurd allocation at the first frame. Export writes sizes that are multiples of 8 (DepthNet and
# ResFlowNet need them, export/build.py) and odd snippets (the target is the middle frame); 2048
# is 5x KITTI's 416-pixel graph width, 32 the smallest size the tests train and export at.
SIZE_MULTIPLE = 8
MIN_SIDE, MAX_SIDE = 32, 2048
MIN_SEQ_LENGTH, MAX_SEQ_LENGTH = 3, 9
MAX_CONVENTION_MAGNITUDE = 1e4  # every number of the conventions (the largest is a reference size)
MIN_NORM_SCALE = 1e-3  # image_norm.scale: a zero scale feeds the nets a constant image
REAL_VIDEO_HINT = (
    "for real video, convert the released GeoNet checkpoints with `geonet-infer convert CHECKPOINT --name NAME`, "
    "then --model NAME (docs/official_models.md)"
)


def file_sha256(path: str | Path, chunk: int = 1 << 20) -> str:
    """Hex sha256 of a file, read in 1 MiB chunks."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


def _from_known_fields(cls, d: dict):
    """Build a dataclass from a dict, ignoring keys a newer writer may have added."""
    known = {f.name for f in fields(cls)}
    return cls(**{k: v for k, v in d.items() if k in known})


@dataclass(frozen=True)
class TensorSpec:
    """One graph input or output. ``shape`` holds ints and ``"B"`` for the batch axis."""

    name: str
    shape: tuple
    dtype: str = "float32"

    @classmethod
    def from_dict(cls, d: dict) -> TensorSpec:
        return cls(name=str(d["name"]), shape=tuple(d["shape"]), dtype=str(d["dtype"]))


@dataclass(frozen=True)
class GraphEntry:
    """One ONNX file of a graph set."""

    file: str  # POSIX path relative to the model directory
    sha256: str
    opset: int
    precision: str  # precision of this file ("fp32" also for rigidflow in the int8 set)
    inputs: tuple[TensorSpec, ...]
    outputs: tuple[TensorSpec, ...]
    exporter: str = ""  # how the file was made (torch.onnx dynamo, ORT quantize_static, ...)

    @classmethod
    def from_dict(cls, d: dict) -> GraphEntry:
        return cls(
            file=str(d["file"]),
            sha256=str(d["sha256"]),
            opset=int(d["opset"]),
            precision=str(d["precision"]),
            inputs=tuple(TensorSpec.from_dict(t) for t in d["inputs"]),
            outputs=tuple(TensorSpec.from_dict(t) for t in d["outputs"]),
            exporter=str(d.get("exporter", "")),
        )

    @property
    def input_names(self) -> tuple[str, ...]:
        return tuple(t.name for t in self.inputs)

    @property
    def output_names(self) -> tuple[str, ...]:
        return tuple(t.name for t in self.outputs)


@dataclass(frozen=True)
class Provenance:
    """Where the graphs came from."""

    architecture: str
    random_init: bool
    export_date: str  # ISO 8601, UTC
    git_commit: str | None = None
    checkpoint: str | None = None  # path as given on the command line
    checkpoint_sha256: str | None = None
    checkpoint_stage: str | None = None
    checkpoint_step: int | None = None
    training_command: str | None = None
    data_dir: str | None = None  # prepared folder(s) trained on, joined with " + "
    exporter: str = ""
    versions: dict = field(default_factory=dict)  # torch, onnx, onnxruntime, onnxscript
    sources: list = field(default_factory=list)  # --from-tf: each TF checkpoint, its nets and files' sha256

    @classmethod
    def from_dict(cls, d: dict) -> Provenance:
        return _from_known_fields(cls, d)


@dataclass(frozen=True)
class Quantization:
    """How the int8 set was made and what it costs in accuracy."""

    method: str
    activation_type: str
    weight_type: str
    per_channel: bool
    reduce_range: bool
    calibrate_method: str
    calibration_data: str
    calibration_samples: dict  # graph -> number of calibration inputs
    calibration_intrinsics: str  # where the K for the resflownet calibration inputs came from
    fp32_graphs: tuple[str, ...]  # graphs of the int8 set that stay fp32
    accuracy_delta: dict | None  # {"depth_abs_rel": {"fp32", "int8", "delta"}, "flow_epe_noc": ...}
    accuracy_delta_reason: str | None = None  # why accuracy_delta is null (or a note)
    graph_notes: dict = field(default_factory=dict)  # graph -> what stayed fp32 / was rescaled in it
    op_types: tuple[str, ...] = ()  # operator types quantised (export --int8-ops); () = every type ORT quantises
    # graph -> which x86 INT8 kernels compute it exactly (convert/int8_arith.py int8_kernels); {} = not recorded
    int8_kernels: dict = field(default_factory=dict)

    @classmethod
    def from_dict(cls, d: dict) -> Quantization:
        d = dict(d)
        d["fp32_graphs"] = tuple(d.get("fp32_graphs", ()))
        d["op_types"] = tuple(d.get("op_types", ()))
        return _from_known_fields(cls, d)


@dataclass(frozen=True)
class Score:
    """One measured number of a model next to its baseline on the same data (written by the model card)."""

    task: str  # depth, flow, pose
    metric: str  # as the card labels it, e.g. "AbsRel"
    data: str  # what it was measured on
    value: float  # the model's FP32 number
    baseline: str  # e.g. "constant depth"
    baseline_value: float
    lower_is_better: bool = True

    @property
    def verdict(self) -> str:
        """ "better", "worse" or "no better" than the baseline."""
        ahead = self.baseline_value - self.value if self.lower_is_better else self.value - self.baseline_value
        return "better" if ahead > 0 else "worse" if ahead < 0 else "no better"

    @classmethod
    def from_dict(cls, d: dict) -> Score:
        d = dict(d)
        for key in ("value", "baseline_value"):
            d[key] = float(d[key])
            if not math.isfinite(d[key]):
                raise ValueError(f"model_card score {key} is {d[key]}")
        return _from_known_fields(cls, d)


@dataclass(frozen=True)
class ModelCard:
    """What the model was trained on and its measured scores, copied from its model card
    (``python -m benchmarks.model_card``); a model directory without one has no measured scores."""

    trained_on: str  # one line
    synthetic_only: bool  # trained on synthetic scenes only: predict/batch say so on real video
    measured_in: str  # where the measurement is written up (docs/models.md)
    generated_utc: str
    real: tuple[Score, ...] = ()
    synthetic: tuple[Score, ...] = ()

    def notice(self) -> str | None:
        """One line for users of a model that may fail them on real video (trained on synthetic
        scenes only, or no better than its baseline on real data): its real-data score and where a
        model for real video comes from; None for any other model."""
        s = self.real[0] if self.real else None
        if not self.synthetic_only and (s is None or s.verdict == "better"):
            return None
        if s is not None:
            real = (
                f"on real video it is {s.verdict} than the {s.baseline} baseline: {s.task} {s.metric} "
                f"{s.value:.3g} vs {s.baseline_value:.3g} on {s.data}, see {self.measured_in}"
            )
        else:
            real = "its real-data scores are not measured"
        trained = "trained on synthetic scenes only: " if self.synthetic_only else ""
        return f"{trained}{real}; {REAL_VIDEO_HINT}"

    @classmethod
    def from_dict(cls, d: dict) -> ModelCard:
        d = dict(d)
        d["synthetic_only"] = bool(d["synthetic_only"])
        for key in ("real", "synthetic"):
            d[key] = tuple(Score.from_dict(s) for s in d.get(key) or ())
        return _from_known_fields(cls, d)


@dataclass(frozen=True)
class Manifest:
    """Everything a consumer needs to run the graphs of one model directory."""

    schema_version: int
    height: int
    width: int
    seq_length: int
    arch: str
    random_init: bool
    precisions: tuple[str, ...]
    graphs: dict  # precision -> {graph name -> GraphEntry}
    conventions: dict  # geonet_infer.conventions.as_dict() at export time, and photometric_alpha (optional)
    provenance: Provenance
    metrics: dict  # the checkpoint's validation metrics ({} for random init)
    quantization: Quantization | None = None
    model_card: ModelCard | None = None  # optional: older manifests and fresh exports have none
    format: str = MANIFEST_FORMAT
    root: Path | None = field(default=None, compare=False, repr=False)  # directory it was loaded from

    # ------------------------------------------------------------------ access
    @property
    def num_source(self) -> int:
        return self.seq_length - 1

    @property
    def photometric_alpha(self) -> float | None:
        """α of the photometric error ``rigidflow.onnx`` computes (``α·DSSIM + (1−α)·L1``, baked in at
        export); None for a manifest written before export recorded it."""
        alpha = self.conventions.get(conventions.PHOTOMETRIC_ALPHA)
        return None if alpha is None else float(alpha)

    def graph_names(self, precision: str = "fp32") -> tuple[str, ...]:
        return tuple(self._set(precision))

    def graph(self, name: str, precision: str = "fp32") -> GraphEntry:
        graphs = self._set(precision)
        if name not in graphs:
            where = self.root / MANIFEST_NAME if self.root else None
            hint = (
                "resflownet needs a stage 'flow' checkpoint at export time"
                if name == "resflownet"
                else f"graphs present: {', '.join(graphs)}"
            )
            raise ModelError(where, f"no '{name}' graph in the {precision} set", hint)
        return graphs[name]

    def path(self, name: str, precision: str = "fp32") -> Path:
        """Absolute path of a graph file (needs a manifest loaded from a directory)."""
        if self.root is None:
            raise ValueError("manifest has no root directory; load it with load_manifest()")
        return self.root / self.graph(name, precision).file

    def files_mib(self, precision: str = "fp32") -> float:
        """Size of the graph files of one precision set on disk (a file shared by two graphs counts once)."""
        sets = [p for p in self.graphs if p in PRECISIONS] if precision == AUTO else [precision]  # auto loads all
        files = {self.path(name, p) for p in sets for name in self._set(p)}
        return sum(f.stat().st_size for f in files) / 2**20

    def _set(self, precision: str) -> dict:
        if precision == AUTO and self.graphs:  # any graph of any set: each is chosen at load
            merged: dict = {}
            for p in sorted(self.graphs, key=lambda p: PRECISIONS.index(p) if p in PRECISIONS else len(PRECISIONS)):
                for name, entry in self.graphs[p].items():
                    merged.setdefault(name, entry)
            return merged
        if precision not in self.graphs:
            where = self.root / MANIFEST_NAME if self.root else None
            raise ModelError(
                where,
                f"no {precision} graphs in this model directory",
                f"precisions present: {', '.join(self.graphs)}; export with --precision fp32,int8",
            )
        return self.graphs[precision]

    # -------------------------------------------------------------- (de)serialise
    def to_dict(self) -> dict:
        d = asdict(self)
        d.pop("root")
        if d["model_card"] is None:  # written by the model card, not by export
            d.pop("model_card")
        # Put the identifying keys first for readers of the JSON.
        return {"format": d.pop("format"), "schema_version": d.pop("schema_version"), **d}

    @classmethod
    def from_dict(cls, d: dict, root: Path | None = None) -> Manifest:
        quant, card = d.get("quantization"), d.get("model_card")
        return cls(
            schema_version=int(d["schema_version"]),
            height=int(d["height"]),
            width=int(d["width"]),
            seq_length=int(d["seq_length"]),
            arch=str(d["arch"]),
            random_init=bool(d["random_init"]),
            precisions=tuple(d["precisions"]),
            graphs={p: {n: GraphEntry.from_dict(g) for n, g in gs.items()} for p, gs in d["graphs"].items()},
            conventions=dict(d["conventions"]),
            provenance=Provenance.from_dict(d["provenance"]),
            metrics=dict(d.get("metrics") or {}),
            quantization=Quantization.from_dict(quant) if quant else None,
            model_card=ModelCard.from_dict(card) if card else None,
            format=str(d.get("format", "")),
            root=root,
        )


def model_notice(manifest: Manifest) -> str | None:
    """The one-line notice ``predict`` and ``batch`` print and record for a model trained on synthetic
    scenes only (from its ``model_card``); None for any other model."""
    return manifest.model_card.notice() if manifest.model_card else None

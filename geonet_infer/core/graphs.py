"""One engine per graph of a model (:class:`GraphSet`), the rigid-flow op in numpy or as its graph."""

from __future__ import annotations

import sys
import warnings
from pathlib import Path

import numpy as np

from geonet_infer import conventions
from geonet_infer.core.int8_safety import int8_unsafe_reason
from geonet_infer.core.rigid import RigidFlowOp
from geonet_infer.core.snippets import resflow_channels
from geonet_infer.core.spec import GRAPH_IO
from geonet_infer.engines import AUTO, ENGINES, Engine, make_engine, pick_fastest
from geonet_infer.errors import InputError, ModelError
from geonet_infer.models.manifest import MANIFEST_NAME, PRECISIONS, Manifest, check_graph_io
from geonet_infer.models.onnx_graph import channels_read

RIGID_OPS = ("graph", "numpy")  # how the rigid-flow op runs: geonet_infer.core.rigid, or rigidflow.onnx


class GraphSet:
    """One engine per graph of a model directory (sessions made once).

    ``precision``: "fp32", "int8", or "auto": per graph, the fastest of the model's precisions that is
    exact on this CPU (:func:`geonet_infer.core.int8_safety.int8_unsafe_reason`), timed at load; FP32 is
    always a candidate, so auto is never slower than FP32 beyond timing noise.
    ``backend``: a name of :data:`geonet_infer.engines.ENGINES`, or "auto" (the faster engine per
    graph, timed here). Every graph's inputs and outputs are checked against the manifest.
    ``rigid_op``: "graph" runs ``rigidflow.onnx`` on ``backend`` like the other graphs; "numpy" runs
    the weightless op with :class:`geonet_infer.core.rigid.RigidFlowOp` (about 1.5x as fast, within
    2e-4 px of the graph) where the manifest's sampler is the one it implements.
    ``threads`` per graph call; ``streams``: graph calls made at once from as many Python threads
    (throughput mode, :class:`geonet_infer.engines.Engine`).
    """

    def __init__(
        self, manifest: Manifest, precision: str, backend: str, threads: int, rigid_op: str = "graph", streams: int = 1
    ):
        if rigid_op not in RIGID_OPS:
            raise InputError(None, f"unknown rigid_op {rigid_op!r}", f"choose one of {', '.join(RIGID_OPS)}")
        self.manifest = manifest
        self.precision = precision
        self.backend_choice: dict[str, dict] = {}  # an "auto": per graph, the timings behind the choice
        self.runs: dict[str, dict] = {}  # per graph: engine, precision and why (summary.json, bench)
        self._engines: dict[str, Engine | RigidFlowOp] = {}
        for name in manifest.graph_names(precision):
            files = self._files(name)
            if name == "rigidflow" and rigid_op == "numpy" and RigidFlowOp.supports(manifest.conventions):
                path = next(iter(files.values()))
                graph = make_engine(path, "onnxruntime", 1)  # read once: its declared io is the op's
                check_graph_io(manifest.graph(name, next(iter(files))), path, *graph.io())
                alpha = manifest.photometric_alpha
                self._engines[name] = RigidFlowOp(
                    conventions.UNRECORDED_PHOTOMETRIC_ALPHA if alpha is None else alpha, graph.io()
                )
                self.runs[name] = {"engine": "numpy", "precision": "fp32", "why": "rigid_op numpy (geometry)"}
                continue
            engines = list(ENGINES) if backend == AUTO else [backend]  # pick_fastest skips what is not installed
            unsafe = self._int8_unsafe(name, files, engines, warn=backend != AUTO and precision != AUTO)
            if backend == AUTO or len(files) > 1:
                engine, self.backend_choice[name] = pick_fastest(
                    files if precision == AUTO else files[precision], threads, unsafe, engines, streams
                )
                chosen_precision = self.backend_choice[name].get("precision", precision)
                why = "auto: fastest " + ("exact engine and precision" if len(files) > 1 else "installed engine")
                why += " at load"
            else:
                (chosen_precision, path), *_ = files.items()
                engine = make_engine(path, backend, threads, streams)
                why = f"backend {backend}"
                if precision == AUTO:
                    why += f"; precision auto: {chosen_precision} is the model's only {name}"
            self._engines[name] = engine
            check_graph_io(manifest.graph(name, chosen_precision), files[chosen_precision], *engine.io())
            for label, reason in unsafe.items():  # an engine named with --precision int8 runs anyway (warned)
                why += f"; {'' if label == engine.name else 'skipped '}{label}: {reason}"
            self.runs[name] = {"engine": engine.name, "precision": self._runs_as(name, chosen_precision), "why": why}
        self._skip_unread_rigid_outputs()

    def _skip_unread_rigid_outputs(self) -> None:
        """The rigid-flow op computes only what ResFlowNet reads, and the rigid flow (the flow and the
        output check use it): a direct ResFlowNet (``training.train --direct-flow``) reads the frames and
        the rigid flow of its input, not the warped frame or the photometric error, which are most of
        the op's time. The channels a graph reads come from its Slice nodes
        (:func:`geonet_infer.models.onnx_graph.channels_read`); a graph that reads its input any other way
        reads all of it. Unread parts enter ResFlowNet as zeros (:func:`~geonet_infer.core.snippets.resflow_input`)."""
        if "rigidflow" not in self._engines or "resflownet" not in self._engines:
            return
        read: set[int] = set()
        for path in self._files("resflownet").values():
            try:
                channels = channels_read(path.read_bytes(), GRAPH_IO["resflownet"][0][0])
            except ValueError:  # protobuf this reader does not follow: the graph keeps all it is given
                channels = None
            if channels is None:
                return
            read |= channels
        engine = self._engines["rigidflow"]
        unread = [
            name
            for name, channels in resflow_channels().items()
            if name in engine.output_names and name != "rigid_flow" and not read.intersection(channels)
        ]
        if unread:
            self._engines["rigidflow"] = engine.only([name for name in engine.output_names if name not in unread])
            self.runs["rigidflow"]["why"] += f"; {' and '.join(unread)} not computed: resflownet does not read them"

    def _files(self, name: str) -> dict[str, Path]:
        """{precision: file} of graph ``name``: one precision, or under "auto" each of the model's whose
        graph differs from FP32's (an INT8 set keeps some graphs in FP32: the same file)."""
        if self.precision != AUTO:
            return {self.precision: self.manifest.path(name, self.precision)}
        files: dict[str, Path] = {}
        for p in PRECISIONS:
            if p in self.manifest.graphs and name in self.manifest.graphs[p]:
                path = self.manifest.path(name, p)
                if path not in files.values():
                    files[p] = path
        return files

    def _runs_as(self, name: str, precision: str) -> str:
        """The arithmetic graph ``name`` of the ``precision`` set runs in (an INT8 set's FP32 graphs)."""
        q = self.manifest.quantization
        return "fp32" if precision == "fp32" or (q and name in q.fp32_graphs) else precision

    def _int8_unsafe(self, name: str, files: dict[str, Path], engines: list[str], warn: bool) -> dict[str, str]:
        """{candidate label: why that engine's INT8 of graph ``name`` is not exact on this CPU}
        (geonet_infer.core.int8_safety); labels as :func:`pick_fastest` makes them. Auto skips those
        candidates (onnxruntime is always exact: its sessions set the remedy); an engine and INT8
        named explicitly run the graph anyway, after one line on stderr."""
        q = self.manifest.quantization
        if "int8" not in files or q is None or self._runs_as(name, "int8") != "int8":
            return {}
        installed = [e for e in engines if ENGINES[e].available()]
        unsafe = {e: r for e in installed if (r := int8_unsafe_reason(e, q.int8_kernels.get(name)))}
        if warn:
            for reason in unsafe.values():
                print(f"geonet-infer: warning: {name} INT8 may be inexact: {reason}", file=sys.stderr)
        return {e if len(files) == 1 else f"{e} int8": r for e, r in unsafe.items()}

    @property
    def names(self) -> tuple[str, ...]:
        """The graphs present, in manifest order."""
        return tuple(self._engines)

    @property
    def engines(self) -> dict[str, str]:
        """Graph name -> the engine running it ("onnxruntime", "openvino", "numpy" for the rigid op).

        Names (issue 42): the *backend* is what a user asks for (``--backend onnxruntime|openvino|auto``),
        the *engine* what runs a graph, a *runner* what runs batch's workers (local, ray)."""
        return {name: engine.name for name, engine in self._engines.items()}

    @property
    def backends(self) -> dict[str, str]:
        """Deprecated name of :attr:`engines` (it names engines, not the backend asked for); one release."""
        warnings.warn("GraphSet.backends is now GraphSet.engines", DeprecationWarning, stacklevel=2)
        return self.engines

    def __contains__(self, name: object) -> bool:
        return name in self._engines

    def engine(self, name: str) -> Engine | RigidFlowOp:
        """The engine of graph ``name`` (``run(feeds) -> {output: array}``); ModelError when absent."""
        if name not in self._engines:
            raise ModelError(
                Path(self.manifest.root or ".") / MANIFEST_NAME,
                f"no '{name}' graph in the {self.precision} set",
                f"graphs present: {', '.join(self._engines)}",
            )
        return self._engines[name]

    def run(self, name: str, **feeds: np.ndarray) -> dict[str, np.ndarray]:
        """Run graph ``name`` on float32 feeds keyed by its input names."""
        return self._engines[name].run({k: np.ascontiguousarray(v, dtype=np.float32) for k, v in feeds.items()})

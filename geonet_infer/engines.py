"""Inference engines behind the Predictor: one ONNX file -> ``run(feeds) -> {output name: array}``.

* ``onnxruntime`` (always installed): :func:`geonet_infer.session.make_session`.
* ``openvino`` (extra ``geonet-infer[openvino]``): the same ONNX files compiled by
  OpenVINO's CPU plugin, which runs the QDQ int8 graphs with VNNI kernels (3-4x
  onnxruntime on the small nets here, ``docs/performance.md``). Inference precision
  is forced to f32: the CPU plugin's default on AVX512-BF16/AMX machines is bf16,
  which is slower here and breaks the rigid-flow op's pixel coordinates
  (``../shared/reference/onnx_notes.md`` section 5).
* ``auto``: times both engines on each graph at load and keeps the faster one per
  graph (:func:`pick_fastest`); onnxruntime alone when OpenVINO is not installed.
"""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Protocol

import numpy as np

from geonet_infer.errors import GeoNetError, InputError
from geonet_infer.manifest import IoSpec, Manifest, check_graph_io
from geonet_infer.session import make_session, make_session_options
from geonet_infer.timing import Case, time_interleaved

BACKENDS = ("onnxruntime", "openvino", "auto")
ENGINES = ("onnxruntime", "openvino")  # what "auto" chooses between


class Engine(Protocol):
    backend: str
    input_names: list[str]
    output_names: list[str]

    def run(self, feeds: dict[str, np.ndarray]) -> dict[str, np.ndarray]: ...

    def io(self) -> tuple[list[IoSpec], list[IoSpec]]: ...

    def describe(self) -> dict: ...


class OrtEngine:
    """An onnxruntime session; feeds must be C-contiguous float32."""

    backend = "onnxruntime"

    def __init__(self, path: str | Path, threads: int | None):
        self.path = Path(path)
        self.session = make_session(self.path, make_session_options(threads=threads))
        self.input_names = [i.name for i in self.session.get_inputs()]
        self.output_names = [o.name for o in self.session.get_outputs()]

    def run(self, feeds: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        return dict(zip(self.output_names, self.session.run(None, feeds)))

    def input_shapes(self) -> dict[str, list]:
        return {i.name: list(i.shape) for i in self.session.get_inputs()}

    def io(self) -> tuple[list[IoSpec], list[IoSpec]]:
        """(inputs, outputs) as (name, shape, numpy dtype name), as the graph declares them."""
        return _ort_io(self.session)

    def describe(self) -> dict:
        so = self.session.get_session_options()
        out = {
            "engine": self.backend,
            "providers": self.session.get_providers(),
            "intra_op_num_threads": so.intra_op_num_threads,
            "inter_op_num_threads": so.inter_op_num_threads,
            "execution_mode": str(so.execution_mode),
            "graph_optimization_level": str(so.graph_optimization_level),
            "enable_cpu_mem_arena": so.enable_cpu_mem_arena,
            "enable_mem_pattern": so.enable_mem_pattern,
        }
        for key in ("session.intra_op.allow_spinning", "session.inter_op.allow_spinning"):
            try:
                out[key] = so.get_session_config_entry(key)
            except Exception:  # noqa: BLE001 -- unset keys raise in some onnxruntime versions
                out[key] = None
        return out


def _openvino():
    """The ``openvino`` module, or None when the ``[openvino]`` extra is not installed."""
    try:
        import openvino
    except ImportError:
        return None
    return openvino


def openvino_available() -> bool:
    return _openvino() is not None


def openvino_version() -> str | None:
    ov = _openvino()
    return None if ov is None else ov.__version__


def _ort_io(session) -> tuple[list[IoSpec], list[IoSpec]]:
    def dtype(ort_type: str) -> str:  # "tensor(float)" -> "float32"
        name = ort_type.removeprefix("tensor(").removesuffix(")")
        return {"float": "float32", "double": "float64"}.get(name, name)

    def specs(args) -> list[IoSpec]:
        return [(a.name, list(a.shape), dtype(a.type)) for a in args]

    return specs(session.get_inputs()), specs(session.get_outputs())


class OpenVinoEngine:
    """An ONNX file compiled by OpenVINO's CPU plugin, once per distinct input shape.

    The graphs have a dynamic batch; OpenVINO runs static shapes faster, so each new
    set of input shapes (a new batch size) is compiled once and cached. An infer request
    is not thread-safe (a second thread's inputs overwrite the first's, or the call fails
    with "busy"), so each thread gets its own request per compiled shape.
    """

    backend = "openvino"

    def __init__(self, path: str | Path, threads: int | None):
        ov = _openvino()
        if ov is None:
            raise InputError(
                None,
                "backend 'openvino' needs the OpenVINO runtime, which is not installed",
                "pip install 'geonet-infer[openvino]', or use backend='onnxruntime'",
            )
        self.path = Path(path)
        if not self.path.is_file():
            raise InputError(self.path, "ONNX model not found", "export models with `python -m export`")
        self.core = ov.Core()
        try:
            self.model = self.core.read_model(str(self.path))
        except Exception as exc:  # OpenVINO raises RuntimeError subclasses for unreadable graphs
            raise InputError(
                self.path,
                f"OpenVINO cannot read this model ({str(exc).splitlines()[0][:300]})",
                "re-export it, or use backend='onnxruntime'",
            ) from exc
        self.input_names = [p.get_any_name() for p in self.model.inputs]
        self.output_names = [p.get_any_name() for p in self.model.outputs]
        self.config = {"PERFORMANCE_HINT": "LATENCY", "INFERENCE_PRECISION_HINT": "f32", "NUM_STREAMS": "1"}
        if threads is not None:
            self.config["INFERENCE_NUM_THREADS"] = str(threads)
        self._compiled: dict[tuple, tuple] = {}  # input shapes -> (compiled model, output ports)
        self._compile_lock = threading.Lock()
        self._local = threading.local()  # .requests: input shapes -> this thread's infer request

    def _compiled_for(self, shapes: tuple) -> tuple:
        with self._compile_lock:  # two threads meeting a new batch size compile it once
            if shapes not in self._compiled:
                model = self.model.clone()
                model.reshape(dict(zip(self.input_names, [list(s) for s in shapes])))
                compiled = self.core.compile_model(model, "CPU", self.config)
                self._compiled[shapes] = (compiled, [compiled.output(name) for name in self.output_names])
            return self._compiled[shapes]

    def _request(self, shapes: tuple):
        requests = self._local.__dict__.setdefault("requests", {})
        if shapes not in requests:
            compiled, outputs = self._compiled_for(shapes)
            requests[shapes] = (compiled.create_infer_request(), outputs)
        return requests[shapes]

    def run(self, feeds: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        shapes = tuple(tuple(feeds[n].shape) for n in self.input_names)
        request, outputs = self._request(shapes)
        result = request.infer([feeds[n] for n in self.input_names])
        # copies: the request reuses its output buffers on the next call
        return {name: np.array(result[port]) for name, port in zip(self.output_names, outputs)}

    def input_shapes(self) -> dict[str, list]:
        return {
            p.get_any_name(): [d.get_length() if d.is_static else "B" for d in p.get_partial_shape()]
            for p in self.model.inputs
        }

    def io(self) -> tuple[list[IoSpec], list[IoSpec]]:
        """(inputs, outputs) as (name, shape, numpy dtype name) of the model as read (before any reshape)."""

        def specs(ports) -> list[IoSpec]:
            out = []
            for port in ports:
                shape = port.get_partial_shape()
                dims = None if shape.rank.is_dynamic else [d.get_length() if d.is_static else None for d in shape]
                out.append((port.get_any_name(), dims, str(port.get_element_type().to_dtype())))
            return out

        return specs(self.model.inputs), specs(self.model.outputs)

    def describe(self) -> dict:
        out = {"engine": self.backend, "config": dict(self.config)}
        if self._compiled:
            compiled = next(iter(self._compiled.values()))[0]
            out["properties"] = {
                k: str(compiled.get_property(k))
                for k in ("INFERENCE_PRECISION_HINT", "INFERENCE_NUM_THREADS", "NUM_STREAMS", "PERFORMANCE_HINT")
            }
        return out


def timing_feeds(engine, seed: int = 0) -> dict[str, np.ndarray]:
    """Batch-1 inputs of realistic range for timing a graph: images ~N(0, 0.5), depth 10 m, zero pose,
    a pinhole K with fx = fy = W centred on the image."""
    rng = np.random.default_rng(seed)
    shapes = {
        name: [d if isinstance(d, int) and d > 0 else 1 for d in shape] for name, shape in engine.input_shapes().items()
    }
    h, w = next(s[-2:] for s in shapes.values() if len(s) == 4)
    feeds = {}
    for name, shape in shapes.items():
        if name == "intrinsics":
            value = np.broadcast_to(np.array([[w, 0, w / 2], [0, w, h / 2], [0, 0, 1]]), shape)
        elif name == "depth":
            value = np.full(shape, 10.0)
        elif name == "pose":
            value = np.zeros(shape)
        else:
            value = rng.normal(0.0, 0.5, shape)
        feeds[name] = np.ascontiguousarray(value, dtype=np.float32)
    return feeds


def pick_fastest(path: str | Path, threads: int | None) -> tuple[Engine, dict]:
    """The faster engine for one graph on this machine (batch 1), and the timings behind the choice.

    Falls back to onnxruntime (with the reason) when OpenVINO is missing or cannot
    compile the graph; timing noise only matters when the two are within a few %.
    """
    ort_engine = OrtEngine(path, threads)
    if not openvino_available():
        return ort_engine, {"chosen": "onnxruntime", "reason": "openvino not installed"}
    try:
        engines = {"onnxruntime": ort_engine, "openvino": OpenVinoEngine(path, threads)}
        feeds = timing_feeds(ort_engine)
        cases = [Case(name, lambda e=engine: e.run(feeds)) for name, engine in engines.items()]
        # interleaved blocks, so both see the same background load; no quiet-wait at load time
        time_interleaved(cases, warmup=2, iters=8, block=4, quiet=False, rewarm_ms=0)
    except GeoNetError:
        raise
    except Exception as exc:  # noqa: BLE001 -- any OpenVINO failure means: use onnxruntime
        return ort_engine, {"chosen": "onnxruntime", "reason": f"openvino failed: {str(exc).splitlines()[0][:200]}"}
    p50 = {case.name: case.stats().p50_ms for case in cases}
    chosen = min(p50, key=p50.get)
    return engines[chosen], {"chosen": chosen, "p50_ms_batch1": {k: round(v, 3) for k, v in p50.items()}}


def check_graphs(manifest: Manifest) -> None:
    """Load every graph file the manifest lists in onnxruntime (no optimisation: only its declared
    inputs and outputs are read) and compare them with the manifest (:func:`check_graph_io`)."""
    seen = set()
    for precision, graphs in manifest.graphs.items():
        for name, entry in graphs.items():
            path = manifest.path(name, precision)
            if (path, entry) in seen:
                continue
            seen.add((path, entry))
            session = make_session(path, make_session_options(threads=1, opt_level="disable"))
            check_graph_io(entry, path, *_ort_io(session))


def make_engine(path: str | Path, backend: str, threads: int | None) -> Engine:
    if backend == "onnxruntime":
        return OrtEngine(path, threads)
    if backend == "openvino":
        return OpenVinoEngine(path, threads)
    raise InputError(None, f"unknown backend {backend!r}", f"choose one of {', '.join(BACKENDS)}")

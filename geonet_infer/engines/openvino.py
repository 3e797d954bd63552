"""The OpenVINO engine (extra ``geonet-infer[openvino]``): the same ONNX files on OpenVINO's CPU plugin.

The CPU plugin runs the QDQ int8 graphs with VNNI kernels (3-4x onnxruntime on the small
nets here, ``docs/performance.md``). Inference precision is forced to f32: the plugin's
default on AVX512-BF16/AMX machines is bf16, which is slower here and breaks the rigid-flow
op's pixel coordinates (``../shared/reference/onnx_notes.md`` section 5).

``openvino`` is imported when an engine is made, never at import time, so this module
imports (and ``available()`` answers False) without the extra.
"""

from __future__ import annotations

import threading
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from geonet_infer.errors import BackendUnavailableError, ModelError
from geonet_infer.models.manifest import IoSpec


def _openvino():
    """The ``openvino`` module, or None when the ``[openvino]`` extra is not installed."""
    try:
        import openvino
    except ImportError:
        return None
    return openvino


class OpenVinoEngine:
    """An ONNX file compiled by OpenVINO's CPU plugin, once per distinct input shape.

    The graphs have a dynamic batch; OpenVINO runs static shapes faster, so each new
    set of input shapes (a new batch size) is compiled once and cached. An infer request
    is not thread-safe (a second thread's inputs overwrite the first's, or the call fails
    with "busy"), so each thread gets its own request per compiled shape.
    """

    name = "openvino"
    summary = "openvino (pip install 'geonet-infer[openvino]', 2-4x faster int8 on VNNI CPUs)"
    requires = "the OpenVINO runtime"
    install_hint = "pip install 'geonet-infer[openvino]'"

    @staticmethod
    def available() -> bool:
        return _openvino() is not None

    @staticmethod
    def version() -> str | None:
        ov = _openvino()
        return None if ov is None else ov.__version__

    def __init__(self, path: str | Path, threads: int | None, streams: int = 1, outputs: Sequence[str] | None = None):
        ov = _openvino()
        if ov is None:
            raise BackendUnavailableError(
                None,
                f"backend {self.name!r} needs {self.requires}, which is not installed",
                f"{self.install_hint}, or use backend='onnxruntime'",
            )
        self.path = Path(path)
        if not self.path.is_file():
            raise ModelError(self.path, "ONNX model not found", "export models with `python -m export`")
        self.core = ov.Core()
        try:
            self.model = self.core.read_model(str(self.path))
        except Exception as exc:  # OpenVINO raises RuntimeError subclasses for unreadable graphs
            raise ModelError(
                self.path,
                f"OpenVINO cannot read this model ({str(exc).splitlines()[0][:300]})",
                "re-export it, or use backend='onnxruntime'",
            ) from exc
        if outputs is not None:  # a model of those results alone: compiling drops what they do not need
            results = zip(self.model.get_results(), self.model.outputs)
            kept = [result for result, port in results if port.get_any_name() in outputs]
            if kept:
                self.model = ov.Model(kept, self.model.get_parameters(), self.model.get_friendly_name())
        self.threads, self.streams = threads, streams
        self.input_names = [p.get_any_name() for p in self.model.inputs]
        self.output_names = [p.get_any_name() for p in self.model.outputs]
        # streams > 1 (throughput mode): as many infer requests run at once, each on `threads` threads; with one
        # stream, requests from several Python threads wait for each other (measured: 1.0x, against 1.9x)
        self.config = {"PERFORMANCE_HINT": "LATENCY", "INFERENCE_PRECISION_HINT": "f32", "NUM_STREAMS": str(streams)}
        if threads is not None:
            self.config["INFERENCE_NUM_THREADS"] = str(threads * streams)
        self._compiled: dict[tuple, tuple] = {}  # input shapes -> (compiled model, output ports)
        self._compile_lock = threading.Lock()
        self._local = threading.local()  # .requests: input shapes -> this thread's infer request

    def only(self, outputs: Sequence[str]) -> OpenVinoEngine:
        """This graph computing only ``outputs`` (and what they need)."""
        return OpenVinoEngine(self.path, self.threads, self.streams, outputs)

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
        out = {"engine": self.name, "config": dict(self.config), "outputs": self.output_names}
        if self._compiled:
            compiled = next(iter(self._compiled.values()))[0]
            out["properties"] = {
                k: str(compiled.get_property(k))
                for k in ("INFERENCE_PRECISION_HINT", "INFERENCE_NUM_THREADS", "NUM_STREAMS", "PERFORMANCE_HINT")
            }
        return out


# 0.x names, still imported by the CLI and tests; new code asks the class
def openvino_available() -> bool:
    return OpenVinoEngine.available()


def openvino_version() -> str | None:
    return OpenVinoEngine.version()

"""The onnxruntime engine: always installed, the reference every other engine is checked against.

Also the package's one onnxruntime session factory (:func:`make_session`, options from
:func:`make_session_options`): export's checks, the tests and the runtime all use it.

CPU facts behind the defaults (``../shared/reference/onnx_notes.md`` section 2):

* ``intra_op_num_threads=0`` (ORT default) sizes the pool to the host's physical
  cores and pins threads; setting a number disables pinning. GeoNet runs several
  sessions one after another per frame, so each may use all cores.
* Spinning is ORT's default and burns CPU between runs; it slows co-located
  work (numpy pre-processing, other sessions). Off by default here.
* ``inter_op_num_threads`` only matters for ``ORT_PARALLEL``; we keep sequential
  execution and 1 inter-op thread.
* Every session of the process allocates from one shared CPU arena (onnxruntime's
  environment allocator, :func:`_share_one_arena`) instead of one arena each: an arena keeps
  its largest run's buffers for good, and a cascade has four sessions. Measured in one
  interleaved run (issue 30, docs/performance.md): peak memory after a 4-frame sequence
  178 -> 112 MiB for the small INT8 model, predict as fast; with no arena at all 110 MiB, but
  every run's buffers are then fresh pages (system time 0.9 -> 1.4 s, predict 6-10 % slower).
* INT8 on CPUs without VNNI (AVX2 only, plain AVX-512): onnxruntime's U8S8 kernels add pairs of
  uint8 x int8 products in int16 with saturation (VPMADDUBSW), so 8-bit weights beyond +-64
  overflow (``geonet_infer/convert/int8_arith.py`` emulates it). :data:`X64_QUANT_PRECISION` turns on
  onnxruntime's own remedy: it stores such a graph's int8 weights as uint8 and runs exact U8U8
  kernels; it changes nothing on CPUs with VNNI or AMX, so it is set only where the INT8 kernel is
  "avx2" (issue 45, docs/performance.md). onnxruntime refuses it for a graph whose int8 weight
  feeds several nodes; such a graph then loads without it, after one line on stderr.
"""

from __future__ import annotations

import contextlib
import sys
import threading
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import onnxruntime as ort

from geonet_infer.engines.cpu import cpu_info
from geonet_infer.errors import InputError, ModelError
from geonet_infer.models.manifest import IoSpec
from geonet_infer.models.onnx_graph import keep_outputs

# onnxruntime's kOrtSessionOptionsAvx2PrecisionMode (see the module docstring)
X64_QUANT_PRECISION = "session.x64quantprecision"

OPT_LEVELS = {
    "disable": ort.GraphOptimizationLevel.ORT_DISABLE_ALL,
    "basic": ort.GraphOptimizationLevel.ORT_ENABLE_BASIC,
    "extended": ort.GraphOptimizationLevel.ORT_ENABLE_EXTENDED,
    "all": ort.GraphOptimizationLevel.ORT_ENABLE_ALL,
}


def make_session_options(
    threads: int | None = None, spinning: bool = False, opt_level: str = "all"
) -> ort.SessionOptions:
    """SessionOptions for CPU inference.

    Args:
        threads: intra-op threads; None = ORT's default (one per physical core).
        spinning: let idle pool threads spin (lower latency, burns CPU).
        opt_level: "disable" | "basic" | "extended" | "all" (graph optimisations).
    """
    if opt_level not in OPT_LEVELS:
        raise InputError(None, f"unknown optimisation level {opt_level!r}", f"choose one of {', '.join(OPT_LEVELS)}")
    if threads is not None and (not isinstance(threads, int) or threads < 1):
        raise InputError(None, f"threads must be a positive integer or None, got {threads!r}")
    so = ort.SessionOptions()
    so.graph_optimization_level = OPT_LEVELS[opt_level]
    so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    so.inter_op_num_threads = 1
    if _share_one_arena():  # see the module docstring
        so.add_session_config_entry("session.use_env_allocators", "1")
    if threads is not None:
        so.intra_op_num_threads = threads
    flag = "1" if spinning else "0"
    so.add_session_config_entry("session.intra_op.allow_spinning", flag)
    so.add_session_config_entry("session.inter_op.allow_spinning", flag)
    if cpu_info()["int8_kernel"] == "avx2":  # only there does it change anything (module docstring)
        so.add_session_config_entry(X64_QUANT_PRECISION, "1")
    so.log_severity_level = 3  # errors only; warnings about unused initialisers are noise
    return so


_arena_lock = threading.Lock()
_arena_shared: bool | None = None  # None: not tried yet


def _share_one_arena() -> bool:
    """Register one CPU arena for the whole process, once; False where this onnxruntime cannot
    (then each session keeps its own arena, onnxruntime's default)."""
    global _arena_shared
    with _arena_lock:
        if _arena_shared is None:
            try:
                info = ort.OrtMemoryInfo("Cpu", ort.OrtAllocatorType.ORT_ARENA_ALLOCATOR, 0, ort.OrtMemType.DEFAULT)
                ort.create_and_register_allocator(info, ort.OrtArenaCfg(0, -1, -1, -1))  # onnxruntime's defaults
                _arena_shared = True
            except Exception:  # noqa: BLE001 -- missing in old versions (AttributeError) or onnxruntime's Fail
                _arena_shared = False
        return _arena_shared


def make_session(
    path: str | Path,
    options: ort.SessionOptions | None = None,
    providers: Sequence[str] = ("CPUExecutionProvider",),
    model: bytes | None = None,
) -> ort.InferenceSession:
    """Load an ONNX graph; errors name the file. ``model``: the graph's bytes as they should run (the
    file's, cut down by :func:`geonet_infer.models.onnx_graph.keep_outputs`) instead of the file.

    Raises GeoNetError if the file is missing or onnxruntime cannot load it,
    or if a requested execution provider did not become active.
    """
    path = Path(path)
    if not path.is_file():
        raise ModelError(path, "ONNX model not found", "export models with `python -m export`")
    options = options or make_session_options()
    source = str(path) if model is None else model
    try:
        try:
            session = ort.InferenceSession(source, sess_options=options, providers=list(providers))
        except Exception as exc:
            if "Attempt to replace the existing tensor" not in str(exc) or not _has_int8_remedy(options):
                raise
            # onnxruntime cannot apply its remedy to an int8 weight that feeds several nodes: without it
            # the graph loads, and its INT8 may saturate on this CPU (said in one line)
            options.add_session_config_entry(X64_QUANT_PRECISION, "0")
            session = ort.InferenceSession(source, sess_options=options, providers=list(providers))
            print(
                f"geonet-infer: warning: {path}: onnxruntime cannot run this graph's INT8 exactly on a CPU "
                "without VNNI (an int8 weight feeds several nodes); its INT8 may saturate here",
                file=sys.stderr,
            )
    except Exception as exc:  # ORT raises Fail / InvalidProtobuf / InvalidGraph / RuntimeException
        raise ModelError(
            path,
            f"onnxruntime cannot load this model ({exc.__class__.__name__}: {str(exc).splitlines()[0][:300]})",
            "the file is corrupt or was written by an incompatible exporter; re-export it",
        ) from exc
    missing = [p for p in providers if p not in session.get_providers()]
    if missing:
        raise ModelError(
            path, f"execution provider(s) {missing} not active", f"available: {ort.get_available_providers()}"
        )
    return session


def _has_int8_remedy(options: ort.SessionOptions) -> bool:
    try:
        return options.get_session_config_entry(X64_QUANT_PRECISION) == "1"
    except RuntimeError:  # onnxruntime raises for an entry never set
        return False


class OrtEngine:
    """An onnxruntime session; feeds must be C-contiguous float32."""

    name = "onnxruntime"
    summary = "onnxruntime"  # this engine in `--backend`'s help
    requires = "onnxruntime"
    install_hint = "pip install geonet-infer"  # a core dependency: installed with the package

    @staticmethod
    def available() -> bool:
        return True

    @staticmethod
    def version() -> str | None:
        return ort.__version__

    def __init__(self, path: str | Path, threads: int | None, streams: int = 1, outputs: Sequence[str] | None = None):
        del streams  # a session takes concurrent calls as it is
        self.path, self.threads = Path(path), threads
        # onnxruntime runs every node whatever outputs a call asks for: fewer outputs need a smaller graph
        model = None
        if outputs is not None and self.path.is_file():
            with contextlib.suppress(ValueError):  # protobuf this reader does not follow: the whole graph
                model = keep_outputs(self.path.read_bytes(), outputs)
        self.session = make_session(self.path, make_session_options(threads=threads), model=model)
        self.input_names = [i.name for i in self.session.get_inputs()]
        self.output_names = [o.name for o in self.session.get_outputs()]

    def only(self, outputs: Sequence[str]) -> OrtEngine:
        """This graph computing only ``outputs`` (and what they need)."""
        return OrtEngine(self.path, self.threads, outputs=outputs)

    def run(self, feeds: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        return dict(zip(self.output_names, self.session.run(None, feeds)))

    def input_shapes(self) -> dict[str, list]:
        return {i.name: list(i.shape) for i in self.session.get_inputs()}

    def io(self) -> tuple[list[IoSpec], list[IoSpec]]:
        """(inputs, outputs) as (name, shape, numpy dtype name), as the graph declares them."""
        return ort_io(self.session)

    def describe(self) -> dict:
        so = self.session.get_session_options()
        out = {
            "engine": self.name,
            "providers": self.session.get_providers(),
            "intra_op_num_threads": so.intra_op_num_threads,
            "inter_op_num_threads": so.inter_op_num_threads,
            "execution_mode": str(so.execution_mode),
            "graph_optimization_level": str(so.graph_optimization_level),
            "enable_cpu_mem_arena": so.enable_cpu_mem_arena,
            "enable_mem_pattern": so.enable_mem_pattern,
            "outputs": self.output_names,  # fewer than the file's after only()
        }
        for key in (
            "session.intra_op.allow_spinning",
            "session.inter_op.allow_spinning",
            "session.use_env_allocators",
            X64_QUANT_PRECISION,
        ):
            try:
                out[key] = so.get_session_config_entry(key)
            except Exception:  # noqa: BLE001 -- unset keys raise in some onnxruntime versions
                out[key] = None
        return out


def ort_io(session: ort.InferenceSession) -> tuple[list[IoSpec], list[IoSpec]]:
    """A session's (inputs, outputs) as (name, shape, numpy dtype name)."""

    def dtype(ort_type: str) -> str:  # "tensor(float)" -> "float32"
        name = ort_type.removeprefix("tensor(").removesuffix(")")
        return {"float": "float32", "double": "float64"}.get(name, name)

    def specs(args) -> list[IoSpec]:
        return [(a.name, list(a.shape), dtype(a.type)) for a in args]

    return specs(session.get_inputs()), specs(session.get_outputs())

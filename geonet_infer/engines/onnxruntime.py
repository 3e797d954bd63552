"""The onnxruntime engine: always installed, the reference every other engine is checked against.

Sessions come from the package's one factory, :func:`geonet_infer.session.make_session`
(CPU options: :func:`geonet_infer.session.make_session_options`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnxruntime as ort

from geonet_infer.manifest import IoSpec
from geonet_infer.session import make_session, make_session_options


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
        }
        for key in ("session.intra_op.allow_spinning", "session.inter_op.allow_spinning"):
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

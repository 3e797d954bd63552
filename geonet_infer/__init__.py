"""geonet_infer: GeoNet depth, flow and pose on CPU (onnxruntime + numpy + OpenCV, no torch).

import geonet_infer
predictor = geonet_infer.load()              # the bundled default model
result = predictor.depth("frame.png")        # DepthResult: depth (H, W), timings_ms
"""

from geonet_infer.core.predictor import Predictor, load
from geonet_infer.core.results import DepthResult, FlowResult, FrameResult, PoseResult, SequenceResult
from geonet_infer.errors import BackendUnavailableError, GeoNetError, GeoNetInputError, InputError, ModelError


def __getattr__(name: str) -> str:
    """``__version__``, read from the installed package's metadata on first use: importlib.metadata
    costs about 0.1 s, which ``import geonet_infer`` should not pay for a string few callers read."""
    if name != "__version__":
        raise AttributeError(f"module 'geonet_infer' has no attribute {name!r}")
    from importlib.metadata import PackageNotFoundError, version

    try:  # one version, in pyproject.toml
        found = version("geonet-infer")
    except PackageNotFoundError:  # running from a source tree that was never installed
        found = "0+unknown"
    globals()["__version__"] = found
    return found


__all__ = [
    "BackendUnavailableError",
    "DepthResult",
    "FlowResult",
    "FrameResult",
    "GeoNetError",
    "GeoNetInputError",
    "InputError",
    "ModelError",
    "PoseResult",
    "Predictor",
    "SequenceResult",
    "__version__",
    "load",
]

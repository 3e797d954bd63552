"""geonet_infer: GeoNet depth, flow and pose on CPU (onnxruntime + numpy + OpenCV, no torch).

import geonet_infer
predictor = geonet_infer.load()              # the bundled default model
result = predictor.depth("frame.png")        # DepthResult: depth (H, W), timings_ms
"""

from geonet_infer.errors import BackendUnavailableError, GeoNetError, GeoNetInputError, InputError, ModelError

try:  # one version, in pyproject.toml
    from importlib.metadata import PackageNotFoundError, version

    __version__ = version("geonet-infer")
except PackageNotFoundError:  # running from a source tree that was never installed
    __version__ = "0+unknown"

from geonet_infer.predictor import Predictor, load  # noqa: E402
from geonet_infer.results import DepthResult, FlowResult, FrameResult, PoseResult, SequenceResult  # noqa: E402

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

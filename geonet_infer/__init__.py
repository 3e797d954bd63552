"""geonet_infer: GeoNet depth, flow and pose on CPU (onnxruntime + numpy + OpenCV, no torch).

    import geonet_infer
    predictor = geonet_infer.load()              # the bundled default model
    result = predictor.depth("frame.png")        # DepthResult: depth (H, W), timings_ms
"""
from geonet_infer.errors import GeoNetInputError

__version__ = "0.1.0"

from geonet_infer.predictor import (DepthResult, FlowResult, FrameResult, PoseResult, Predictor,  # noqa: E402
                                    SequenceResult, load)

__all__ = ["DepthResult", "FlowResult", "FrameResult", "GeoNetInputError", "PoseResult", "Predictor",
           "SequenceResult", "__version__", "load"]

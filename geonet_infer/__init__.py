"""geonet_infer: GeoNet depth, flow and pose on CPU (onnxruntime + numpy + OpenCV, no torch)."""
from geonet_infer.errors import GeoNetInputError

__version__ = "0.1.0"
__all__ = ["GeoNetInputError", "__version__"]

"""torch -> ONNX export of GeoNet (model directories the runtime ``geonet_infer`` loads).

from export import ExportConfig, export_model
"""

from export.build import ExportConfig, export_model

__all__ = ["ExportConfig", "export_model"]

"""Moved to :mod:`geonet_infer.output` (issue 42): ``predict_to_dir`` in ``output.predict``, the file
layout in ``output.layout``, ``OutputOptions`` in ``output.options``, the writer, point clouds and
video in their own modules; the folder ownership in :mod:`geonet_infer.ownership`.

This alias goes in the next release; each use of an old name warns (DeprecationWarning).
"""

from geonet_infer._moved import forward

__getattr__ = forward(
    __name__,
    "geonet_infer.output.predict",
    "geonet_infer.output.layout",
    "geonet_infer.output.options",
    "geonet_infer.output.video",
    "geonet_infer.output.writer",
    "geonet_infer.output.frames",
    "geonet_infer.tasks",
    "geonet_infer.limits",
)

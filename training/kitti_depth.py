"""Velodyne -> depth ground truth now lives in the runtime (:mod:`geonet_infer.velodyne`),
so ``geonet-infer eval`` and training share one implementation; re-exported for old imports."""

from geonet_infer.velodyne import (
    load_velodyne_points,
    project_velodyne,
    velodyne_to_depth_map,
    velodyne_to_image_matrix,
)

__all__ = ["load_velodyne_points", "project_velodyne", "velodyne_to_depth_map", "velodyne_to_image_matrix"]

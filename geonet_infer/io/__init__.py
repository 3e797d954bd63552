"""File formats shared by training, evaluation, the runtime and the synthetic data.

numpy + OpenCV (+ isal's deflate for the PNGs we write). Every writer goes through
:func:`atomic_write`, so a crash never leaves a half-written file where a reader would trust it.
Every reader raises :class:`~geonet_infer.errors.GeoNetError` naming the file.

Modules: ``atomic`` (atomic writes, ``.npy``), ``images`` (RGB images, masks, image
folders), ``png`` (the PNG encoder every writer uses), ``flow`` (KITTI flow PNG, ``.flo``),
``depth`` (KITTI depth PNG), ``poses`` (KITTI / TUM trajectories), ``calib`` (calibration
files, :class:`Camera`), ``frames`` (video / KITTI drive / image-folder frame sources). Colour
maps live in :mod:`geonet_infer.output.viz`. Everything public is re-exported here.

Encodings (see ``docs/synthetic_data.md``):

* Images: 8-bit RGB in memory (OpenCV's BGR order only inside ``images`` and ``frames``).
* KITTI flow PNG: 16-bit, 3 channels, R = u*64 + 2**15, G = v*64 + 2**15,
  B = 1 valid / 0 invalid; invalid pixels are written as (0, 0, 0).
* KITTI depth PNG: 16-bit, 1 channel, round(depth_m * 256); 0 = no measurement.
* Middlebury ``.flo``: float32 tag 202021.25, int32 width, int32 height,
  then interleaved (u, v) float32, little-endian, row-major.
* KITTI odometry poses: 12 values per line, row-major 3x4 camera-to-world.
* TUM poses: ``time tx ty tz qx qy qz qw`` (Hamilton quaternion, w last).
* KITTI calibration: ``key: v1 v2 ...`` lines; our own files hold
  ``K: fx 0 cx 0 fy cy 0 0 1`` (row-major 3x3).
* GeoNet ``<frame>_cam.txt``: one line ``fx,0.,cx,0.,fy,cy,0.,0.,1.``.
* Camera distortion: OpenCV order ``k1 k2 p1 p2 [k3 ...]``.
"""

from __future__ import annotations

from geonet_infer.io.atomic import atomic_write, save_npy_atomic
from geonet_infer.io.calib import (
    CAMERA_FORMATS,
    Camera,
    cam_txt_line,
    read_calib_file,
    read_calib_K,
    read_cam_txt,
    read_camera,
    require_key,
    write_calib_K,
    write_cam_txt,
)
from geonet_infer.io.depth import DEPTH_SCALE, read_depth_kitti, write_depth_kitti
from geonet_infer.io.flow import (
    FLO_MAGIC,
    FLOW_OFFSET,
    FLOW_SCALE,
    decode_flow_kitti,
    encode_flow_kitti,
    read_flo,
    read_flow_kitti,
    write_flo,
    write_flow_kitti,
)
from geonet_infer.io.frames import VIDEO_SUFFIXES, Frame, FrameSource, open_frames
from geonet_infer.io.images import IMAGE_SUFFIXES, list_images, read_image, read_mask, write_image, write_mask
from geonet_infer.io.layouts import KITTI_CALIB_NAME
from geonet_infer.io.poses import (
    quaternion_to_rotation,
    read_kitti_poses,
    read_tum_poses,
    rotation_to_quaternion,
    write_kitti_poses,
    write_tum_poses,
)

__all__ = [
    # atomic
    "atomic_write",
    "save_npy_atomic",
    # images
    "IMAGE_SUFFIXES",
    "list_images",
    "read_image",
    "write_image",
    "read_mask",
    "write_mask",
    # flow
    "FLOW_SCALE",
    "FLOW_OFFSET",
    "FLO_MAGIC",
    "encode_flow_kitti",
    "decode_flow_kitti",
    "write_flow_kitti",
    "read_flow_kitti",
    "write_flo",
    "read_flo",
    # depth
    "DEPTH_SCALE",
    "write_depth_kitti",
    "read_depth_kitti",
    # poses
    "read_kitti_poses",
    "write_kitti_poses",
    "rotation_to_quaternion",
    "quaternion_to_rotation",
    "write_tum_poses",
    "read_tum_poses",
    # calib
    "CAMERA_FORMATS",
    "Camera",
    "read_camera",
    "read_calib_file",
    "require_key",
    "read_calib_K",
    "write_calib_K",
    "cam_txt_line",
    "write_cam_txt",
    "read_cam_txt",
    # frames
    "VIDEO_SUFFIXES",
    "KITTI_CALIB_NAME",
    "Frame",
    "FrameSource",
    "open_frames",
]

"""Procedural KITTI-like driving sequences with exact depth, optical-flow and pose ground truth.

KITTI cannot be downloaded here, so training and the evaluation code are exercised
on synthetic scenes written in KITTI's own encodings (see ``docs/synthetic_data.md``).

How a frame is made (numpy + OpenCV only, no torch):

* The scene is a flat ground plane (road with lane markings, sidewalks, grass),
  yaw-oriented boxes (buildings, walls, poles, trees, parked and moving cars,
  far backdrop blocks) and a world-fixed sky sphere of radius >= 1000 m. The sky
  has a *finite* depth so its flow is exact; it is beyond the 256 m that a KITTI
  uint16 depth PNG can hold, so depth PNGs store 0 (= no measurement) there, as
  KITTI's LiDAR ground truth does for the sky.
* Every pixel is ray-cast analytically (vectorised numpy). Rays are
  ``D = R_cw @ K^-1 [u, v, 1]`` so the ray parameter of a hit *is* its z-depth.
  Boxes are only tested inside the image rectangle their (near-plane clipped)
  corners project to.
* Geometry (depth, hit points, flow) is cast at the pixel centres of the output
  grid, u = 0..W-1, v = 0..H-1, in float64. Colour is cast on a 2x2 supersampled
  grid (offsets +-0.25 px) in float32 and area-downsampled, textures are
  mip-mapped (trilinear), lane markings are box-filtered analytically.
* Flow t -> t+1: each hit point is moved by the camera motion (and, on a moving
  car, by that car's own rigid motion) and projected into frame t+1. ``occ``
  validity = it lands inside [0, W-1] x [0, H-1] in front of the camera; ``noc``
  additionally requires it to be visible in frame t+1: its depth there is not
  behind all four rendered depths around its landing point (on a plane inverse
  depth is linear in the image, so a visible point is never behind all four).

Modules: ``scene`` (road, trajectory, boxes), ``textures`` (material tiles, mip atlas),
``render`` (ray casting, colour), ``truth`` (depth, motion mask, flow), ``sequence``
(frames, files, whole folders: :class:`SynthConfig` + :func:`generate`), ``cli``
(``python -m training.synth --help``).
"""

from training.synth.cli import build_parser, main
from training.synth.sequence import (
    GENERATOR_VERSION,
    SynthConfig,
    generate,
    generate_sequence,
    iter_frames,
    sequence_name,
    write_sequence,
)

__all__ = [
    "GENERATOR_VERSION",
    "SynthConfig",
    "build_parser",
    "generate",
    "generate_sequence",
    "iter_frames",
    "main",
    "sequence_name",
    "write_sequence",
]

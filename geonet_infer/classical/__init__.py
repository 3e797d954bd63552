"""The classical methods, the other engine of each task: DIS flow and ORB-VO poses (OpenCV).

The eval scores them as baselines (:mod:`geonet_infer.eval.baselines`, ``geonet-infer eval``);
here are the methods and their names; :mod:`geonet_infer.core.classical_frames` fills a sequence's
:class:`~geonet_infer.core.results.FrameResult` flow or poses with them, so ``predict``, ``batch`` and
:meth:`Predictor.iter_sequence` write them in the usual layout.

* ``flow_method="dis"``: OpenCV DIS optical flow, preset medium (:func:`dis_flow`, the
  eval's "DIS medium"), frame t -> t+1 at the input resolution on the frames as the networks
  see them (undistorted when the camera has distortion). No network and no intrinsics needed.
* ``pose_method="orbvo"``: the eval's two-view ORB-VO step (:func:`relative_pose`:
  ORB, cross-checked matches, 5-point RANSAC, ``recoverPose``) per consecutive pair. Monocular
  steps have no length; each step's is set from the frame's predicted depth: the step's inliers
  are triangulated with a unit step and the length is the median of (predicted depth /
  triangulated depth) over them. Translations are so in the depth's units, like the network's
  poses: metres with a camera height (the smoothed metric depth), else the model's relative
  scale. A pair whose matches moved less than :data:`STILL_SHIFT_PX` (median) is a camera
  standing still: no motion. Any other pair that fails (too few matches, inliers or triangulated
  points) repeats the previous step (the first one: no motion), as the eval's ORB-VO does.
  Needs DepthNet and K.
"""

from __future__ import annotations

from collections.abc import Iterable

from geonet_infer.classical.flow import DIS_PRESETS, dis_flow, grey
from geonet_infer.classical.pose import (
    MIN_TRIANGULATED,
    ORB_FEATURES,
    ORB_MIN_INLIERS,
    STILL_SHIFT_PX,
    PairPose,
    euler_xyz,
    orb_matcher,
    relative_pose,
    step_length,
)
from geonet_infer.errors import InputError

__all__ = [
    "CLASSICAL_GRAPHS", "CLASSICAL_STAGES", "DIS_PRESET", "DIS_PRESETS", "FLOW_METHODS", "MIN_TRIANGULATED",
    "ORB_FEATURES", "ORB_MIN_INLIERS", "POSE_METHODS", "STILL_SHIFT_PX", "PairPose", "check_methods",
    "classical_tasks", "describe", "dis_flow", "euler_xyz", "grey", "orb_matcher", "relative_pose", "step_length",
]  # fmt: skip

FLOW_METHODS = ("network", "dis")
POSE_METHODS = ("network", "orbvo")
DIS_PRESET = "medium"  # the eval's DIS row (docs/real_eval.md)
CLASSICAL_STAGES = ("dis", "orbvo")  # timings_ms keys of the classical methods
CLASSICAL_GRAPHS = {"flow": (), "pose": ("depthnet",)}  # ORB-VO takes its steps' length from the depth


def check_methods(flow_method: str, pose_method: str) -> None:
    if flow_method not in FLOW_METHODS:
        raise InputError(None, f"unknown flow method {flow_method!r}", f"choose one of {', '.join(FLOW_METHODS)}")
    if pose_method not in POSE_METHODS:
        raise InputError(None, f"unknown pose method {pose_method!r}", f"choose one of {', '.join(POSE_METHODS)}")


def classical_tasks(tasks: Iterable[str], flow_method: str, pose_method: str) -> tuple[str, ...]:
    """The tasks of ``tasks`` that a classical method makes."""
    chosen = {"flow": flow_method == "dis", "pose": pose_method == "orbvo"}
    return tuple(t for t in tasks if chosen.get(t, False))


def describe(tasks: Iterable[str], flow_method: str, pose_method: str) -> dict:
    """What made each output, for summary.json."""
    tasks = tuple(tasks)
    out: dict[str, dict] = {}
    if "depth" in tasks:
        out["depth"] = {"method": "network"}
    if "flow" in tasks:
        out["flow"] = (
            {"method": "dis", "detail": f"OpenCV DIS optical flow, preset {DIS_PRESET}, at the input resolution"}
            if flow_method == "dis"
            else {"method": "network"}
        )
    if "pose" in tasks:
        out["pose"] = (
            {
                "method": "orbvo",
                "detail": "two-view ORB-VO per consecutive pair (ORB, 5-point RANSAC, recoverPose); matches "
                f"moving under {STILL_SHIFT_PX:g} px (median): no motion; another failed pair repeats the last step",
                "scale": "step length = median(predicted depth / triangulated depth) over the step's inliers: "
                "in the depth's units (metres with a camera height)",
            }
            if pose_method == "orbvo"
            else {"method": "network"}
        )
    return out

"""``output.frames.unusable``: one bad value anywhere fails a frame, as ``np.isfinite(x).all()`` defines it."""

import numpy as np
import pytest

from geonet_infer.core.results import FrameResult
from geonet_infer.output.frames import unusable

TASKS = ("depth", "pose", "flow")


def result(depth: np.ndarray, flow: np.ndarray, pose: np.ndarray) -> FrameResult:
    return FrameResult(
        index=0,
        name="000000",
        depth=depth,
        disparity=None,
        camera_to_world=pose,
        pose_to_next=None,
        pose_vector_to_next=None,
        flow=flow,
        undistorted=False,
        timings_ms={},
    )


def scene(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    depth = rng.uniform(1, 80, (37, 53)).astype(np.float32)
    flow = rng.normal(0, 5, (37, 53, 2)).astype(np.float32)
    return depth, flow, np.eye(4)


@pytest.mark.parametrize("what", ["depth", "flow", "pose"])
@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_one_bad_value_anywhere_is_found(what, bad):
    rng = np.random.default_rng(0)
    for trial in range(20):  # one value at a random place, and at the first and last element
        depth, flow, pose = scene(rng)
        values = {"depth": depth, "flow": flow, "pose": pose}[what]
        where = (0, values.size - 1, int(rng.integers(values.size)))[min(trial, 2)]
        values.flat[where] = bad
        assert not np.isfinite(values).all()  # the definition the check must agree with
        assert unusable(result(depth, flow, pose), TASKS) == f"NaN/inf {what}"


def test_finite_outputs_pass_and_a_task_left_out_is_not_checked():
    rng = np.random.default_rng(1)
    depth, flow, pose = scene(rng)
    assert unusable(result(depth, flow, pose), TASKS) is None
    flow[3, 4, 1] = np.nan
    assert unusable(result(depth, flow, pose), ("depth", "pose")) is None
    assert unusable(result(depth, flow, pose), TASKS) == "NaN/inf flow"


def test_a_constant_depth_is_degenerate():
    rng = np.random.default_rng(2)
    _, flow, pose = scene(rng)
    assert unusable(result(np.full((37, 53), 2.5, np.float32), flow, pose), TASKS) == (
        "degenerate depth (every pixel 2.5)"
    )

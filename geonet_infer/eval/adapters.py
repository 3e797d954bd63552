"""What ``geonet-infer eval`` scores: a model's predictor or a baseline as the callables of the scoring
loops (depth ``fn(rgb)``, flow ``fn(frames, K)``, pose ``fn(frames, K)``)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from geonet_infer.errors import InputError
from geonet_infer.eval import metrics
from geonet_infer.eval.datasets import SNIPPET


# ----------------------------------------------------------------------------- model adapters
def _needs_K(fn):
    fn.needs_intrinsics = True
    return fn


def refuse_random_init(predictor) -> None:
    if predictor.manifest.random_init:
        raise InputError(
            predictor.model_dir,
            "this model directory holds random-init (timing-only) graphs",
            "accuracy needs graphs exported from a trained --checkpoint",
        )


def model_depth_fn(predictor, allow_random_init: bool = False) -> Callable:
    """Depth of a :class:`~geonet_infer.core.predictor.Predictor` at the input resolution.
    ``allow_random_init`` (every adapter): score random weights (development cards only)."""
    if not allow_random_init:
        refuse_random_init(predictor)
    return lambda rgb: predictor.depth(rgb).depth


def model_flow_fn(predictor, allow_random_init: bool = False) -> Callable:
    """Full flow t -> t+1; a 3-frame model gets [t-1, t, t+1] when the item has it, any other
    case the pair [t, t+1] (the runtime pads it as at a video start)."""
    if not allow_random_init:
        refuse_random_init(predictor)

    def predict(frames, K):
        if len(frames) == predictor.seq_length:
            return predictor.flow(list(frames), K).flow
        return predictor.flow(list(frames[-2:]), K).flow

    return _needs_K(predict)


def snippet_from_pose_calls(pose_fn: Callable, frames: list, seq_length: int) -> np.ndarray:
    """5-frame snippet poses (first-frame coordinates) from a PoseNet taking ``seq_length`` frames.

    ``pose_fn(frames) -> (L-1, 4, 4)`` target->source transforms (target in the middle).
    L = 5: one call, the paper's protocol. L = 3: the triplets [0, 1, 2] and [2, 3, 4], chained
    through frame 2: G1 = T(1->0), G2 = G1 T(1->2)^-1, G3 = G2 T(3->2), G4 = G3 T(3->4)^-1.
    """
    if seq_length == SNIPPET:
        return metrics.snippet_poses_to_global(pose_fn(frames), target_index=SNIPPET // 2)
    if seq_length != 3:
        raise InputError(
            None,
            f"pose snippets need a PoseNet of 3 or 5 frames, this one takes {seq_length}",
            "export the model with --seq-length 3 or 5",
        )
    (T10, T12), (T32, T34) = pose_fn(frames[0:3]), pose_fn(frames[2:5])
    G1 = np.asarray(T10, np.float64)
    G2 = G1 @ metrics.rigid_inverse(T12)
    G3 = G2 @ np.asarray(T32, np.float64)
    return np.stack([np.eye(4), G1, G2, G3, G3 @ metrics.rigid_inverse(T34)])


def model_pose_fn(predictor, allow_random_init: bool = False) -> Callable:
    """Snippet poses from the runtime's PoseNet (:func:`snippet_from_pose_calls`)."""
    if not allow_random_init:
        refuse_random_init(predictor)
    return lambda frames, K: snippet_from_pose_calls(
        lambda f: predictor.pose(list(f)).matrices, frames, predictor.seq_length
    )


def model_fn(task: str, predictor, allow_random_init: bool = False) -> Callable:
    adapter = {"depth": model_depth_fn, "flow": model_flow_fn, "pose": model_pose_fn}[task]
    return adapter(predictor, allow_random_init)


# ----------------------------------------------------------------------------- baselines
def baseline_fns(task: str, method: str) -> dict[str, Callable]:
    """{row label: fn} of a baseline ``method`` ("dis" gives both DIS presets)."""
    from geonet_infer.eval import baselines as b

    table = {
        "depth": {"constant": {"constant depth": b.constant_depth}},
        "flow": {
            "zero": {"zero flow": b.zero_flow},
            "dis": {"DIS medium": b.dis_flow("medium"), "DIS ultrafast": b.dis_flow("ultrafast")},
            "dis-medium": {"DIS medium": b.dis_flow("medium")},
            "dis-ultrafast": {"DIS ultrafast": b.dis_flow("ultrafast")},
        },
        "pose": {"identity": {"identity pose": b.identity_pose}, "orb-vo": {"ORB-VO": _needs_K(b.orb_vo)}},
    }[task]
    if method not in table:
        raise InputError(None, f"no {task} method {method!r}", f"{task} methods: model, {', '.join(table)}")
    return table[method]


BASELINES = {
    "depth": ("constant",),
    "flow": ("dis", "dis-medium", "dis-ultrafast", "zero"),
    "pose": ("orb-vo", "identity"),
}

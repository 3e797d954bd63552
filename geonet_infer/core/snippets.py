"""Snippets: the ONE window rule at a sequence's ends, PoseNet's order, ResFlowNet's 12-channel input."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from geonet_infer.core.spec import ImageLike, InputSpec, Intrinsics, StageTimer, camera_at, read_frame, to_network
from geonet_infer.errors import InputError
from geonet_infer.io.calib import Camera


def snippet_indices(t: int, num_frames: int, seq_length: int) -> list[int]:
    """Frame indices of the snippet for target ``t``, ordered [target] + sources in temporal order.

    The snippet is the window t - k .. t + k (k = seq_length // 2). At the ends
    of a sequence a missing neighbour is replaced by the nearest existing frame
    (indices clipped to [0, num_frames - 1]): the first frame of a 3-frame model
    is seen as [f0, f0, f1] in temporal order, i.e. a zero-motion previous frame.
    This is the only place that order is written down for the runtime.
    """
    if num_frames < 2:
        raise InputError(
            None, f"a sequence needs at least 2 frames, got {num_frames}", "pass consecutive frames of one video"
        )
    k = seq_length // 2
    window = snippet_window(t, num_frames, seq_length)
    return [window[k]] + window[:k] + window[k + 1 :]


def snippet_window(t: int, num_frames: int, seq_length: int) -> list[int]:
    """The frames t - k .. t + k (k = seq_length // 2) in temporal order, each clipped to
    [0, num_frames - 1]: the one rule for a snippet at the ends of a sequence (see :func:`snippet_indices`)."""
    k = seq_length // 2
    return [min(max(i, 0), num_frames - 1) for i in range(t - k, t + k + 1)]


def next_source_position(seq_length: int) -> int:
    """Position of frame t + 1 among the sources of :func:`snippet_indices` (0-based)."""
    return seq_length // 2


def snippet_frames(frames: Sequence[ImageLike], seq_length: int) -> list[ImageLike]:
    """A full snippet (``seq_length`` frames, target in the middle), or a pair [t, t+1] padded
    as at a sequence start (:func:`snippet_indices`)."""
    L = seq_length
    if isinstance(frames, np.ndarray) and frames.ndim == 4:
        frames = list(frames)
    if not isinstance(frames, (list, tuple)):
        raise InputError(
            None,
            f"expected a list of frames, got {type(frames).__name__}",
            f"pass {L} consecutive frames (target in the middle) or a pair [t, t+1]",
        )
    if len(frames) == L:
        return list(frames)
    if len(frames) == 2:
        return [frames[i] for i in sorted(snippet_indices(0, 2, L))]
    raise InputError(
        None,
        f"got {len(frames)} frames; this model takes snippets of {L} (target in the middle) or a pair [t, t+1]",
        "pass consecutive frames of one video",
    )


def load_snippet(
    spec: InputSpec, frames: Sequence[ImageLike], camera: Intrinsics | None, timer: StageTimer
) -> tuple[np.ndarray, Camera | None, tuple[int, int]]:
    """One snippet (or pair) -> (network inputs (L, 3, h, w), camera at the frames' size, size (H, W)).

    The frames must share one size.
    """
    frames = snippet_frames(frames, spec.seq_length)
    rgbs, names = zip(*[read_frame(f, timer, i) for i, f in enumerate(frames)])
    sizes = {r.shape[:2] for r in rgbs}
    if len(sizes) > 1:
        detail = ", ".join(f"{n}: {r.shape[1]}x{r.shape[0]}" for n, r in zip(names, rgbs))
        raise InputError(
            None, f"frames of one snippet differ in size ({detail})", "pass consecutive frames of one camera"
        )
    size = rgbs[0].shape[:2]
    cam = camera_at(camera, size)
    return np.stack([to_network(spec, r, cam, timer) for r in rgbs]), cam, size


# ----------------------------------------------------------------------------- graph inputs
# ResFlowNet's input, in channel order: (part, channels). Training (training/model.py) stacks the
# same parts in the same order, so the exported graph and this runtime cannot disagree.
RESFLOW_INPUT = (("target", 3), ("source", 3), ("warped", 3), ("rigid_flow", 2), ("error", 1))


def resflow_input(parts: dict[str, np.ndarray]) -> np.ndarray:
    """The (B, 12, h, w) ResFlowNet input from its :data:`RESFLOW_INPUT` parts, each (B, C, h, w).

    A part missing from ``parts`` is zeros: one the ResFlowNet graph does not read, so the rigid-flow
    op did not make it (:meth:`geonet_infer.core.graphs.GraphSet._skip_unread_rigid_outputs`)."""
    B, _, h, w = parts["target"].shape
    return np.concatenate(
        [parts[name] if name in parts else np.zeros((B, c, h, w), np.float32) for name, c in RESFLOW_INPUT], axis=1
    )


def resflow_channels() -> dict[str, range]:
    """The channels of the ResFlowNet input each :data:`RESFLOW_INPUT` part fills."""
    channels, first = {}, 0
    for name, count in RESFLOW_INPUT:
        channels[name] = range(first, first + count)
        first += count
    return channels


def posenet_order(target: int, seq_length: int) -> list[int]:
    """Snippet positions in PoseNet's input order for a snippet in temporal order whose target
    sits at ``target``: [target] + the sources in temporal order (as :func:`snippet_indices`)."""
    return [target] + [i for i in range(seq_length) if i != target]

"""Snippets that teach the nets a stop: still, slowed and time-reversed copies of real snippets (issue 53).

Every clip the bundled model had trained on was a highway at speed, so its PoseNet learnt one forward
step whatever the frames showed. ``training.prepare --motion-mix static=0.3,stride2=0.3,reverse=0.3``
adds, for each target frame and with the given probability (seeded per sample), one more sample of
each variant beside the normal stride-1 snippet:

* ``static``  -- the target frame repeated ``seq_length`` times; each source copy gets the photometric
  noise and the sub-pixel jitter of a camera standing still with its engine running
  (:data:`STATIC_NOISE_LEVELS`, :data:`STATIC_JITTER_PX`). Labels, whatever the dataset's teachers:
  zero flow (valid everywhere) and the identity motion to every source.
* ``stride2`` -- frames t-2, t, t+2: twice the speed. ``stride0`` would be ``static``, stride 1 is the
  normal snippet, so the three strides of the issue are all there.
* ``reverse`` -- the stride-1 window in reverse temporal order (a camera backing up; a target whose
  "next" frame is its previous one). Teachers and true poses label it like any snippet: the labels
  follow the window's order.

A variant's sample is ``<frame>_<variant>`` beside ``<frame>`` in the same folder, so train.txt lists
it like any other.
"""

from __future__ import annotations

import zlib

import cv2
import numpy as np

VARIANTS = ("static", "stride2", "reverse")
STATIC_NOISE_LEVELS = 2.0  # std of the Gaussian noise added to each still copy, levels of 255
STATIC_JITTER_PX = 0.25  # largest shift of a still copy, pixels at H x W (a vibrating mount); labelled 0


def parse_motion_mix(text: str | None) -> dict[str, float]:
    """``"static=0.3,reverse=0.2"`` -> {"static": 0.3, "reverse": 0.2}; ValueError names the bad part."""
    mix: dict[str, float] = {}
    for part in filter(None, (text or "").split(",")):
        name, sep, value = part.partition("=")
        name = name.strip()
        if not sep or name not in VARIANTS:
            raise ValueError(f"{part!r}: expected VARIANT=PROBABILITY with VARIANT one of {', '.join(VARIANTS)}")
        try:
            p = float(value)
        except ValueError:
            raise ValueError(f"{part!r}: {value!r} is not a number") from None
        if not 0.0 <= p <= 1.0:
            raise ValueError(f"{part!r}: the probability must lie in [0, 1]")
        mix[name] = p
    return mix


def chosen(name: str, variant: str, probability: float, seed: int) -> bool:
    """Whether sample ``name`` gets ``variant``: a draw seeded by the name, so re-runs agree."""
    rng = np.random.default_rng([seed, zlib.crc32(f"{name} {variant}".encode())])
    return bool(rng.random() < probability)


def variant_window(run: list, i: int, half: int, variant: str) -> tuple | None:
    """The frames of ``variant``'s snippet around ``run[i]`` in temporal order, or None where the run
    is too short for it (stride 2 near the ends)."""
    if variant == "static":
        return (run[i],) * (2 * half + 1)
    if variant == "stride2":
        lo, hi = i - 2 * half, i + 2 * half
        return tuple(run[lo : hi + 1 : 2]) if lo >= 0 and hi < len(run) else None
    if variant == "reverse":
        return tuple(run[i - half : i + half + 1])[::-1]
    raise ValueError(f"unknown variant {variant!r}")


def still_copy(frame: np.ndarray, name: str, k: int) -> np.ndarray:
    """One still camera's copy of ``frame`` (H, W, 3) uint8: a sub-pixel shift of at most
    :data:`STATIC_JITTER_PX` and Gaussian noise of :data:`STATIC_NOISE_LEVELS`, seeded by the sample
    name and the copy's index ``k``."""
    rng = np.random.default_rng([zlib.crc32(name.encode()), k])
    dx, dy = rng.uniform(-STATIC_JITTER_PX, STATIC_JITTER_PX, size=2)
    h, w = frame.shape[:2]
    shifted = cv2.warpAffine(
        frame, np.float32([[1, 0, dx], [0, 1, dy]]), (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT
    )
    noisy = shifted.astype(np.float32) + rng.normal(0.0, STATIC_NOISE_LEVELS, size=shifted.shape)
    return np.clip(np.rint(noisy), 0, 255).astype(np.uint8)


def static_labels(n_sources: int, height: int, width: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A still camera's labels: zero flow (H, W, 2), valid everywhere (H, W), identity motions (N, 4, 4)."""
    return (
        np.zeros((height, width, 2), np.float32),
        np.ones((height, width), bool),
        np.tile(np.eye(4), (n_sources, 1, 1)),
    )

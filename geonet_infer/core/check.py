"""A check of every flow output, made from the frames themselves: no ground truth needed.

For a pair t -> t+1 the next frame is warped back onto frame t by a flow (``cv2.remap``,
bilinear; its positions rounded to 1/32 px, far below what a grey-level check resolves). The
error of a flow is the mean absolute grey-level difference (0-255, grey as
``cv2.COLOR_RGB2GRAY``) between the warped next frame and frame t, over the pixels every flow
checked keeps in view (a pixel whose flow leaves the image, or is not finite, is left out).
The trivial answer, no motion, is the next frame as it is, scored over the same pixels. A flow
*explains* the pair when its error is below the no-motion error; a tie (zero flow) does not.
Three questions per pair:

* the full flow against no motion (does the flow move the right things?);
* the rigid flow (the static scene from depth and pose) against no motion: depth and pose
  judged together;
* how far the full flow and the rigid flow agree: median and p95 of |flow - rigid| in input
  pixels, and the fraction of pixels within :data:`AGREE_PX`.

The check is a function of the frames and the flows only (:func:`check_pair`), so it judges
any flow source. The runtime runs it at the networks' size on the frames as the networks saw
them (undistorted, resized), where it costs about 2 ms a pair (docs/runtime.md, "The output
check").
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, fields
from functools import lru_cache

import cv2
import numpy as np

__all__ = ["AGREE_PX", "GREY_WEIGHTS", "METHOD", "FrameCheck", "SequenceCheck", "check_pair"]

AGREE_PX = 3.0  # |flow - rigid| within this many input pixels counts as agreeing (KITTI's outlier bound)
GREY_WEIGHTS = (0.299, 0.587, 0.114)  # R, G, B: cv2.COLOR_RGB2GRAY's
METHOD = (
    "mean absolute grey-level difference (0-255) between frame t and frame t+1 warped back by the flow "
    "(bilinear), over the pixels every checked flow keeps in view; no motion = frame t+1 as it is"
)


@dataclass(frozen=True)
class FrameCheck:
    """The check of one pair t -> t+1 (:func:`check_pair`).

    Attributes:
        still_error: mean |frame t+1 - frame t| in grey levels (0-255): no motion's error.
        flow_error: the same with frame t+1 warped back by the full flow.
        rigid_error: the same for the rigid flow (depth + pose); None when no rigid flow was
            checked (a flow that has no rigid part).
        in_view: fraction of frame t's pixels scored (every checked flow keeps them in view).
        flow_rigid_median_px, flow_rigid_p95_px: median and 95th percentile of |flow - rigid|
            in input pixels (None without a rigid flow).
        flow_rigid_within: fraction of pixels where |flow - rigid| <= :data:`AGREE_PX` input pixels.
    """

    still_error: float
    flow_error: float
    in_view: float
    rigid_error: float | None = None
    flow_rigid_median_px: float | None = None
    flow_rigid_p95_px: float | None = None
    flow_rigid_within: float | None = None

    @property
    def flow_explains(self) -> bool:
        """The flow explains the next frame better than no motion (False for a tie or nothing in view)."""
        return bool(self.flow_error < self.still_error)

    @property
    def rigid_explains(self) -> bool | None:
        """:attr:`flow_explains` for the rigid flow; None without one."""
        return None if self.rigid_error is None else bool(self.rigid_error < self.still_error)

    def as_dict(self) -> dict:
        """JSON-ready: values rounded to 3 decimals, NaN (nothing in view) as None."""
        return {
            "still_error": _round(self.still_error),
            "flow_error": _round(self.flow_error),
            "flow_explains": self.flow_explains,
            "rigid_error": _round(self.rigid_error),
            "rigid_explains": self.rigid_explains,
            "in_view": _round(self.in_view),
            "flow_rigid_median_px": _round(self.flow_rigid_median_px),
            "flow_rigid_p95_px": _round(self.flow_rigid_p95_px),
            "flow_rigid_within": _round(self.flow_rigid_within),
        }


@dataclass(frozen=True)
class SequenceCheck:
    """The checks of a sequence's pairs summed up (:meth:`from_checks`).

    Attributes:
        pairs: pairs checked.
        flow_no_better: pairs whose flow explains the next frame no better than no motion.
        rigid_no_better: the same for the rigid flow; None when no pair had one.
        median_still_error, median_flow_error, median_rigid_error: medians over the pairs (grey levels).
        median_flow_rigid_px: median over the pairs of each pair's median |flow - rigid| (input px).
        median_flow_rigid_within: median over the pairs of the fraction within :data:`AGREE_PX`.
    """

    pairs: int
    flow_no_better: int
    rigid_no_better: int | None
    median_still_error: float | None
    median_flow_error: float | None
    median_rigid_error: float | None
    median_flow_rigid_px: float | None
    median_flow_rigid_within: float | None

    @classmethod
    def from_checks(cls, checks: Iterable[FrameCheck]) -> SequenceCheck:
        checks = list(checks)
        rigid = [c for c in checks if c.rigid_error is not None]
        return cls(
            pairs=len(checks),
            flow_no_better=sum(not c.flow_explains for c in checks),
            rigid_no_better=sum(not c.rigid_explains for c in rigid) if rigid else None,
            median_still_error=_median([c.still_error for c in checks]),
            median_flow_error=_median([c.flow_error for c in checks]),
            median_rigid_error=_median([c.rigid_error for c in rigid]),
            median_flow_rigid_px=_median([c.flow_rigid_median_px for c in rigid]),
            median_flow_rigid_within=_median([c.flow_rigid_within for c in rigid]),
        )

    @classmethod
    def from_dict(cls, data: dict) -> SequenceCheck:
        """Back from :meth:`as_dict` (summary.json's "check")."""
        return cls(**{f.name: data[f.name] for f in fields(cls)})

    @property
    def trivial_wins(self) -> bool:
        """No motion explains the frames as well as the flow (or the rigid flow) on most pairs."""
        worst = max(self.flow_no_better, self.rigid_no_better or 0)
        return self.pairs > 0 and worst > self.pairs / 2

    def line(self) -> str:
        """One sentence for a closing line, e.g. 'flow explains the next frame no better than no
        motion on 70 of 77 pairs; the rigid flow (depth + pose) on 60; ...'."""
        if not self.pairs:
            return "no pair of frames with flow to check"
        text = f"flow explains the next frame no better than no motion on {self.flow_no_better} of {self.pairs} pairs"
        if self.rigid_no_better is not None:
            text += f"; the rigid flow (depth + pose) on {self.rigid_no_better}"
        if self.median_flow_rigid_within is not None:
            text += (
                f"; flow and rigid flow agree within {AGREE_PX:g} px on {self.median_flow_rigid_within:.0%} of pixels"
            )
            text += " (median pair)"
        return text

    def warning(self) -> str | None:
        """A one-line warning when no motion does as well as the model on most pairs, else None."""
        if not self.trivial_wins:
            return None
        which = [
            name
            for name, bad in (("flow", self.flow_no_better), ("rigid flow (depth + pose)", self.rigid_no_better or 0))
            if bad > self.pairs / 2
        ]
        return (
            f"on most of this footage the {' and the '.join(which)} explain{'s' if len(which) == 1 else ''} the "
            f"next frame no better than no motion at all: do not trust {'them' if len(which) > 1 else 'it'} here "
            "(summary.json 'check'; docs/runtime.md, 'The output check')"
        )

    def as_dict(self) -> dict:
        return {
            "pairs": self.pairs,
            "flow_no_better": self.flow_no_better,
            "rigid_no_better": self.rigid_no_better,
            "median_still_error": _round(self.median_still_error),
            "median_flow_error": _round(self.median_flow_error),
            "median_rigid_error": _round(self.median_rigid_error),
            "median_flow_rigid_px": _round(self.median_flow_rigid_px),
            "median_flow_rigid_within": _round(self.median_flow_rigid_within),
            "trivial_wins": self.trivial_wins,
        }


def check_pair(
    image: np.ndarray,
    next_image: np.ndarray,
    flow: np.ndarray,
    rigid_flow: np.ndarray | None = None,
    *,
    size: tuple[int, int] | None = None,
    units: tuple[float, float] = (1.0, 1.0),
) -> FrameCheck:
    """Check the flow (and the rigid flow) of one pair against no motion (module docstring).

    Args:
        image, next_image: frames t and t+1, (H, W, 3) RGB or (H, W) grey, grey levels 0-255
            (uint8 or float).
        flow: (H, W, 2) flow t -> t+1 in pixels of these arrays.
        rigid_flow: (H, W, 2) its rigid part, or None.
        size: (h, w) to check at, smaller is cheaper (frames resized with ``cv2.INTER_AREA``,
            flows bilinearly and scaled per axis); None: as given.
        units: input pixels per pixel of these arrays (u, v), for |flow - rigid| (the runtime checks
            at the network size and reports input pixels).
    """
    a, b = _grey(image), _grey(next_image)
    flows = [np.asarray(flow, np.float32)] + ([] if rigid_flow is None else [np.asarray(rigid_flow, np.float32)])
    for name, f in zip(("flow", "rigid_flow"), flows):
        if f.shape != a.shape + (2,) or b.shape != a.shape:
            raise ValueError(f"{name} {f.shape} and the frames {a.shape}, {b.shape} must be (H, W, 2) and (H, W)")
    if size is not None and tuple(size) != a.shape:
        h, w = size
        sx, sy = w / a.shape[1], h / a.shape[0]
        a, b = (cv2.resize(x, (w, h), interpolation=cv2.INTER_AREA) for x in (a, b))
        flows = [cv2.resize(f, (w, h), interpolation=cv2.INTER_LINEAR) * np.array([sx, sy], np.float32) for f in flows]
        units = (units[0] / sx, units[1] / sy)
    H, W = a.shape
    maps = [_pixel_grid(H, W) + f for f in flows]
    keep = np.ones((H, W), bool)
    for m in maps:  # in view: the sampled position lies in the image (NaN compares False); one set for all
        keep &= (m[..., 0] >= 0) & (m[..., 0] <= W - 1) & (m[..., 1] >= 0) & (m[..., 1] <= H - 1)
    warped = [cv2.remap(b, m, None, cv2.INTER_LINEAR, None, cv2.BORDER_REPLICATE) for m in maps]
    still, flow_error, *rigid_error = (_mean_abs(x, a, keep) for x in (b, *warped))
    if rigid_flow is None:
        return FrameCheck(still_error=still, flow_error=flow_error, in_view=float(keep.mean()))
    du, dv = ((flows[0][..., i] - flows[1][..., i]) * np.float32(units[i]) for i in (0, 1))
    distance = cv2.magnitude(du, dv)
    distance = distance[np.isfinite(distance)]
    median, p95 = np.percentile(distance, [50, 95]) if distance.size else (math.nan, math.nan)
    return FrameCheck(
        still_error=still,
        flow_error=flow_error,
        in_view=float(keep.mean()),
        rigid_error=rigid_error[0],
        flow_rigid_median_px=float(median),
        flow_rigid_p95_px=float(p95),
        flow_rigid_within=float(np.mean(distance <= AGREE_PX)) if distance.size else math.nan,
    )


def _grey(image: np.ndarray) -> np.ndarray:
    x = np.asarray(image)
    if x.ndim == 3 and x.shape[2] == 3:
        x = cv2.cvtColor(np.ascontiguousarray(x, np.float32), cv2.COLOR_RGB2GRAY)
    if x.ndim != 2:
        raise ValueError(f"a frame must be (H, W, 3) RGB or (H, W) grey, got shape {x.shape}")
    return np.ascontiguousarray(x, np.float32)


@lru_cache(maxsize=8)
def _pixel_grid(height: int, width: int) -> np.ndarray:
    """(H, W, 2) float32 pixel positions (u, v): a flow added to it is a ``cv2.remap`` map."""
    u, v = np.meshgrid(np.arange(width, dtype=np.float32), np.arange(height, dtype=np.float32))
    grid = np.stack([u, v], axis=-1)
    grid.setflags(write=False)
    return grid


def _mean_abs(x: np.ndarray, y: np.ndarray, keep: np.ndarray) -> float:
    if not keep.any():
        return math.nan
    return float(np.abs(x[keep] - y[keep]).mean())


def _median(values: Sequence[float | None]) -> float | None:
    finite = [v for v in values if v is not None and math.isfinite(v)]
    return float(np.median(finite)) if finite else None


def _round(value: float | None) -> float | None:
    return None if value is None or not math.isfinite(value) else round(float(value), 3)

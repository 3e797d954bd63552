"""Visualisation: Middlebury flow colours, depth colour maps and side-by-side panels (uint8 RGB)."""

from __future__ import annotations

import re

import cv2
import numpy as np

from geonet_infer.limits import MAX_COLOUR_SCALE_FRAMES

__all__ = ["flow_to_color", "depth_to_color", "side_by_side", "SteadyScale", "inverse_depth_range", "flow_range"]


def _make_color_wheel() -> np.ndarray:
    """Middlebury colour wheel (Baker et al. 2011): (55, 3) float RGB in [0, 255]."""
    RY, YG, GC, CB, BM, MR = 15, 6, 4, 11, 13, 6
    segments = []
    for n, start, ch_up, ch_down in (
        (RY, (255, 0, 0), 1, None),
        (YG, (255, 255, 0), None, 0),
        (GC, (0, 255, 0), 2, None),
        (CB, (0, 255, 255), None, 1),
        (BM, (0, 0, 255), 0, None),
        (MR, (255, 0, 255), None, 2),
    ):
        seg = np.tile(np.array(start, dtype=np.float64), (n, 1))
        ramp = np.floor(255 * np.arange(n) / n)
        if ch_up is not None:
            seg[:, ch_up] = ramp
        else:
            seg[:, ch_down] = 255 - ramp
        segments.append(seg)
    return np.concatenate(segments)


_COLOR_WHEEL = _make_color_wheel()
_WHEEL01_PLANES = np.ascontiguousarray((_COLOR_WHEEL / 255).astype(np.float32).T)  # (3, 55): R, G, B


def flow_to_color(flow: np.ndarray, max_flow: float | None = None, valid: np.ndarray | None = None) -> np.ndarray:
    """Middlebury colour coding of flow: hue = direction, saturation = magnitude.

    Same wheel as the Middlebury/KITTI visualisations (Baker et al., ``flowToColor``):
    +x (right) is red, -x cyan, +y (down) orange-yellow, -y blue-violet.

    Args:
        flow: (H, W, 2) float px.
        max_flow: magnitude shown at full saturation; None = max over valid pixels.
        valid: (H, W) bool; invalid pixels are drawn black.
    Returns:
        (H, W, 3) uint8 RGB.
    """
    # float32 for the angle and magnitude, float64 where the wheel is interpolated (the
    # promotion plain numpy gives: int32 - float32). Written plane by plane with ``out=``
    # buffers, a band of rows at a time: the same arithmetic as an (H, W, 3) broadcast, bytes
    # identical, several times faster.
    flow = np.asarray(flow, dtype=np.float32)
    u, v = flow[..., 0], flow[..., 1]
    ok = np.isfinite(u) & np.isfinite(v)
    if valid is not None:
        ok &= np.asarray(valid, dtype=bool)
    zero = np.float32(0)
    u = np.where(ok, u, zero)  # fresh float32 planes, modified in place below
    v = np.where(ok, v, zero)
    rad = np.hypot(u, v)
    everywhere = bool(ok.all())  # the usual case: no boolean indexing (slow on full frames)
    if max_flow is None:
        max_flow = float(rad.max() if everywhere else rad[ok].max()) if ok.any() else 0.0
    scale = np.float32(1.0 / max(max_flow, 1e-9))
    u *= scale
    v *= scale
    rad *= scale
    img = np.empty(flow.shape[:2] + (3,), np.uint8)
    rows = max(1, _CHUNK_PIXELS // max(flow.shape[1], 1))
    for r0 in range(0, flow.shape[0], rows):
        band = slice(r0, r0 + rows)
        _wheel_colours(u[band], v[band], rad[band], img[band])
    if not everywhere:
        img[~ok] = 0
    return img


_CHUNK_PIXELS = 16384  # a band of rows whose float64 planes stay in the CPU's L2 cache


def _wheel_colours(u: np.ndarray, v: np.ndarray, rad: np.ndarray, img: np.ndarray) -> None:
    """Colours of scaled flow (u, v, rad: float32, overwritten) into ``img`` (..., 3) uint8."""
    ncols = len(_COLOR_WHEEL)
    fk = np.arctan2(np.negative(v, out=v), np.negative(u, out=u), out=u)
    fk /= np.float32(np.pi)
    fk += 1
    fk *= np.float32((ncols - 1) / 2)
    k0 = fk.astype(np.intp)  # fk >= 0: truncation is floor; intp: what np.take indexes with
    k1 = k0 + 1
    k1[k1 == ncols] = 0
    f = fk - k0  # float64
    g = 1 - f
    rad64 = rad.astype(np.float64)  # converted once, not once per channel
    dark = rad > 1  # beyond max_flow the colour darkens; below, saturation grows with magnitude
    col = np.empty_like(f)
    other = np.empty_like(f)
    for c in range(3):
        np.multiply(g, np.take(_WHEEL01_PLANES[c], k0), out=col)
        col += np.multiply(f, np.take(_WHEEL01_PLANES[c], k1), out=other)
        np.multiply(col, np.float32(0.75), out=other)
        np.subtract(1, col, out=col)
        col *= rad64
        np.subtract(1, col, out=col)
        np.copyto(col, other, where=dark)
        col *= 255
        img[..., c] = col  # col >= 0: the cast truncates, i.e. floors


def depth_to_color(
    depth_or_disp: np.ndarray, is_disparity: bool = False, vmax: float | None = None, colormap: int = cv2.COLORMAP_MAGMA
) -> np.ndarray:
    """Colour a depth (or disparity) map like monodepth/GeoNet figures: near = bright.

    Depth is converted to inverse depth, normalised by its 95th percentile (or
    ``vmax`` in inverse-depth units) and mapped with an OpenCV colormap (magma).

    Args:
        depth_or_disp: (H, W) float; depth in metres (0/non-finite = none) or disparity.
        is_disparity: True if the input already is inverse depth / disparity.
        vmax: value (inverse depth) at the top of the colormap; None = 95th percentile.
    Returns:
        (H, W, 3) uint8 RGB; pixels without depth are black.
    """
    x = np.asarray(depth_or_disp, dtype=np.float64)
    ok = np.isfinite(x) & (x > 0)
    everywhere = bool(ok.all())  # the usual case: no boolean indexing (slow on full frames)
    inv = np.zeros_like(x)
    if is_disparity:
        np.copyto(inv, x, where=ok)
    else:
        np.divide(1.0, x, out=inv, where=ok)
    if vmax is None:
        vmax = float(np.percentile(inv if everywhere else inv[ok], 95)) if ok.any() else 1.0
    inv /= max(vmax, 1e-12)  # in place: each full-frame float64 temporary costs page faults
    np.clip(inv, 0, 1, out=inv)
    inv *= 255
    bgr = cv2.applyColorMap(inv.astype(np.uint8), colormap)
    if not everywhere:
        bgr[~ok] = 0
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def side_by_side(
    panels: list[np.ndarray], labels: list[str] | None = None, height: int | None = None, gap: int = 4
) -> np.ndarray:
    """Panels resized to one height and placed left to right, optionally labelled.

    Args:
        panels: (H_i, W_i, 3) uint8 RGB images (an (H, W) grey panel is expanded to 3 channels).
        labels: one caption per panel, drawn in white on a dark strip above it; None = no strip.
        height: common panel height in px; None = the height of the first panel. Each panel keeps
            its aspect ratio (cv2.INTER_AREA).
        gap: dark columns between panels.
    Returns:
        (strip + height, sum of widths + gaps, 3) uint8 RGB.
    """
    if not panels:
        raise ValueError("side_by_side needs at least one panel")
    if labels is not None and len(labels) != len(panels):
        raise ValueError(f"{len(labels)} labels for {len(panels)} panels")
    imgs = []
    for i, p in enumerate(panels):
        p = np.asarray(p)
        if p.dtype != np.uint8:
            raise ValueError(f"panel {i} must be uint8, got {p.dtype}")
        if p.ndim == 2:
            p = np.repeat(p[..., None], 3, axis=2)
        if p.ndim != 3 or p.shape[2] != 3:
            raise ValueError(f"panel {i} must be (H, W, 3) RGB, got shape {p.shape}")
        imgs.append(p)
    h = int(height) if height is not None else imgs[0].shape[0]
    if h <= 0:
        raise ValueError(f"height must be positive, got {h}")
    resized = []
    for p in imgs:
        w = max(1, round(p.shape[1] * h / p.shape[0]))
        resized.append(p if p.shape[:2] == (h, w) else cv2.resize(p, (w, h), interpolation=cv2.INTER_AREA))
    strip_h = 0
    font, thickness = cv2.FONT_HERSHEY_SIMPLEX, 1
    scale = max(0.35, min(1.0, h / 400))
    if labels is not None:
        (_, text_h), baseline = cv2.getTextSize("Ag", font, scale, thickness)
        strip_h = text_h + baseline + 8
    total_w = sum(p.shape[1] for p in resized) + gap * (len(resized) - 1)
    out = np.full((strip_h + h, total_w, 3), 24, np.uint8)  # dark strip and gaps
    x = 0
    for i, p in enumerate(resized):
        out[strip_h:, x : x + p.shape[1]] = p
        if labels is not None and labels[i]:
            canvas = np.ascontiguousarray(out[:strip_h, x : x + p.shape[1]])
            cv2.putText(
                canvas,
                str(labels[i]),
                (4, strip_h - baseline - 4),
                font,
                scale,
                (255, 255, 255),
                thickness,
                cv2.LINE_AA,
            )
            out[:strip_h, x : x + p.shape[1]] = canvas
        x += p.shape[1] + gap
    return out


def inverse_depth_range(depth: np.ndarray) -> float | None:
    """The top of :func:`depth_to_color`'s default scale: the 95th percentile of inverse depth over
    pixels with depth (None: no such pixel)."""
    x = np.asarray(depth, dtype=np.float64)
    ok = np.isfinite(x) & (x > 0)
    return float(np.percentile(1.0 / x[ok], 95)) if ok.any() else None


def flow_range(flow: np.ndarray) -> float | None:
    """The top of :func:`flow_to_color`'s default scale: the largest finite flow magnitude."""
    f = np.asarray(flow, dtype=np.float32)
    mag = np.hypot(f[..., 0], f[..., 1])
    mag = mag[np.isfinite(mag)]
    return float(mag.max()) if mag.size else None


COLOUR_SCALES = ("first:N", "running", "frame")


class SteadyScale:
    """One colour scale for the frames of a video, so a still scene keeps its colours.

    ``mode``: "first:N" (default "first:8") fixes the depth and flow scales at the median of the
    first N frames' own ranges (:func:`inverse_depth_range`, :func:`flow_range`); "running" uses the
    median of every frame seen so far (it settles, it does not flicker); "frame" gives each frame its
    own range (the pictures of single images). Feed each frame to :meth:`observe` in order;
    :meth:`scales` is (inverse-depth max, flow max) for ``depth_to_color(vmax=)`` /
    ``flow_to_color(max_flow=)``, None meaning the frame's own.
    """

    def __init__(self, mode: str = "first:8"):
        self.mode, self.first_n = _parse_colour_scale(mode)
        self._depth: list[float] = []
        self._flow: list[float] = []
        self._seen = 0
        self._fixed: tuple[float | None, float | None] | None = None

    @property
    def ready(self) -> bool:
        """Whether :meth:`scales` is final for the frames observed so far ("first:N": N seen)."""
        return self.mode != "first" or self._fixed is not None

    def observe(self, depth: np.ndarray | None, flow: np.ndarray | None) -> None:
        if self.mode == "frame" or self._fixed is not None:
            return
        if depth is not None and (value := inverse_depth_range(depth)) is not None:
            self._depth.append(value)
        if flow is not None and (value := flow_range(flow)) is not None:
            self._flow.append(value)
        self._seen += 1
        if self.mode == "first" and self._seen >= self.first_n:
            self.finish()

    def finish(self) -> None:
        """The input ended (or memory holds no more frames): "first:N" fixes its scale from the frames it got."""
        if self.mode == "first" and self._fixed is None:
            self._fixed = self._medians()

    def scales(self) -> tuple[float | None, float | None]:
        if self.mode == "frame":
            return None, None
        return self._fixed if self._fixed is not None else self._medians()

    def _medians(self) -> tuple[float | None, float | None]:
        return tuple(float(np.median(v)) if v else None for v in (self._depth, self._flow))  # type: ignore[return-value]

    def describe(self) -> dict:
        depth, flow = self.scales()
        return {
            "mode": self.mode if self.mode != "first" else f"first:{self.first_n}",
            "frames": self._seen,  # whose ranges made the scale: first:N of huge frames may stop early
            "inverse_depth_max": depth,
            "flow_max_px": flow,
        }


def _parse_colour_scale(text: str) -> tuple[str, int]:
    if text in ("frame", "running"):
        return text, 0
    head, _, n = str(text).partition(":")
    # ASCII digits only: str.isdigit() also takes '²', which int() refuses
    if head == "first" and re.fullmatch(r"[0-9]+", n) and 1 <= int(n) <= MAX_COLOUR_SCALE_FRAMES:
        return "first", int(n)
    raise ValueError(
        f"colour scale {text!r}: expected first:N (N from 1 to {MAX_COLOUR_SCALE_FRAMES}), running or frame"
    )

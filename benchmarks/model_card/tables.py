"""The model card's tables: depth, flow and pose blocks, the camera-height text, before / after."""

from __future__ import annotations

import operator
import re
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

from benchmarks.markdown import sig3
from benchmarks.markdown import table as _table
from benchmarks.model_card.measure import (
    DEPTH_HEADERS,
    PRECISION_LABEL,
    ROW_LABEL,
    SYNTH_DEPTH_TARGET,
    _flatten,
)
from geonet_infer.eval import metrics


# ----------------------------------------------------------------------------- card
def _data_synth(result: dict) -> str:
    s = result["synthetic"]
    cfg = s.get("synth_config") or {}
    size = f", {cfg['height']}×{cfg['width']}" if "height" in cfg and "width" in cfg else ""
    return f"`{Path(s['synth_dir']).name}` held-out ({len(s['sequences'])} seq{size})"


def _frame_span(frames: list[str]) -> str:
    """The frames as a range: 0–9 for numbered frames, else the first and the last name."""
    if len(frames) == 1:
        return frames[0]
    return f"{int(frames[0])}–{int(frames[-1])}" if all(f.isdigit() for f in frames) else f"{frames[0]}…{frames[-1]}"


def _data_kitti(result: dict) -> str:
    k = result["kitti"]
    frames = k["frames"]
    pf = k["depth"]["per_frame"][0]
    return (
        f"KITTI raw `{Path(k['dir']).name}`, frames {_frame_span(frames)} ({len(frames)}, {pf['width']}×{pf['height']})"
    )


def _camera_height_label(p: str, camera_height: float) -> str:
    return f"{PRECISION_LABEL[p]}, scaled by camera height {camera_height:g} m (no median scaling)"


def _depth_table(block: dict, data: str, count_key: str) -> list[str]:
    """Median-scaled rows; with a ``camera_height`` block, each precision's camera-height row beside it."""
    rows = []
    by_height = block.get("camera_height")
    for key in ("fp32", "int8", "constant_baseline"):
        if key not in block:
            continue
        rows.append(
            [ROW_LABEL[key], data] + [sig3(block[key][c]) for c in metrics.DEPTH_KEYS] + [sig3(block[key]["count"])]
        )
        if by_height and key in by_height:
            means, failed = by_height[key], by_height[f"{key}_ground_fit_failed"]
            scored = block["frames"] - len(failed)
            count = f"{scored} of {block['frames']}" + (f", ground fit failed on {len(failed)}" if failed else "")
            rows.append(
                [_camera_height_label(key, by_height["camera_height_m"]), data]
                + [sig3(means[c] if means else None) for c in metrics.DEPTH_KEYS]
                + [count]
            )
    return _table(["predictor", "data"] + list(DEPTH_HEADERS) + [count_key], rows)


def _camera_height_text(block: dict) -> list[str]:
    """What the camera-height rows did, with every frame whose ground fit failed."""
    h = block["camera_height"]
    out = [
        f"Scaled by camera height: per frame, a ground plane is fitted to the predicted depth "
        "(`geonet_infer.core.scale.fit_ground_plane`: RANSAC on the image below the horizon, normal within 20° of "
        "the camera's down axis, at least 10 % of the points within 2 % of the plane's distance; a plane with "
        "over 3 % of the points more than 30 % beyond it along their rays is skipped, as a car top the road is "
        f"seen beside) and the depth is multiplied so that the plane lies {h['camera_height_m']:g} m below the "
        "camera (KITTI's colour cameras); the ground truth is not used "
        '(`evaluation.evaluate_depth(..., scaling="camera_height")`, '
        "`geonet-infer eval depth --camera-height`). A frame without such a plane is not scored and never "
        "median-scaled instead: the means cover the other frames."
    ]
    for p in ("fp32", "int8"):
        failed = h.get(f"{p}_ground_fit_failed")
        if failed:
            out.append(
                f"**{PRECISION_LABEL[p]}: no ground plane in {len(failed)} of {block['frames']} frames** "
                f"({', '.join(failed)})."
            )
    return [" ".join(out), ""]


def _floor_text(block: dict, before: dict | None) -> list[str]:
    """The depth-floor diagnostic of each precision (and of the previous model)."""

    def shares(b: dict) -> str:
        return ", ".join(f"{PRECISION_LABEL[p]} {sig3(b[p]['floor_share'])}" for p in ("fp32", "int8") if p in b)

    was = f"; before: {shares(before)}" if before else ""
    return [
        "Depth floor, without ground truth: the share of the lower image half in the fullest 0.2 %-wide "
        "bin of log depth, mean over these frames (`geonet_infer.eval.metrics.depth_floor_share`). A road "
        "scene's depth spreads to a few %; a near field predicted as one value (dead decoder features "
        f"leave the disparity head's bias) shows as a large share: {shares(block)}{was}.",
        "",
    ]


def _flow_table(block: dict, data: str) -> list[str]:
    rows = []
    for key in ("fp32", "int8", "zero_flow_baseline", "dis_medium_baseline"):
        if key not in block:
            continue
        b = block[key]
        rows.append(
            [
                ROW_LABEL[key],
                data,
                sig3(b["noc"]["epe"]),
                sig3(b["occ"]["epe"]),
                sig3(b["noc"]["fl"]),
                sig3(b["occ"]["fl"]),
                sig3(b["noc"]["count"]),
            ]
        )
    return _table(["predictor", "data", "EPE noc (px)", "EPE occ (px)", "Fl noc", "Fl occ", "pairs"], rows)


def _pose_table(block: dict, data: str) -> list[str]:
    rows = []
    for key in ("fp32", "int8", "identity_baseline", "orb_vo_baseline"):
        if key not in block:
            continue
        b = block[key]
        rows.append(
            [
                ROW_LABEL[key],
                data,
                f"{sig3(b['ate_snippet']['mean'])} ± {sig3(b['ate_snippet']['std'])}",
                f"{sig3(b['ate_rmse_true']['mean'])} ± {sig3(b['ate_rmse_true']['std'])}",
                sig3(b["count"]),
            ]
        )
    return _table(["predictor", "data", "ATE, paper (÷N) mean ± std", "ATE, true RMSE mean ± std", "snippets"], rows)


def _camera_height_limitation(block: dict) -> str:
    """How far metric depth from the camera height got on the KITTI frames (FP32)."""
    h = block["camera_height"]
    failed, n = len(h["fp32_ground_fit_failed"]), block["frames"]
    if failed == n:
        return (
            f"Metric depth from the camera height ({h['camera_height_m']:g} m) found no ground plane in any of the "
            f"{n} KITTI frames, so without ground truth this model gives depth in arbitrary units."
        )
    return (
        f"Metric depth from the camera height ({h['camera_height_m']:g} m) found a ground plane in {n - failed} of "
        f"{n} KITTI frames (AbsRel {sig3(h['fp32']['abs_rel'])} on those, without median scaling)."
    )


def _compare(model: float, baseline: float, lower_is_better: bool = True) -> str:
    better = model < baseline if lower_is_better else model > baseline
    return "better than" if better else ("equal to" if model == baseline else "worse than")


def _stage_origin(command: str | None) -> str | None:
    """Where the training run started: ``initialised from X`` (--init-checkpoint) or ``resumed from X`` (--resume)."""
    for flag, verb in (("--resume", "resumed from"), ("--init-checkpoint", "initialised from")):
        m = re.search(rf"{flag}[ =](\S+)", command or "")
        if m:
            return f"{verb} `{m.group(1)}`"
    return None


def _checkpoint_text(prov: dict) -> str:
    if prov.get("checkpoint") and prov.get("checkpoint_sha256"):
        return f"`{prov['checkpoint']}` (sha256 `{prov['checkpoint_sha256'][:12]}…`)"
    return "n/a"


class Headline(NamedTuple):
    """A row of the before/after table: one model number, the baseline it is judged by and the issue's target."""

    label: str
    where: str  # "synthetic" or "kitti"
    task: str
    metric: str  # key in the flattened block of one precision
    baseline: str  # key of the baseline's block
    baseline_name: str
    target: str
    meets: Callable[[float, float], bool]  # (model, baseline) -> the target is met


HEADLINES = (
    Headline(
        "real KITTI frames {frames} depth AbsRel",
        "kitti",
        "depth",
        "abs_rel",
        "constant_baseline",
        "constant",
        "below constant",
        operator.lt,
    ),
    Headline(
        "synthetic held-out depth AbsRel",
        "synthetic",
        "depth",
        "abs_rel",
        "constant_baseline",
        "constant",
        f"≤ {SYNTH_DEPTH_TARGET:g}",
        lambda model, _: model <= SYNTH_DEPTH_TARGET,
    ),
    Headline(
        "synthetic flow EPE-noc (px)",
        "synthetic",
        "flow",
        "noc.epe",
        "dis_medium_baseline",
        "DIS medium",
        "below DIS medium",
        operator.lt,
    ),
    Headline(
        "synthetic pose ATE (paper ÷N, mean)",
        "synthetic",
        "pose",
        "ate_snippet.mean",
        "orb_vo_baseline",
        "ORB-VO",
        "below ORB-VO",
        operator.lt,
    ),
)


def _headline(side: dict, h: Headline, precision: str) -> float | None:
    """``h``'s number of one side (the result or its "before" block); None if it has no such precision."""
    block = side[h.where][h.task]
    return _flatten(block[precision])[h.metric] if precision in block else None


def _side_text(label: str, model: dict) -> str:
    random = "; random-init weights" if model["random_init"] else ""
    return f"{label} `{model['dir']}` (checkpoint {_checkpoint_text(model['provenance'])}{random})"


def _before_after(result: dict) -> list[str]:
    """Section "Before / after": the headline numbers of the previous model and this one, with baseline,
    target and verdict; nothing without ``--before``."""
    before = result.get("before")
    if not before:
        return []
    rows = []
    for h in HEADLINES:
        baseline = _flatten(result[h.where][h.task][h.baseline])[h.metric]
        meets = h.meets(_headline(result, h, "fp32"), baseline)
        rows.append(
            [h.label.format(frames=_frame_span(result["kitti"]["frames"]))]
            + [sig3(_headline(side, h, p)) for side in (before, result) for p in ("fp32", "int8")]
            + [f"{sig3(baseline)} ({h.baseline_name})", h.target, "yes" if meets else "no"]
        )
    headers = [
        "",
        "before FP32",
        "before INT8",
        "after FP32",
        "after INT8",
        "baseline",
        "target",
        "after meets target?",
    ]
    return [
        "## Before / after",
        "",
        *_table(headers, rows),
        "",
        f"{_side_text('Before:', before['model'])}; {_side_text('after:', result['model'])}. Both were measured "
        "in this one run, on the same data and through the same code; the baselines are the rows of the tables "
        'below. Lower is better in every row; "after meets target?" judges the after model\'s FP32 number.',
        "",
    ]

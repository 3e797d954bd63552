"""``geonet-infer report OUT``: one offline HTML page of a predict (or batch) output folder (issue 59).

For each sequence: the output check's errors per pair over time (flow, rigid flow, no motion), the
camera path from above, the frame / depth / flow of the best and the worst pairs, the stage table,
the intrinsics and where they came from, and what the model says of itself (its notice, the run's
warnings). It reads only what predict wrote (summary.json, poses_kitti.txt, the colour maps) and, where
it can still be opened, the input (for the frames' thumbnails).
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from geonet_infer.errors import InputError
from geonet_infer.output.html import Page, require_plotly
from geonet_infer.output.layout import SUMMARY_NAME

MAX_SEQUENCES = 12  # a batch folder: the first sequences get a section each (the page's size)
CHECK_SERIES = (("flow_error", "flow"), ("rigid_error", "rigid flow (depth + pose)"), ("still_error", "no motion"))


def read_summary(folder: Path) -> dict:
    """A predict run's summary.json, or an InputError naming what is wrong with the folder."""
    path = folder / SUMMARY_NAME
    if not folder.is_dir():
        raise InputError(folder, "not a folder", "pass a predict or batch --out folder, or a bench --json file")
    if not path.is_file():
        raise InputError(
            folder, f"not a predict output folder (no {SUMMARY_NAME})", "pass the --out of predict or batch"
        )
    try:
        summary = json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(
            path, f"not valid JSON, truncated or damaged ({exc.__class__.__name__})", "run predict again"
        ) from None
    if not isinstance(summary, dict):
        raise InputError(path, "not a predict summary (not a JSON object)", "pass the --out of predict or batch")
    return summary


def is_predict_summary(summary: dict) -> bool:
    return {"frames", "timings_ms_per_frame", "check"} <= set(summary)


def sequence_folders(folder: Path) -> list[tuple[Path, dict]]:
    """(folder, summary) of each predict run in ``folder``: itself, or a batch's sequence folders."""
    summary = read_summary(folder)
    if is_predict_summary(summary):
        return [(folder, summary)]
    found = []
    for sub in sorted(p for p in folder.iterdir() if p.is_dir() and (p / SUMMARY_NAME).is_file()):
        inner = read_summary(sub)
        if is_predict_summary(inner):
            found.append((sub, inner))
    if not found:
        raise InputError(folder / SUMMARY_NAME, "not a predict or batch summary", "pass the --out of predict or batch")
    return found


def predict_page(folder: Path) -> Page:
    go = require_plotly()
    runs = sequence_folders(folder)
    page = Page(f"geonet-infer: {folder.name}")
    if len(runs) > 1:
        page.text(
            f"A batch of {len(runs)} sequences"
            + (f"; the first {MAX_SEQUENCES} are shown." if len(runs) > MAX_SEQUENCES else ".")
        )
    for sub, summary in runs[:MAX_SEQUENCES]:
        _sequence_sections(page, go, sub, summary, titled=len(runs) > 1)
    return page


def _sequence_sections(page: Page, go, folder: Path, summary: dict, titled: bool) -> None:
    name = summary.get("input", {}).get("name") or folder.name
    if titled:
        page.heading(f"Sequence {name}")
    model = summary.get("model") or {}
    model_name = Path(str(model.get("dir", "?"))).name
    page.text(
        f"{summary['frames']} frames of {summary.get('input', {}).get('path', '?')} -> {folder}; "
        f"{summary.get('failed', 0)} failed; {summary.get('frames_per_s', 0):.1f} frames/s; model {model_name} "
        f"({model.get('precision', '?')}, {model.get('isa', '')})."
    )
    _check_section(page, go, summary)
    _path_section(page, go, folder)
    _pairs_section(page, folder, summary)
    page.heading("Where the time went (ms per frame)")
    timings = summary.get("timings_ms_per_frame") or {}
    page.table(["stage", "ms"], [[k, float(v)] for k, v in timings.items()])
    _camera_section(page, summary)
    page.heading("What the model says of itself")
    notices = [summary.get("model_notice")] + list(summary.get("notes") or [])
    for text in filter(None, notices):
        page.text(str(text), note=True)
    if not any(notices):
        page.text("No notice: the model states no limit for this footage.")


def _check_section(page: Page, go, summary: dict) -> None:
    page.heading("The output check: does the flow explain the next frame better than no motion?")
    check = summary.get("check")
    if not check:
        page.text("The check did not run (--no-check, or fewer than two frames).")
        return
    pairs = check["per_pair"]
    frames = [p["frame"] for p in pairs]
    figure = go.Figure()
    for key, label in CHECK_SERIES:
        values = [p.get(key) for p in pairs]
        if any(v is not None for v in values):
            figure.add_trace(go.Scatter(x=frames, y=values, mode="lines+markers", name=label))
    method = (summary.get("methods") or {}).get("flow", {}).get("method", "network")
    figure.update_layout(
        title=f"Error per pair, grey levels (flow: {method}); lower is better",
        xaxis_title="frame", yaxis_title="mean |frame t+1 warped back - frame t|", height=380,
    )  # fmt: skip
    page.plot(figure)
    page.text(
        f"The flow is no better than no motion on {check['flow_no_better']} of {check['pairs']} pairs, the rigid "
        f"flow on {check.get('rigid_no_better', 'n/a')}; median errors: flow {check['median_flow_error']:.2f}, "
        f"no motion {check['median_still_error']:.2f} ({check['method']})."
    )


def _path_section(page: Page, go, folder: Path) -> None:
    page.heading("The camera path, from above")
    poses_file = folder / "poses_kitti.txt"
    if not poses_file.is_file():
        page.text("No poses (pose was not among the tasks).")
        return
    poses = np.loadtxt(poses_file, ndmin=2).reshape(-1, 3, 4)
    x, z = poses[:, 0, 3], poses[:, 2, 3]
    figure = go.Figure(go.Scatter(x=x, y=z, mode="lines+markers", name="network", marker={"size": 4}))
    figure.add_trace(
        go.Scatter(x=[x[0]], y=[z[0]], mode="markers", name="start", marker={"size": 12, "symbol": "star"})
    )
    figure.update_layout(
        title="x (right) against z (forward), the first camera's frame", xaxis_title="x", yaxis_title="z",
        height=420, yaxis={"scaleanchor": "x"},
    )  # fmt: skip
    page.plot(figure)


def _pairs_section(page: Page, folder: Path, summary: dict) -> None:
    check = summary.get("check")
    if not check or not check["per_pair"]:
        return
    page.heading("The best and the worst pairs (flow error minus no-motion error)")
    pairs = sorted(check["per_pair"], key=lambda p: p["flow_error"] - p["still_error"])
    chosen = [("best", pairs[0]), ("worst", pairs[-1])]
    frames = _input_frames(summary, {p["frame"] for _, p in chosen})
    for label, pair in chosen:
        name = pair["frame"]
        page.thumbnails(
            [
                (
                    f"{label}: frame {name} (flow {pair['flow_error']:.1f}, no motion {pair['still_error']:.1f})",
                    frames.get(name),
                ),
                (f"depth {name}", _picture(folder / "depth" / f"{name}.png")),
                (f"flow {name} -> next", _picture(folder / "flow_vis" / f"{name}.png")),
            ]
        )


def _picture(path: Path) -> np.ndarray | None:
    image = cv2.imread(str(path), cv2.IMREAD_COLOR) if path.is_file() else None
    return None if image is None else cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def _input_frames(summary: dict, names: set[str]) -> dict[str, np.ndarray]:
    """The input frames of ``names``, where the input can still be opened (else none: the page says less)."""
    from geonet_infer.io.frames import open_frames

    path = summary.get("input", {}).get("path")
    found: dict[str, np.ndarray] = {}
    if not path or not Path(path).exists():
        return found
    try:
        for frame in open_frames(path):
            if frame.name in names and frame.rgb is not None:
                found[frame.name] = frame.rgb
            if len(found) == len(names):
                break
    except Exception:  # noqa: BLE001 -- a thumbnail is not worth failing the page for
        return found
    return found


def _camera_section(page: Page, summary: dict) -> None:
    page.heading("The intrinsics")
    camera = summary.get("camera")
    if not camera:
        page.text("No intrinsics were needed (depth alone, or DIS flow without network poses).")
        return
    K, size = camera["K"], camera.get("size")
    page.table(
        ["fx", "fy", "cx", "cy", "size", "origin", "source"],
        [[float(K[0][0]), float(K[1][1]), float(K[0][2]), float(K[1][2]), f"{size[0]}x{size[1]}" if size else "?",
          camera.get("origin", "?"), camera.get("source", "?")]],
    )  # fmt: skip

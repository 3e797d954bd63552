"""torch vs onnxruntime parity helpers (export smoke checks and tests).

The ORT-side GeoNet cascade is the runtime's :class:`geonet_infer.core.predictor.Predictor`;
export uses it for INT8 calibration inputs and accuracy deltas, so there is one cascade.
onnxruntime sessions always come from :func:`geonet_infer.engines.onnxruntime.make_session`.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from geonet_infer.engines.onnxruntime import make_session


def max_abs_diff(a, b) -> float:
    return float(np.max(np.abs(np.asarray(a, np.float64) - np.asarray(b, np.float64))))


def relative_max_diff(actual, reference) -> float:
    """max |actual - reference| divided by the range (max - min) of the reference."""
    reference = np.asarray(reference, np.float64)
    span = float(reference.max() - reference.min())
    return max_abs_diff(actual, reference) / max(span, 1e-12)


def torch_outputs(module, inputs: Sequence) -> list[np.ndarray]:
    """Run an export wrapper in torch (no_grad) on numpy/torch inputs -> numpy outputs."""
    import torch  # export-side helper; the runtime never calls this

    with torch.no_grad():
        out = module(*[torch.as_tensor(np.asarray(x)) for x in inputs])
    out = out if isinstance(out, (tuple, list)) else (out,)
    return [o.detach().cpu().numpy() for o in out]


def ort_outputs(session_or_path, inputs: Sequence) -> list[np.ndarray]:
    """Run an ONNX graph (session or path) with positional inputs -> list of outputs."""
    session = make_session(session_or_path) if isinstance(session_or_path, (str, Path)) else session_or_path
    feed = {i.name: np.ascontiguousarray(np.asarray(x, np.float32)) for i, x in zip(session.get_inputs(), inputs)}
    return session.run(None, feed)


def compare_graph(module, onnx_path, inputs: Sequence) -> dict[str, dict[str, float]]:
    """torch wrapper vs ORT graph on the same inputs: {output: {max_abs, relative}} (relative to range)."""
    session = make_session(onnx_path)
    names = [o.name for o in session.get_outputs()]
    ref = torch_outputs(module, inputs)
    got = ort_outputs(session, [np.asarray(x) for x in inputs])
    return {n: {"max_abs": max_abs_diff(g, r), "relative": relative_max_diff(g, r)} for n, g, r in zip(names, got, ref)}

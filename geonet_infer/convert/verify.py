"""``--verify``: the converted fp32 graphs against the checkpoint's own forward pass, on the user's frames.

The reference is the official network re-stated in TensorFlow (:mod:`.official_tf`) fed with the
checkpoint's tensors, when TensorFlow is installed: that checks the whole conversion, the mapping
included. ``python -m export --from-tf --verify`` (repository, torch) falls back to our PyTorch nets
holding the same tensors (``reference``); with neither, the line says plainly that nothing was compared.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from geonet_infer.convert.frames import load_frames, pose_feeds
from geonet_infer.convert.official import SCOPES, Selection
from geonet_infer.core.spec import InputSpec
from geonet_infer.errors import GeoNetError, InputError

TOLERANCE = 1e-3  # of the output's range: a swapped or untransposed tensor is off by the whole range
OUTPUTS = {"depthnet": ("depth", "disparity"), "posenet": ("pose", "pose"), "resflownet": ("flow", "residual_flow")}
TF_REFERENCE = "the official TensorFlow graph with the checkpoint's tensors"


class VerifyError(GeoNetError):
    """A converted graph differs from the reference beyond :data:`TOLERANCE` of the output's range."""


def feeds(frames: list, spec: InputSpec) -> dict:
    """One input per graph: the first frame; the first snippet; frame 0 -> 1 for the flow net
    (its 12 channels: target, source, the source as its own warp, zero rigid flow and error)."""
    out = {"depthnet": spec.to_network(frames[0])[None]}
    if len(frames) >= spec.seq_length:
        out["posenet"] = pose_feeds(frames[: spec.seq_length], spec)[0]["snippet"]
    if len(frames) >= 2:
        tgt, src = (spec.to_network(f) for f in frames[:2])
        zeros = np.zeros((3, *tgt.shape[1:]), np.float32)
        out["resflownet"] = np.concatenate([tgt, src, src, zeros])[None]
    return out


def tensorflow_outputs(sel: Selection, graph: str, feed: np.ndarray, scale_normalize: bool):
    """The official forward pass from the checkpoint's tensors; None without TensorFlow, or for a net
    with no TF re-statement here (the vgg DepthNet)."""
    kind = OUTPUTS[graph][0]
    spec = sel.specs[kind]
    if kind != "pose" and spec.arch != "resnet50":
        return None
    from geonet_infer.convert.official_tf import OfficialNet

    try:
        net = OfficialNet(SCOPES[kind])  # imports TensorFlow
    except ImportError:
        return None
    ckpt = sel.checkpoints[kind]
    net.values = {name: ckpt.tensor(name) for name in ckpt.scope_variables(kind)}
    x = np.ascontiguousarray(np.transpose(feed, (0, 2, 3, 1)))
    if kind == "depth":
        disp = net.disp_resnet50(x)[0].numpy()
        if scale_normalize:  # the official spatial_normalize: each map over its mean
            disp = disp / disp.mean(axis=(1, 2, 3), keepdims=True)
        return np.transpose(disp, (0, 3, 1, 2))
    if kind == "pose":
        return net.pose(x, spec.num_source).numpy()
    h, w = x.shape[1:3]
    return np.transpose(net.flow(x)[0].numpy() * np.array([w, h], np.float32), (0, 3, 1, 2))  # pixels


def verify(
    model_dir: Path,
    sel: Selection,
    frames_dir: Path,
    *,
    height: int,
    width: int,
    seq_length: int,
    scale_normalize: bool,
    reference: Callable[[str, np.ndarray], tuple[np.ndarray, str] | None] | None = None,
) -> str:
    """One line comparing each converted graph with its reference; VerifyError beyond the tolerance."""
    from geonet_infer.engines.onnxruntime import make_session

    frames, _ = load_frames(frames_dir, height, width, max_frames=max(seq_length, 2))
    inputs = feeds(frames, InputSpec.from_conventions(height, width, seq_length))
    parts, failed, references, unchecked = [], [], set(), []
    for graph, (kind, output) in OUTPUTS.items():
        if kind not in sel.specs or graph not in inputs or not (Path(model_dir) / f"{graph}.onnx").is_file():
            continue
        value = inputs[graph]
        session = make_session(Path(model_dir) / f"{graph}.onnx")
        names = [o.name for o in session.get_outputs()]
        got = dict(zip(names, session.run(None, {session.get_inputs()[0].name: value})))[output]
        ref, what = tensorflow_outputs(sel, graph, value, scale_normalize), TF_REFERENCE
        if ref is None and reference is not None and (fallback := reference(graph, value)) is not None:
            ref, what = fallback
        if ref is None:
            unchecked.append(graph)
            continue
        references.add(what)
        err = np.abs(got.astype(np.float64) - ref)
        span = float(ref.max() - ref.min()) or 1.0
        parts.append(f"{graph} {output} max {err.max():.2e} mean {err.mean():.2e} (range {span:.3g})")
        if err.max() > TOLERANCE * span:
            failed.append(graph)
    if not parts and not unchecked:
        raise InputError(
            frames_dir,
            f"{len(frames)} frame(s): too few to verify the converted graphs",
            f"pass a folder of at least {seq_length} consecutive frames",
        )
    line = f"verify: first frames of {frames_dir} at {height}x{width}"
    if parts:
        line += f", converted ONNX vs {' and '.join(sorted(references))}, |error|: {'; '.join(parts)}"
    if unchecked:
        line += (
            f"; not verified: {', '.join(unchecked)} (no reference: install TensorFlow, "
            "pip install tensorflow-cpu, for the official forward pass)"
        )
    if failed:
        raise VerifyError(None, f"{line}: {', '.join(failed)} beyond {TOLERANCE:g} of the range")
    return line

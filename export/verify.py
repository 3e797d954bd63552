"""torch vs onnxruntime parity helpers, and the ORT-side GeoNet cascade.

Used by the export CLI (smoke checks, INT8 calibration and accuracy deltas) and
by the tests. onnxruntime sessions always come from
:func:`geonet_infer.session.make_session`, the one factory the runtime uses too.

The cascade (:class:`OrtCascade`) reproduces ``GeoNet.flow_forward`` at scale 0
for the forward direction target -> next frame:

1. normalise the frames (``conventions.IMAGE_NORM``) in numpy;
2. ``depthnet``: depth of the target (middle frame);
3. ``posenet``: snippet [target, sources in temporal order] -> poses target -> source;
4. ``rigidflow``: target depth, the pose of the chosen source, K, target, source ->
   rigid flow, source warped to the target, photometric error norm;
5. ``resflownet``: the 12 channels [target, source, warped, rigid flow, error]
   (``training.model.flownet_input`` order) -> full flow = residual + rigid flow.
"""
from __future__ import annotations

from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from geonet_infer.conventions import IMAGE_NORM
from geonet_infer.errors import GeoNetInputError
from geonet_infer.manifest import Manifest, load_manifest
from geonet_infer.session import make_session, make_session_options


# ----------------------------------------------------------------------------- numbers
def max_abs_diff(a, b) -> float:
    return float(np.max(np.abs(np.asarray(a, np.float64) - np.asarray(b, np.float64))))


def relative_max_diff(actual, reference) -> float:
    """max |actual - reference| divided by the range (max - min) of the reference."""
    reference = np.asarray(reference, np.float64)
    span = float(reference.max() - reference.min())
    return max_abs_diff(actual, reference) / max(span, 1e-12)


def to_network(rgb: np.ndarray) -> np.ndarray:
    """uint8 RGB (H, W, 3) or (N, H, W, 3) -> float32 NCHW in the network range."""
    rgb = np.asarray(rgb)
    if rgb.ndim == 3:
        rgb = rgb[None]
    if rgb.ndim != 4 or rgb.shape[-1] != 3:
        raise GeoNetInputError(None, f"expected (H, W, 3) or (N, H, W, 3) RGB images, got shape {rgb.shape}")
    x = rgb.astype(np.float32).transpose(0, 3, 1, 2) / np.float32(255.0)
    return IMAGE_NORM.apply(x).astype(np.float32)


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
    return {n: {"max_abs": max_abs_diff(g, r), "relative": relative_max_diff(g, r)}
            for n, g, r in zip(names, got, ref)}


# ----------------------------------------------------------------------------- cascade
class OrtCascade:
    """The four graphs of a model directory run as GeoNet's depth -> pose -> rigid -> residual cascade.

    Args:
        model_dir: a directory written by ``python -m export`` (validated with load_manifest).
        precision: "fp32" or "int8" graph set.
        threads: intra-op threads per session (None = ORT default).
        graphs: which graphs to load (default: every graph of the set).
    """

    def __init__(self, model_dir: str | Path, precision: str = "fp32", threads: int | None = None,
                 graphs: Sequence[str] | None = None, manifest: Manifest | None = None):
        self.manifest = manifest or load_manifest(model_dir)
        self.precision = precision
        options = make_session_options(threads=threads)
        names = graphs or self.manifest.graph_names(precision)
        self.sessions = {n: make_session(self.manifest.path(n, precision), options) for n in names}
        self.height, self.width = self.manifest.height, self.manifest.width
        self.seq_length = self.manifest.seq_length

    # ------------------------------------------------------------------ pieces
    def _session(self, name: str):
        if name not in self.sessions:
            self.sessions[name] = make_session(self.manifest.path(name, self.precision),
                                               make_session_options())
        return self.sessions[name]

    def _run(self, name: str, **feeds) -> dict[str, np.ndarray]:
        session = self._session(name)
        out = session.run(None, {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in feeds.items()})
        return dict(zip([o.name for o in session.get_outputs()], out))

    def _check_frames(self, frames: Sequence[np.ndarray]) -> None:
        if len(frames) != self.seq_length:
            raise GeoNetInputError(None, f"got {len(frames)} frames, the model takes snippets of {self.seq_length}",
                                   "pass consecutive frames [t-k, ..., t, ..., t+k]")
        for f in frames:
            if np.asarray(f).shape != (self.height, self.width, 3):
                raise GeoNetInputError(None, f"frame shape {np.asarray(f).shape}, the graphs take "
                                       f"({self.height}, {self.width}, 3) uint8 RGB",
                                       "resize with cv2.INTER_AREA and scale K accordingly")

    def depth(self, rgb: np.ndarray) -> np.ndarray:
        """uint8 (H, W, 3) or (N, H, W, 3) -> depth (N, 1, H, W)."""
        return self._run("depthnet", image=to_network(rgb))["depth"]

    def poses(self, frames: Sequence[np.ndarray]) -> np.ndarray:
        """Frames in temporal order (target in the middle) -> (N_src, 6) poses target -> each source."""
        self._check_frames(frames)
        norm = [to_network(f) for f in frames]
        mid = len(frames) // 2
        snippet = np.concatenate([norm[mid]] + norm[:mid] + norm[mid + 1:], axis=1)
        return self._run("posenet", snippet=snippet)["pose"][0]

    def flow_input(self, frames: Sequence[np.ndarray], K: np.ndarray, source_index: int | None = None,
                   depth: np.ndarray | None = None, poses: np.ndarray | None = None) -> tuple[np.ndarray, dict]:
        """The (1, 12, H, W) ResFlowNet input for target -> source ``source_index``.

        ``source_index`` counts the sources in temporal order without the target;
        None = the frame right after the target (t+1). Returns (input, parts).
        """
        self._check_frames(frames)
        mid = len(frames) // 2
        src = mid if source_index is None else source_index
        source_frame = [f for i, f in enumerate(frames) if i != mid][src]
        target_n, source_n = to_network(frames[mid]), to_network(source_frame)
        depth = self.depth(frames[mid]) if depth is None else depth
        poses = self.poses(frames) if poses is None else poses
        K = np.asarray(K, np.float32).reshape(1, 3, 3)
        rigid = self._run("rigidflow", depth=depth, pose=poses[src][None], intrinsics=K,
                          target=target_n, source=source_n)
        x = np.concatenate([target_n, source_n, rigid["warped"], rigid["rigid_flow"], rigid["error"]], axis=1)
        return x, {"depth": depth, "poses": poses, **rigid}

    def __call__(self, frames: Sequence[np.ndarray], K: np.ndarray) -> dict[str, np.ndarray]:
        """Frames [t-1, t, t+1] (uint8 RGB at the graphs' H x W) and K at H x W ->

        depth (H, W), pose (6,) t -> t+1, poses (N_src, 6), rigid_flow (H, W, 2),
        flow (H, W, 2) full flow t -> t+1 (only if the set has resflownet), px.
        """
        x, parts = self.flow_input(frames, K)
        out = {"depth": parts["depth"][0, 0], "pose": parts["poses"][len(frames) // 2],
               "poses": parts["poses"], "rigid_flow": parts["rigid_flow"][0].transpose(1, 2, 0),
               "warped": parts["warped"][0], "error": parts["error"][0, 0], "flow_input": x}
        if "resflownet" in self.manifest.graph_names(self.precision):
            flow = self._run("resflownet", flow_input=x)
            out["flow"] = flow["flow"][0].transpose(1, 2, 0)
            out["residual_flow"] = flow["residual_flow"][0].transpose(1, 2, 0)
        return out


def ort_cascade(model_dir: str | Path, frames: Sequence[np.ndarray], K: np.ndarray,
                precision: str = "fp32") -> dict[str, np.ndarray]:
    """One-shot :class:`OrtCascade`: frames [t-1, t, t+1] uint8, K (3, 3) ->
    dict(depth, pose, rigid_flow, flow, ...) for t -> t+1 (see ``OrtCascade.__call__``)."""
    return OrtCascade(model_dir, precision)(frames, K)


# ------------------------------------------------------------------ accuracy predictors
def _refuse_random_init(manifest: Manifest) -> None:
    if manifest.random_init:
        raise GeoNetInputError(manifest.root, "this model directory holds random-init (timing-only) graphs",
                               "accuracy needs graphs exported from a trained --checkpoint")


def ort_depth_predictor(cascade: OrtCascade) -> Callable[[np.ndarray], np.ndarray]:
    """``predict_depth(rgb uint8 (H, W, 3)) -> depth (H, W)`` for training.evaluate.evaluate_depth."""
    _refuse_random_init(cascade.manifest)

    def predict(rgb: np.ndarray) -> np.ndarray:
        if rgb.shape[:2] != (cascade.height, cascade.width):
            raise GeoNetInputError(None, f"frame is {rgb.shape[0]}x{rgb.shape[1]}, the graphs take "
                                   f"{cascade.height}x{cascade.width}", "evaluate on data at the export size")
        return cascade.depth(rgb)[0, 0]
    return predict


def ort_flow_predictor(cascade: OrtCascade) -> Callable[[list, np.ndarray], np.ndarray]:
    """``predict_flow(frames [t-1, t, t+1], K) -> flow t -> t+1 (H, W, 2)`` for evaluate_flow."""
    _refuse_random_init(cascade.manifest)

    def predict(triplet: list, K: np.ndarray) -> np.ndarray:
        return cascade(triplet, K)["flow"]
    return predict

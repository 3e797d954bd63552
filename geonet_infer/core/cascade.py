"""The GeoNet cascade: the one place that turns frames into graph inputs and runs the graphs.

Per frame t of a sequence:

1. ``depthnet``  frame t -> disparity and depth (relative scale);
2. ``posenet``   snippet [t, t-k .. t-1, t+1 .. t+k] -> poses t -> each source;
3. ``rigidflow`` depth of t, pose t -> t+1, K -> rigid flow t -> t+1, frame t+1
   warped onto t, photometric error (the last two only when ResFlowNet reads them:
   :meth:`GraphSet._skip_unread_rigid_outputs`);
4. ``resflownet`` [t, t+1, warped, rigid flow, error] (:data:`RESFLOW_INPUT`) -> full flow
   t -> t+1 (= rigid + residual).

The graphs run at one fixed size (the manifest's ``height`` x ``width``, 128 x 416 for the
released models) on images normalised to the network range. Here, once:

* :class:`InputSpec` reads the manifest's conventions and refuses the ones this runtime does
  not implement (a model exported under other rules fails loudly instead of producing
  plausible garbage); :meth:`InputSpec.to_network` resizes with ``cv2.INTER_AREA`` and normalises;
* :func:`check_image`, :func:`read_frame`, :func:`camera_at`: frames and cameras as the graphs need them;
* :func:`graph_intrinsics` scales K from the input size to the graph size;
* :func:`snippet_indices` forms the snippet around a frame, replicating the end frames;
  :func:`posenet_order` puts the target first for PoseNet;
* :func:`resflow_input` stacks ResFlowNet's 12 channels (training builds the same order);
* :class:`GraphSet` holds one engine per graph; :func:`run_cascade` runs steps 1-4 on a batch of
  snippets; :func:`iter_frames` runs them over a whole sequence, each frame's depth once;
* :func:`disparity_to_input`, :func:`flow_to_input` map outputs back to the input size (flow
  vectors scaled per axis).

:class:`geonet_infer.Predictor` is the public face of this module; benchmarks and export's
INT8 calibration call it directly.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from geonet_infer.core.graphs import (  # noqa: F401  (re-exported: this module's names before the split)
    RIGID_OPS,
    GraphSet,
)
from geonet_infer.core.snippets import (  # noqa: F401  (re-exported: this module's names before the split)
    RESFLOW_INPUT,
    load_snippet,
    next_source_position,
    posenet_order,
    resflow_input,
    snippet_frames,
    snippet_indices,
    snippet_window,
)
from geonet_infer.core.spec import (  # noqa: F401  (re-exported: this module's names before the split)
    CHANNEL_ORDERS,
    GRAPH_IO,
    STAGES,
    ImageLike,
    InputSpec,
    Intrinsics,
    StageTimer,
    camera_at,
    check_image,
    disparity_to_input,
    flow_to_input,
    flows_to_input,
    graph_intrinsics,
    read_frame,
    to_network,
)
from geonet_infer.errors import ModelError
from geonet_infer.io.camera import assumed_camera


def run_cascade(
    graphs: GraphSet,
    spec: InputSpec,
    snippets: np.ndarray,
    targets: list[int],
    K: np.ndarray | None,
    size: tuple[int, int],
    *,
    timer: StageTimer | None = None,
    disparity: np.ndarray | None = None,
    source_position: int | None = None,
    run_resflow: bool = True,
    with_flow: bool = True,
    feeds: dict[str, dict[str, np.ndarray]] | None = None,
) -> dict[str, Any]:
    """Steps 1-4 on a batch of normalised snippets (B, L, 3, h, w) in temporal order.

    Args:
        targets: ``targets[b]`` is the target's index in snippet b.
        K: (3, 3) intrinsics at the input size ``size`` (H, W) (None only with ``with_flow=False``).
        disparity: (B, h, w) disparity of the targets, to reuse depth computed elsewhere.
        source_position: the source (index among the sources) flow goes to; None = the frame
            after the target (:func:`next_source_position`).
        run_resflow: False stops before ResFlowNet (its input is still built: INT8 calibration).
        with_flow: False stops after PoseNet (and then needs no DepthNet).
        feeds: a dict that gets each graph's inputs as it was called with them (graph name ->
            {input name: float32 array}): realistic inputs for timing one graph alone.
    Returns:
        "disparity" (B, h, w), "pose" (B, 6) and "pose_matrix" (B, 4, 4) target -> source; with flow
        also "rigid_flow" (B, 2, h, w) and "flow_input" (B, 12, h, w), and after ResFlowNet
        "residual_flow" and "flow" (B, 2, h, w), all at the graph size.
    """
    timer = timer or StageTimer()

    def call(name: str, **inputs: np.ndarray) -> dict[str, np.ndarray]:
        if feeds is not None:
            feeds[name] = {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in inputs.items()}
        return graphs.run(name, **inputs)

    B, L = snippets.shape[:2]
    rows = np.arange(B)
    target = snippets[rows, targets]
    orders = [posenet_order(t, L) for t in targets]
    src_pos = next_source_position(L) if source_position is None else source_position
    source = snippets[rows, [order[1 + src_pos] for order in orders]]
    if disparity is None and with_flow:
        with timer.stage("depthnet"):
            disparity = call("depthnet", image=target)["disparity"][:, 0]
    with timer.stage("posenet"):
        stacked = np.stack([np.concatenate(list(snippets[b, order])) for b, order in enumerate(orders)])
        pose = call("posenet", snippet=stacked)
    out: dict[str, Any] = {
        "disparity": disparity,
        "pose": pose["pose"][:, src_pos],
        "pose_matrix": pose["pose_matrix"][:, src_pos],
    }
    if not with_flow:
        return out
    assert disparity is not None  # DepthNet ran above unless disparity was given
    if K is None:  # the stated rule rather than a stop (geonet_infer.io.camera.ASSUMED_RULE)
        K = assumed_camera(size[1], size[0]).K
    K_graph = np.repeat(graph_intrinsics(K, size, spec)[None], B, axis=0)
    with timer.stage("rigidflow"):
        rigid = call(
            "rigidflow",
            depth=1.0 / disparity[:, None],
            pose=pose["pose"][:, src_pos],
            intrinsics=K_graph,
            target=target,
            source=source,
        )
    with timer.stage("resflownet"):  # its input: part of its cost (the latency table adds up)
        flow_input = resflow_input({"target": target, "source": source, **rigid})
    out.update(rigid_flow=rigid["rigid_flow"], flow_input=flow_input)
    if run_resflow and "resflownet" in graphs:
        with timer.stage("resflownet"):
            out.update(call("resflownet", flow_input=flow_input))
    return out


def calibration_input(
    graphs: GraphSet,
    spec: InputSpec,
    frames: Sequence[ImageLike],
    camera: Intrinsics,
    source_index: int | None = None,
) -> np.ndarray:
    """The (1, 12, h, w) ResFlowNet input for target -> source ``source_index`` (INT8 calibration).

    ``frames``: a snippet (any size; resized like every other call); ``source_index`` counts
    sources in temporal order without the target (None = the frame after the target).
    """
    missing = [g for g in ("depthnet", "posenet", "rigidflow") if g not in graphs]
    if missing:  # builds ResFlowNet's input, does not run it
        raise ModelError(graphs.manifest.root, f"calibrating ResFlowNet needs the {', '.join(missing)} graph(s)")
    timer = StageTimer()
    x, cam, size = load_snippet(spec, frames, camera, timer)
    mid = len(x) // 2
    source = next_source_position(spec.seq_length) if source_index is None else source_index
    parts = run_cascade(
        graphs,
        spec,
        x[None],
        [mid],
        cam.K if cam else None,
        size,
        timer=timer,
        source_position=source,
        run_resflow=False,
    )
    return parts["flow_input"]


def __getattr__(name: str):
    # imported on first use: a plain import here would be a cycle (geonet_infer.core.sequence imports this module)
    import importlib

    where = {"iter_frames": "geonet_infer.core.sequence"}.get(name)
    if where is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(where), name)

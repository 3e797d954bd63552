"""Score a PyTorch checkpoint with the runtime's evaluation code (same datasets, metrics, tables).

``python -m training.evaluate --checkpoint runs/small_flow/last.pt --data data/synth40
--heldout data/synth40_prepared/heldout.txt --task all``

This module only turns a checkpoint into the numpy callables that
:mod:`geonet_infer.eval.evaluation` scores (so a checkpoint, its ONNX fp32 export and the
INT8 twin are measured by one code path). Frames go through the runtime's own pre- and
post-processing (:mod:`geonet_infer.core.cascade`: area resize to the training size,
normalisation, outputs mapped back to the input size), so any layout works, KITTI included.

``evaluate_depth`` / ``evaluate_flow`` keep the summary format that ``export`` reads
(held-out synthetic sequences, with the trivial baselines).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from geonet_infer.core.cascade import InputSpec, disparity_to_input, flow_to_input, graph_intrinsics
from geonet_infer.errors import GeoNetError, InputError
from geonet_infer.eval import baselines, evaluation, metrics
from geonet_infer.eval.datasets import LAYOUTS, depth_dataset, flow_dataset, load_dataset, read_heldout
from training.checkpoint import load_weights, model_from_checkpoint
from training.geometry import pose_vec_to_mat
from training.model import GeoNet

DepthFn = Callable[[np.ndarray], np.ndarray]
FlowFn = Callable[[list, np.ndarray], np.ndarray]
MAX_DEPTH = evaluation.MAX_DEPTH


def heldout_sequences(prepared_dir: str | Path) -> list[str]:
    """Sequence folders listed in ``<prepared_dir>/heldout.txt`` (never trained on)."""
    path = Path(prepared_dir) / "heldout.txt"
    if not path.is_file():
        raise InputError(
            path, "no held-out list", "prepare synthetic data with `python -m training.prepare --kind synth`"
        )
    return read_heldout(path)


# -------------------------------------------------------------- summaries for export / model card
def _mean(rows: list[dict], keys) -> dict:
    return metrics.aggregate([{k: r.get(k, np.nan) for k in keys} for r in rows])


def evaluate_depth(
    predict_depth: DepthFn, synth_dir: str | Path, sequences: list[str], stride: int = 1, crop: str | None = None
) -> dict:
    """{"model": means, "constant_baseline": means, "frames": n} on held-out synthetic sequences.

    ``crop``: None (every pixel with ground truth) or a crop name of :func:`geonet_infer.eval.metrics.crop_mask`.
    """
    data = depth_dataset(synth_dir, "synth", sequences, stride)
    keys = (*metrics.DEPTH_KEYS, "scale", "n_valid")
    out = {}
    for name, fn in (("model", predict_depth), ("constant_baseline", baselines.constant_depth)):
        out[name] = _mean(evaluation.evaluate_depth(fn, data, crop=crop)["items"], keys)
    return out | {"frames": len(data.items)}


def _flow_summary(rows: list[dict], which: str) -> dict:
    return _mean(
        [
            {
                "epe": r[f"epe_{which}"],
                "fl": r[f"fl_{which}"],
                "acc": 1.0 - r[f"fl_{which}"],
                "n_valid": r.get(f"n_valid_{which}", np.nan),
            }
            for r in rows
        ],
        ("epe", "fl", "acc", "n_valid"),
    )


def evaluate_flow(predict_flow: FlowFn, synth_dir: str | Path, sequences: list[str], stride: int = 1) -> dict:
    """EPE/Fl (noc and occ) of flow t -> t+1 from the triplet [t-1, t, t+1], and the zero-flow baseline."""
    data = flow_dataset(synth_dir, "synth", sequences, stride)
    if not getattr(predict_flow, "needs_intrinsics", False):
        predict_flow = _needs_K(predict_flow)
    model = evaluation.evaluate_flow(predict_flow, data)["items"]
    zero = evaluation.evaluate_flow(baselines.zero_flow, data)["items"]
    return {
        "noc": _flow_summary(model, "noc"),
        "occ": _flow_summary(model, "all"),
        "zero_flow_baseline_noc": _flow_summary(zero, "noc"),
        "pairs": len(model),
    }


def _needs_K(fn):
    def predict(frames, K):
        return fn(frames, K)

    predict.needs_intrinsics = True
    return predict


# -------------------------------------------------------------- torch predictors
class _TorchModel:
    """A checkpoint's GeoNet behind the runtime's pre/post-processing."""

    def __init__(self, model: GeoNet, height: int, width: int):
        self.model = model
        self.seq_length = model.num_source + 1
        self.spec = InputSpec.from_conventions(height, width, self.seq_length)

    def normalised(self, rgb: np.ndarray) -> torch.Tensor:
        """(1, 3, h, w) network-range tensor, resized like the runtime."""
        return torch.from_numpy(self.spec.to_network(rgb)).unsqueeze(0)

    def unit(self, rgb: np.ndarray) -> torch.Tensor:
        """(1, 3, h, w) in [0, 1] (flow_forward normalises itself)."""
        return (self.normalised(rgb) - self.spec.norm_offset) / self.spec.norm_scale


def torch_depth_predictor(model: GeoNet, height: int, width: int) -> DepthFn:
    tm = _TorchModel(model, height, width)

    @torch.no_grad()
    def predict(rgb: np.ndarray) -> np.ndarray:
        disp = model.depth_net(tm.normalised(rgb))[0][0, 0].numpy()
        return disparity_to_input(disp, rgb.shape[:2])[0]

    return predict


def torch_flow_predictor(model: GeoNet, height: int, width: int) -> FlowFn:
    """Full flow from the target to the frame after it, scale 0; a pair [t, t+1] is padded to
    [t, t, t+1] like the runtime does at a sequence start."""
    tm = _TorchModel(model, height, width)

    @torch.no_grad()
    def predict(frames: list, K: np.ndarray) -> np.ndarray:
        frames = list(frames) if len(frames) == 3 else [frames[-2], frames[-2], frames[-1]]
        target = tm.unit(frames[1])
        sources = torch.stack([tm.unit(frames[0])[0], tm.unit(frames[2])[0]]).unsqueeze(0)
        K_t = torch.from_numpy(graph_intrinsics(K, frames[1].shape[:2], tm.spec)).unsqueeze(0)
        fwd_full, _, _, _ = model.flow_forward(target, sources, K_t)
        return flow_to_input(fwd_full[0][1].numpy(), frames[1].shape[:2])  # row 1 = source t+1

    predict.needs_intrinsics = True
    return predict


def torch_pose_predictor(model: GeoNet, height: int, width: int) -> Callable:
    """5-frame snippet poses in the first frame's coordinates (:func:`evaluation.snippet_from_pose_calls`)."""
    tm = _TorchModel(model, height, width)

    @torch.no_grad()
    def pose_call(frames: list) -> np.ndarray:
        mid = len(frames) // 2
        order = [mid] + [i for i in range(len(frames)) if i != mid]  # target, then sources in time order
        stacked = torch.cat([tm.normalised(frames[i]) for i in order], dim=1)
        vectors = model.pose_net(stacked)[0]  # (N, 6)
        return pose_vec_to_mat(vectors).double().numpy()

    return lambda frames, K: evaluation.snippet_from_pose_calls(pose_call, frames, tm.seq_length)


# -------------------------------------------------------------- ONNX predictors (export's accuracy delta)
def onnx_depth_fn(predictor) -> DepthFn:
    """``predict_depth`` of a :class:`geonet_infer.core.predictor.Predictor` (refuses random-init models)."""
    return evaluation.model_depth_fn(predictor)


def onnx_flow_fn(predictor) -> FlowFn:
    """``predict_flow(frames [t-1, t, t+1], K)`` of a Predictor: full flow t -> t+1."""
    return evaluation.model_flow_fn(predictor)


# -------------------------------------------------------------- command line
def checkpoint_methods(model: GeoNet, cfg: dict, tasks: list[str], label: str) -> dict[str, tuple[str, Callable]]:
    """{task: (row label, fn)} of a loaded checkpoint; flow only if it has ResFlowNet."""
    makers = {"depth": torch_depth_predictor, "flow": torch_flow_predictor, "pose": torch_pose_predictor}
    return {
        t: (label, makers[t](model, cfg["height"], cfg["width"]))
        for t in tasks
        if t != "flow" or model.flow_net is not None
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m training.evaluate", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument(
        "--checkpoint",
        required=True,
        help="a last.pt / best.pt from training.train, or a weights file (training.checkpoint)",
    )
    p.add_argument("--data", type=Path, help="dataset folder, any layout of `geonet-infer eval --help`")
    p.add_argument("--layout", default="auto", choices=["auto"] + sorted({n for v in LAYOUTS.values() for n in v}))
    p.add_argument("--heldout", type=Path, help="synth layout: only the sequences of this heldout.txt")
    p.add_argument("--synth-dir", type=Path, help="older form: output of training.synth (= --data)")
    p.add_argument("--prepared-dir", type=Path, help="older form: output of training.prepare (its heldout.txt)")
    p.add_argument("--task", choices=["depth", "flow", "pose", "all"], default="all")
    p.add_argument(
        "--crop",
        choices=["auto", "none", "garg", "eigen"],
        default="auto",
        help="depth crop (auto: Garg on KITTI, every GT pixel on synthetic)",
    )
    p.add_argument("--max-depth", type=float, default=MAX_DEPTH, help="depth cap in metres (default 80)")
    p.add_argument("--stride", type=int, default=1, help="evaluate every n-th item")
    p.add_argument("--out", "--json", dest="out", help="write the JSON result here too")
    args = p.parse_args(argv)
    try:
        data = args.data or args.synth_dir
        if data is None:
            raise InputError(None, "no data", "pass --data DIR (or --synth-dir with --prepared-dir)")
        sequences = (
            read_heldout(args.heldout)
            if args.heldout
            else heldout_sequences(args.prepared_dir)
            if args.prepared_dir
            else None
        )
        ckpt = load_weights(args.checkpoint)
        step = ckpt["step"] if "step" in ckpt else ckpt["source"].get("step")
        model = model_from_checkpoint(ckpt)
        tasks = ["depth", "flow", "pose"] if args.task == "all" else [args.task]
        name = Path(args.checkpoint).name
        label = f"checkpoint {name} (step {step})" if step is not None else f"weights {name}"
        results = []
        for task, (row, fn) in checkpoint_methods(model, ckpt["config"], tasks, label).items():
            dataset = load_dataset(task, data, args.layout, sequences=sequences, stride=args.stride)
            kwargs = (
                {"crop": None if args.crop == "none" else args.crop, "max_depth": args.max_depth}
                if task == "depth"
                else {}
            )
            results.append((row, evaluation.EVALUATORS[task](fn, dataset, method=row, **kwargs)))
    except GeoNetError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    for _, result in results:
        print(evaluation.format_table([(result["method"], result)]))
    if args.out:
        evaluation.write_json(
            args.out, {"checkpoint": str(args.checkpoint), "step": step, "results": [r for _, r in results]}
        )
    errors = [e for _, r in results for e in r["errors"]]
    for e in errors:
        print(f"error: {e['item']}: {e['problem']}", file=sys.stderr)
    return 1 if errors else 0


if __name__ == "__main__":
    sys.exit(main())

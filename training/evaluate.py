"""Evaluate depth and flow on the held-out synthetic sequences.

``python -m training.evaluate --checkpoint runs/rigid/last.pt --synth-dir data/synth
--prepared-dir data/prepared``

The loops take plain numpy predictors, so the same code scores a torch
checkpoint, an exported ONNX fp32 model and its INT8 twin:

* ``predict_depth(rgb uint8 (H, W, 3)) -> depth (H, W)``
* ``predict_flow(frames [t-1, t, t+1] uint8, K (3, 3)) -> flow t->t+1 (H, W, 2)``

Depth follows the Eigen protocol (median scaling, clamp to [1e-3, 80] m) on
every pixel with ground truth (no Garg crop: synthetic frames have no car bonnet
or sky-less band to crop). Flow is EPE on noc and occ pixels (KITTI 2015 style).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from geonet_infer import metrics
from geonet_infer.conventions import IMAGE_NORM
from geonet_infer.errors import GeoNetInputError
from geonet_infer.io import list_images, read_calib_K, read_depth_kitti, read_flow_kitti, read_image
from training.model import GeoNet

DepthFn = Callable[[np.ndarray], np.ndarray]
FlowFn = Callable[[list, np.ndarray], np.ndarray]
MAX_DEPTH = 80.0


def heldout_sequences(prepared_dir: str | Path) -> list[str]:
    """Sequence folders listed in ``<prepared_dir>/heldout.txt`` (never trained on)."""
    path = Path(prepared_dir) / "heldout.txt"
    if not path.is_file():
        raise GeoNetInputError(path, "no held-out list",
                               "prepare synthetic data with `python -m training.prepare --kind synth`")
    return sorted({line.split()[0] for line in path.read_text().splitlines() if line.strip()})


def _frames(sequence_dir: Path) -> list[Path]:
    image_dir = sequence_dir / "image"
    try:
        return list_images(image_dir)
    except GeoNetInputError as err:
        raise GeoNetInputError(image_dir, err.problem, "is this a training.synth sequence?") from None


def evaluate_depth(predict_depth: DepthFn, synth_dir: str | Path, sequences: list[str],
                   stride: int = 1, crop: str | None = None) -> dict:
    """Depth metrics of ``predict_depth`` and of a constant-depth baseline.

    Returns {"model": {abs_rel, ...}, "constant_baseline": {...}, "frames": n}.
    The baseline predicts one constant; after median scaling that constant is
    the median ground-truth depth of each frame. ``crop``: None (every pixel with
    ground truth) or a KITTI crop name of :func:`geonet_infer.metrics.crop_mask`.
    """
    model_rows, baseline_rows = [], []
    for name in sequences:
        for frame in _frames(Path(synth_dir) / name)[::stride]:
            gt = read_depth_kitti(frame.parent.parent / "depth" / frame.name)
            pred = predict_depth(read_image(frame))
            pred = metrics.resize_depth_to(pred, gt.shape)
            model_rows.append(metrics.depth_metrics(gt, pred, max_depth=MAX_DEPTH, crop=crop))
            baseline_rows.append(metrics.depth_metrics(gt, np.ones_like(gt), max_depth=MAX_DEPTH, crop=crop))
    return {"model": metrics.aggregate(model_rows), "constant_baseline": metrics.aggregate(baseline_rows),
            "frames": len(model_rows)}


def evaluate_flow(predict_flow: FlowFn, synth_dir: str | Path, sequences: list[str],
                  stride: int = 1) -> dict:
    """EPE (noc and occ) of flow t -> t+1 predicted from the triplet [t-1, t, t+1]."""
    rows_noc, rows_occ, zero_noc = [], [], []
    for name in sequences:
        seq = Path(synth_dir) / name
        frames = _frames(seq)
        K = read_calib_K(seq / "calib.txt")
        for t in range(1, len(frames) - 1, stride):
            triplet = [read_image(frames[i]) for i in (t - 1, t, t + 1)]
            pred = predict_flow(triplet, K)
            gt_noc, valid_noc = read_flow_kitti(seq / "flow_noc" / frames[t].name)
            gt_occ, valid_occ = read_flow_kitti(seq / "flow_occ" / frames[t].name)
            rows_noc.append(metrics.flow_epe(gt_noc, valid_noc, pred))
            rows_occ.append(metrics.flow_epe(gt_occ, valid_occ, pred))
            zero_noc.append(metrics.flow_epe(gt_noc, valid_noc, np.zeros_like(pred)))
    return {"noc": metrics.aggregate(rows_noc), "occ": metrics.aggregate(rows_occ),
            "zero_flow_baseline_noc": metrics.aggregate(zero_noc), "pairs": len(rows_noc)}


# -------------------------------------------------------------- torch predictors
def _to_tensor(rgb: np.ndarray) -> torch.Tensor:
    """uint8 (H, W, 3) -> (1, 3, H, W) in [0, 1]."""
    return torch.from_numpy(rgb).permute(2, 0, 1).float().div(255.0).unsqueeze(0)


def _check_size(model_hw: tuple[int, int], rgb: np.ndarray, what: str) -> None:
    if rgb.shape[:2] != model_hw:
        raise GeoNetInputError(None, f"{what} is {rgb.shape[0]}x{rgb.shape[1]}, the model was trained at "
                               f"{model_hw[0]}x{model_hw[1]}", "generate or prepare data at that size")


def torch_depth_predictor(model: GeoNet, height: int, width: int) -> DepthFn:
    @torch.no_grad()
    def predict(rgb: np.ndarray) -> np.ndarray:
        _check_size((height, width), rgb, "frame")
        disp = model.depth_net(IMAGE_NORM.apply(_to_tensor(rgb)))[0]
        return (1.0 / disp)[0, 0].numpy()
    return predict


def torch_flow_predictor(model: GeoNet, height: int, width: int) -> FlowFn:
    """Full flow from the target (middle frame) to the last source (t+1), scale 0."""
    @torch.no_grad()
    def predict(triplet: list, K: np.ndarray) -> np.ndarray:
        _check_size((height, width), triplet[1], "frame")
        target = _to_tensor(triplet[1])
        sources = torch.stack([_to_tensor(triplet[0])[0], _to_tensor(triplet[2])[0]]).unsqueeze(0)
        K_t = torch.from_numpy(np.asarray(K, np.float32)).unsqueeze(0)
        fwd_full, _, _, _ = model.flow_forward(target, sources, K_t)
        return fwd_full[0][1].permute(1, 2, 0).numpy()  # rows i-major: row 1 = source t+1
    return predict


# -------------------------------------------------------------- ONNX predictors (the runtime)
def _refuse_random_init(predictor) -> None:
    if predictor.manifest.random_init:
        raise GeoNetInputError(predictor.model_dir, "this model directory holds random-init (timing-only) graphs",
                               "accuracy needs graphs exported from a trained --checkpoint")


def onnx_depth_fn(predictor) -> DepthFn:
    """``predict_depth`` of a :class:`geonet_infer.predictor.Predictor` (refuses random-init models)."""
    _refuse_random_init(predictor)
    return lambda rgb: predictor.depth(rgb).depth


def onnx_flow_fn(predictor) -> FlowFn:
    """``predict_flow(frames [t-1, t, t+1], K)`` of a Predictor: full flow t -> t+1."""
    _refuse_random_init(predictor)
    return lambda triplet, K: predictor.flow(triplet, K).flow


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m training.evaluate", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--checkpoint", required=True, help="a last.pt / best.pt from training.train")
    p.add_argument("--synth-dir", required=True, help="output of training.synth")
    p.add_argument("--prepared-dir", required=True, help="output of training.prepare (has heldout.txt)")
    p.add_argument("--task", choices=["depth", "flow", "all"], default="all")
    p.add_argument("--crop", choices=["none", "garg", "eigen"], default="none",
                   help="depth: pixels scored (none = all with ground truth; garg/eigen = KITTI crops)")
    p.add_argument("--stride", type=int, default=1, help="evaluate every n-th frame")
    p.add_argument("--out", help="write the JSON result here too")
    args = p.parse_args(argv)
    from training.train import load_checkpoint, model_from_checkpoint  # avoid an import cycle
    try:
        ckpt = load_checkpoint(args.checkpoint)
        model = model_from_checkpoint(ckpt)
        cfg = ckpt["config"]
        sequences = heldout_sequences(args.prepared_dir)
        result = {"checkpoint": str(args.checkpoint), "step": ckpt["step"], "sequences": sequences}
        if args.task in ("depth", "all"):
            result["depth"] = evaluate_depth(torch_depth_predictor(model, cfg["height"], cfg["width"]),
                                             args.synth_dir, sequences, args.stride,
                                             crop=None if args.crop == "none" else args.crop)
            result["depth"]["crop"] = args.crop
        if args.task in ("flow", "all") and model.flow_net is not None:
            result["flow"] = evaluate_flow(torch_flow_predictor(model, cfg["height"], cfg["width"]),
                                           args.synth_dir, sequences, args.stride)
    except GeoNetInputError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    text = json.dumps(result, indent=2)
    print(text)
    if args.out:
        Path(args.out).write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Recompute the batch-norm running statistics of a trained model on its training data.

    python -m training.recalibrate runs/stop20/flow/last.pt runs/stop21/combined.pt [--batches 200]

Why (issue 53, round 21): a stage trains its nets on batch statistics while inference normalises with
the running ones, which move by ``--bn-momentum`` per step (1e-3 by default, the official decay 0.999).
After a short fine-tune they still describe the inputs the net saw before it: round 20's ResFlowNet,
retrained as a direct flow net for 1,200 steps, returned 0.8 px of flow for three identical frames, and
0.02 px once its statistics were recomputed.

The nets the checkpoint's stage trained (ResFlowNet in stage flow; DepthNet and PoseNet in stage rigid)
run in training mode over ``--batches`` batches of the training folders the checkpoint names (or
``--data-dir``), without augmentation (the inputs as inference gives them; a stage-flow model's
``--rigid-corruption`` is off here for the same reason) and without gradients; their running means and
variances become the plain average over those batches (what ``torch.optim.swa_utils.update_bn`` does).
No weight changes. Writes a weights file (``training.checkpoint.save_weights``).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch
from torch.utils.data import ConcatDataset

from geonet_infer.errors import GeoNetError, InputError
from training.checkpoint import load_weights, model_from_checkpoint, save_weights, trained_by
from training.config import TrainConfig
from training.data import SequenceDataset, make_loader
from training.model import GeoNet

BATCHES = 200
BATCH_SIZE = 4


def batch_norms(nets: list[torch.nn.Module]) -> list[torch.nn.modules.batchnorm._BatchNorm]:
    return [m for net in nets for m in net.modules() if isinstance(m, torch.nn.modules.batchnorm._BatchNorm)]


@torch.no_grad()
def recalibrate(model: GeoNet, stage: str, loader, batches: int) -> int:
    """Replace the running statistics of ``stage``'s nets in ``model`` by their average over ``batches``
    batches of ``loader``; returns the batches used. The model is left in eval mode."""
    nets = [model.flow_net] if stage == "flow" else [model.depth_net, model.pose_net]
    norms = batch_norms(nets)
    if not norms:
        raise InputError(None, f"the {stage} stage's nets have no batch norm", "nothing to recalibrate")
    for norm in norms:
        norm.reset_running_stats()
    model.eval()
    for net in nets:
        net.train()
    used = 0
    for batch in loader:
        if used == batches:
            break
        for norm in norms:  # a cumulative average: batch k weighs 1/k
            norm.momentum = 1.0 / (used + 1)
        frames = batch["target"], batch["sources"], batch["intrinsics"]
        model.flow_forward(*frames) if stage == "flow" else model.rigid_forward(*frames)
        used += 1
    model.eval()
    return used


def main(argv=None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m training.recalibrate",
        description="Recompute a trained model's batch-norm running statistics (the nets its stage trained) on "
        "its training data, without augmentation or gradients; no weight changes. Writes a weights file.",
    )
    p.add_argument("checkpoint", help="a checkpoint or weights file of training.train")
    p.add_argument("out", help="the weights file to write")
    p.add_argument("--batches", type=int, default=BATCHES, help=f"batches of {BATCH_SIZE} snippets to average over")
    p.add_argument(
        "--data-dir",
        action="append",
        default=None,
        metavar="DIR",
        help="prepared folders whose train.txt snippets to use (repeatable; default: the checkpoint's own "
        "--data-dir and --extra-data-dir)",
    )
    p.add_argument("--seed", type=int, default=0, help="the order the snippets are drawn in")
    args = p.parse_args(argv)
    try:
        if args.batches < 1:
            raise InputError(None, f"--batches must be at least 1, got {args.batches}", "e.g. --batches 200")
        state = load_weights(args.checkpoint)
        cfg = TrainConfig.from_dict(state["config"])
        folders = args.data_dir or [cfg.data_dir, *cfg.extra_data_dirs]
        data = ConcatDataset(
            [SequenceDataset(d, "train", cfg.seq_length, cfg.height, cfg.width, augment=False) for d in folders]
        )
        loader = make_loader(data, BATCH_SIZE, shuffle=True, seed=args.seed, drop_last=True)
        model = model_from_checkpoint(state)
        model.rigid_corruption = 1.0
        used = recalibrate(model, state["stage"], loader, args.batches)
        source = {**trained_by(state), "recalibrated": f"{used} batches of {BATCH_SIZE} from {', '.join(folders)}"}
        save_weights({**state, "model": model.state_dict()}, args.out, source)
    except GeoNetError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(
        f"wrote {args.out}: batch-norm statistics of {used} batches ({Path(args.out).stat().st_size / 2**20:.1f} MiB)"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Score models on footage without labels: GeoNet's own self-supervised losses on a prepared folder.

``python -m training.photometric --checkpoint runs/flowsup/F/last.pt weights/small_synth.pt --data-dir data/udacity``

Real video rarely comes with depth or flow ground truth, but the training objective can
still be measured on it: the photometric error of the rigid warp (stage rigid) or of the
full-flow warp (stage flow) on every sample of ``--splits``, with no augmentation. It is
not a metric of accuracy (a net can lower it without being right, e.g. by smearing flow
into occlusions), so use it as a guard: a model trained on synthetic scenes that does much
worse on real footage than another has not transferred.

Every model is scored with the official loss weights and no loss masks (whatever it was
trained with), so the numbers of different models are comparable; lower is better.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import torch
from torch.utils.data import ConcatDataset

from geonet_infer.errors import GeoNetError, InputError
from training.checkpoint import load_weights, model_from_checkpoint
from training.config import TrainConfig
from training.data import SequenceDataset, make_loader
from training.losses import LossWeights
from training.train import stage_loss, to_device

STAGES = ("rigid", "flow")


def photometric_terms(
    checkpoint: str | Path, data_dir: str | Path, splits: tuple[str, ...] = ("train", "val"), stage: str | None = None
) -> dict:
    """Mean self-supervised loss terms of ``checkpoint`` over the samples of ``data_dir``'s splits.

    Returns {"stage", "samples", "terms": {name: mean over samples}}; ``stage`` defaults to the
    checkpoint's own (a stage-rigid checkpoint cannot be scored on stage flow).
    """
    state = load_weights(checkpoint)
    cfg = TrainConfig.from_dict(state["config"])
    stage = stage or cfg.stage
    if stage not in STAGES:
        raise InputError(None, f"unknown stage {stage!r}", f"choose one of {', '.join(STAGES)}")
    if stage == "flow" and cfg.stage != "flow":
        raise InputError(checkpoint, "has no ResFlowNet (stage rigid)", "score it with --stage rigid")
    cfg = replace(cfg, weights=LossWeights(), mask_out_of_view=False, automask=False)
    model = model_from_checkpoint({**state, "config": cfg.to_dict()})
    data = ConcatDataset(
        [SequenceDataset(data_dir, split, cfg.seq_length, cfg.height, cfg.width, augment=False) for split in splits]
    )
    sums: dict[str, float] = {}
    count = 0
    with torch.no_grad():
        for batch in make_loader(data, batch_size=4, shuffle=False):
            n = len(batch["name"])
            for name, value in stage_loss(model, stage, *to_device(batch, torch.device("cpu"))).terms.items():
                sums[name] = sums.get(name, 0.0) + value * n
            count += n
    return {"stage": stage, "samples": count, "terms": {k: v / count for k, v in sums.items()}}


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m training.photometric",
        description="Score checkpoints on unlabelled prepared footage with GeoNet's self-supervised losses "
        "(official weights, no masks, no augmentation; lower is better). A guard for transfer, not an accuracy metric.",
    )
    p.add_argument(
        "--checkpoint",
        required=True,
        nargs="+",
        help="checkpoints or weights files (training.checkpoint), one row each",
    )
    p.add_argument("--data-dir", required=True, type=Path, help="a training.prepare folder (e.g. real video)")
    p.add_argument("--splits", default="train,val", help="comma list of its splits to score (default %(default)s)")
    p.add_argument("--stage", choices=STAGES, default=None, help="losses of this stage (default: the checkpoint's)")
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    splits = tuple(s for s in args.splits.split(",") if s)
    try:
        rows = [(c, photometric_terms(c, args.data_dir, splits, args.stage)) for c in args.checkpoint]
    except GeoNetError as err:
        print(f"python -m training.photometric: error: {err}", file=sys.stderr)
        return 2
    names = list(rows[0][1]["terms"])
    print(f"{args.data_dir} ({', '.join(splits)}), {rows[0][1]['samples']} samples")
    print("| checkpoint | stage | " + " | ".join(names) + " |")
    print("|---|---|" + "---|" * len(names))
    for path, r in rows:
        print(
            f"| `{path}` | {r['stage']} | " + " | ".join(f"{r['terms'].get(n, float('nan')):.4f}" for n in names) + " |"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())

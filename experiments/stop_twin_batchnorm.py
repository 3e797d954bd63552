"""Issue 53, round 13: does it matter whether the stride twins share PoseNet's call with their batch?

    python -m experiments.stop_twin_batchnorm runs/stop13/rigid/last.pt

On the first 60 stride2 copies of ``data/s_udacity_norev`` (``scripts/stop_finetune.sh prepare``; no
augmentation) and their normal snippets: the median ratio of PoseNet's translation lengths (stride 2 over
stride 1) in inference mode (running batch-norm statistics), in training mode with four copies and their
four twins in one call, and in training mode with each twin in a call of its own (round 13's term).
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from geonet_infer.conventions import IMAGE_NORM
from training.checkpoint import load_weights, model_from_checkpoint
from training.data import SequenceDataset


def ratio(fast: torch.Tensor, slow: torch.Tensor) -> float:
    return float((fast[..., :3].norm(dim=-1) / slow[..., :3].norm(dim=-1)).median())


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoint")
    parser.add_argument("--data", default="data/s_udacity_norev")
    parser.add_argument("--copies", type=int, default=60)
    args = parser.parse_args(argv)
    pose_net = model_from_checkpoint(load_weights(args.checkpoint)).pose_net
    dataset = SequenceDataset(args.data, "train", augment=False, load_twins=True)
    rows = [i for i, name in enumerate(dataset.names) if name.endswith("_stride2")][: args.copies]
    fast, slow = [], []
    for i in rows:
        item = dataset[i]
        for out, target, sources in ((fast, "target", "sources"), (slow, "twin_target", "twin_sources")):
            out.append(torch.cat([IMAGE_NORM.apply(item[target]), IMAGE_NORM.apply(item[sources]).flatten(0, 1)]))
    fast_in, slow_in = torch.stack(fast), torch.stack(slow)
    with torch.no_grad():
        pose_net.eval()
        print(f"inference mode: {ratio(pose_net(fast_in), pose_net(slow_in)):.2f}")
        pose_net.train()  # batch statistics; the running ones change too, but nothing is saved
        groups = range(0, len(rows) - 3, 4)
        joint = [ratio(*pose_net(torch.cat([fast_in[k : k + 4], slow_in[k : k + 4]])).split(4)) for k in groups]
        alone = [
            ratio(pose_net(fast_in[k : k + 4]), torch.cat([pose_net(slow_in[j : j + 1]) for j in range(k, k + 4)]))
            for k in groups
        ]
        print(f"training mode, twins in the batch's call: {np.median(joint):.2f}")
        print(f"training mode, each twin in a call of its own: {np.median(alone):.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

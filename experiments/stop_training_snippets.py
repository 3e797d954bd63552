"""Issue 53: what a stage-rigid checkpoint's PoseNet does on its own training snippets, without exporting it.

    python -m experiments.stop_training_snippets weights/small_synth.pt runs/stop2/rigid/last.pt \\
        runs/stop3/rigid/last.pt runs/stop5/rigid/last.pt

On the odometry samples of ``data/s_odom`` (``scripts/stop_finetune.sh prepare``; true poses, no augmentation),
per checkpoint: the mean predicted path of the stride-1 moving snippets (the net's unit), how much the unit
true/predicted path varies between them (std / mean: 0 = one speed scale for every snippet), the stride-2
copies' predicted path over the stride-1 ones' (the truth: about 2), and the still copies' over the moving
ones' (0 = the stops are learnt). Round 4 was stopped on these figures, before anything was scored.
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from geonet_infer.conventions import IMAGE_NORM
from training.checkpoint import load_weights, model_from_checkpoint
from training.data import SequenceDataset
from training.geometry import pose_vec_to_mat


def paths(checkpoint: str, dataset: SequenceDataset) -> list[tuple[str, float, float]]:
    """(sample name, predicted path, true path) of every sample: summed step lengths target -> sources."""
    model = model_from_checkpoint(load_weights(checkpoint)).eval()
    rows = []
    with torch.no_grad():
        for i in range(len(dataset)):
            item = dataset[i]
            target, sources = IMAGE_NORM.apply(item["target"][None]), IMAGE_NORM.apply(item["sources"][None])
            T = pose_vec_to_mat(model.pose_net(torch.cat([target, sources.flatten(1, 2)], dim=1))[0])
            true = item["pose_gt"][:, :3, 3].norm(dim=-1).sum().item()
            rows.append((item["name"], T[:, :3, 3].norm(dim=-1).sum().item(), true))
    return rows


def summary(rows: list[tuple[str, float, float]]) -> dict:
    moving = np.array([(p, t) for n, p, t in rows if t > 0 and not n.endswith(("_stride2", "_static"))])
    stride2 = np.array([p for n, p, t in rows if n.endswith("_stride2")])
    still = np.array([p for n, p, t in rows if t == 0 and n.endswith("_static")])
    unit = moving[:, 1] / moving[:, 0]
    return {
        "moving_snippets": len(moving),
        "mean_moving_path": float(moving[:, 0].mean()),
        "unit_spread": float(unit.std() / unit.mean()),
        "stride2_over_moving": float(stride2.mean() / moving[:, 0].mean()),
        "still_over_moving": float(still.mean() / moving[:, 0].mean()),
        "still_copies": len(still),
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("checkpoints", nargs="+", help="weights or stage-rigid checkpoints")
    p.add_argument("--data", default="data/s_odom", help="a training.prepare folder with true poses")
    args = p.parse_args(argv)
    dataset = SequenceDataset(args.data, split="train", augment=False, load_pose=True)
    for checkpoint in args.checkpoints:
        s = summary(paths(checkpoint, dataset))
        print(
            f"{checkpoint}: moving path {s['mean_moving_path']:.3f} (n={s['moving_snippets']}), unit spread "
            f"{s['unit_spread']:.3f}, stride 2 / stride 1 {s['stride2_over_moving']:.2f}, still / moving "
            f"{s['still_over_moving']:.2f} (n={s['still_copies']})"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Issue 53: does a PoseNet measure how fast the camera moves, or only whether it moves?

    python -m experiments.stop_speed_probe --model bundled=geonet_infer/models/small_synth \\
        --model round12=runs/stop12/model --json docs/stop_speed_probe.json
    python -m experiments.stop_speed_probe --model round16=runs/stop16/model --json docs/stop_speed_probe.json  # adds

On the KITTI odometry frames no model trained on (06 targets 3-27, 01 targets 34-47; grey, the
sequence's calibration not needed by PoseNet), every target t is given to PoseNet as the snippets
(t-s, t, t+s) for strides s = 0 (one frame three times), 1, 2 and 3: a camera standing, driving, and
driving twice and three times as fast. The mean predicted translation length per stride, and its ratio
to stride 1's: a PoseNet that measures speed gives about 0, 1, 2, 3 (the truth's ratios are printed
beside them); one that does not gives about 1 for every moving stride.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

import geonet_infer
from geonet_infer.io.images import read_image

REALDATA = Path("../shared/realdata")
TARGETS = {"06": range(3, 28), "01": range(34, 48)}  # t +- 3 outside the trained 06 31-50, 01 0-30
STRIDES = (0, 1, 2, 3)


def probe(model: str | Path) -> dict:
    predictor = geonet_infer.load(model, precision="fp32", mode="latency")
    out = {}
    for seq, targets in TARGETS.items():
        folder = REALDATA / f"kitti_odometry_{seq}/sequences/{seq}/image_0"
        centres = np.loadtxt(REALDATA / f"kitti_odometry_{seq}/poses/{seq}.txt").reshape(-1, 3, 4)[:, :, 3]
        frames: dict[int, np.ndarray] = {}

        def frame(i: int, frames=frames, folder=folder) -> np.ndarray:
            if i not in frames:
                frames[i] = read_image(folder / f"{i:06d}.png")
            return frames[i]

        step = {}
        true = {}
        for s in STRIDES:
            lengths = [
                np.linalg.norm(predictor.pose([frame(t - s), frame(t), frame(t + s)]).vectors[:, :3], axis=1).mean()
                for t in targets
            ]
            step[s] = float(np.mean(lengths))
            true[s] = float(np.mean([np.linalg.norm(centres[t + s] - centres[t]) for t in targets]))
        out[seq] = {
            "targets": len(targets),
            "mean_translation": step,
            "ratio_to_stride_1": {s: step[s] / step[1] for s in STRIDES},
            "true_ratio_to_stride_1": {s: true[s] / true[1] for s in STRIDES},
        }
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", action="append", required=True, metavar="NAME=DIR", help="repeatable")
    parser.add_argument(
        "--json", type=Path, help="write the figures here (the models already in the file are kept, these replaced)"
    )
    args = parser.parse_args(argv)
    result = json.loads(args.json.read_text()) if args.json and args.json.is_file() else {}
    for spec in args.model:
        name, _, path = spec.partition("=")
        result[name] = probe(path)
        for seq, fig in result[name].items():
            ratios = " ".join(
                f"s{s} {fig['ratio_to_stride_1'][s]:.2f} (truth {fig['true_ratio_to_stride_1'][s]:.2f})"
                for s in STRIDES
            )
            print(f"{name:10s} {seq}: step at stride 1 {fig['mean_translation'][1]:.4f}; ratios {ratios}")
    if args.json:
        args.json.write_text(json.dumps(result, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

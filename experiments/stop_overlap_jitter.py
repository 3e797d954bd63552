"""Issue 53: where a PoseNet's step-length spread comes from, without exporting it.

    python -m experiments.stop_overlap_jitter weights/small_synth.pt weights/stop_round14.pt

On the held-out KITTI odometry targets of ``experiments.stop_speed_probe`` (06: t 3-27, 01: t 34-47; never
trained on), every target t is fed as the snippet (t-1, t, t+1), as the runtime does. Per checkpoint and
sequence, in log units (0.01 = 1 %):

* within a call: the spread of log(step t -> t+1 / step t-1 -> t) around the truth's ratio, the two
  steps of one call;
* across calls: the RMS of log(step t -> t+1 from the call on t / the same step from the call on t+1),
  one step measured twice (0 in the truth);
* against the truth: the spread of log(predicted / true step t -> t+1);
* directions, in degrees: where camera t+1 lies seen from camera t, as the calls on t and on t+1 give it
  (across calls) and against the truth's (mean angle).

Round 16's ``--pose-overlap`` was chosen on these figures: round 14's two steps of a call agreed (0.6 % on
06, 0.4 % on 01) and one step measured by neighbouring calls did not (12.0 % on 06, 8.2 % on 01; the bundled
model 2.5 % and 2.2 %). Frames are resized to 128x416 with
OpenCV's area filter (the grey camera 0 repeated to three channels), not through the runtime.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np
import torch

from geonet_infer.conventions import IMAGE_NORM
from geonet_infer.io import read_kitti_poses
from training.checkpoint import load_weights, model_from_checkpoint
from training.geometry import pose_vec_to_mat

ODOMETRY = Path("../shared/realdata")
TARGETS = {"06": range(3, 28), "01": range(34, 48)}  # held out: experiments.stop_speed_probe's


def read_frame(sequence: str, t: int, root: Path = ODOMETRY) -> torch.Tensor:
    """(3, 128, 416) float32 in [0, 1]: grey camera 0, area-resized."""
    path = root / f"kitti_odometry_{sequence}" / "sequences" / sequence / "image_0" / f"{t:06d}.png"
    image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if image is None:
        raise SystemExit(f"{path}: cannot read the frame")
    small = cv2.resize(image, (416, 128), interpolation=cv2.INTER_AREA).astype(np.float32) / 255.0
    return torch.from_numpy(small)[None].expand(3, -1, -1).contiguous()


def true_next_centres(sequence: str, root: Path = ODOMETRY) -> np.ndarray:
    """(M, 3) camera t+1's centre in camera t's coordinates, from the official camera-to-world poses (its
    length is the true step t -> t+1, metres)."""
    poses = read_kitti_poses(root / f"kitti_odometry_{sequence}" / "poses" / f"{sequence}.txt")
    return np.einsum("mji,mj->mi", poses[:-1, :3, :3], poses[1:, :3, 3] - poses[:-1, :3, 3])


@torch.no_grad()
def call_motions(model, frames: dict[int, torch.Tensor], t: int) -> np.ndarray:
    """(2, 4, 4) PoseNet's motions target t -> t-1 and t -> t+1 (``POSE``: each maps frame t's points into the
    source's) from its call on (t-1, t, t+1)."""
    sources = torch.stack([frames[t - 1], frames[t + 1]])[None]
    pose_input = torch.cat([IMAGE_NORM.apply(frames[t][None]), IMAGE_NORM.apply(sources).flatten(1, 2)], dim=1)
    return pose_vec_to_mat(model.pose_net(pose_input)[0]).double().numpy()


def _angle(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)), -1, 1))))


def jitter(checkpoint: str, sequence: str, targets: range) -> dict[str, float]:
    model = model_from_checkpoint(load_weights(checkpoint)).eval()
    frames = {t: read_frame(sequence, t) for t in range(targets.start - 1, targets.stop + 1)}
    T = {t: call_motions(model, frames, t) for t in targets}
    steps = {t: (np.linalg.norm(T[t][0, :3, 3]), np.linalg.norm(T[t][1, :3, 3])) for t in targets}
    # camera t+1 seen from camera t: the inverse's translation of t -> t+1, or t+1 -> t's own translation
    ahead = {t: -T[t][1, :3, :3].T @ T[t][1, :3, 3] for t in targets}
    behind = {t: T[t][0, :3, 3] for t in targets}  # camera t-1 seen from camera t
    centres = true_next_centres(sequence)
    truth = np.linalg.norm(centres, axis=1)
    within = [np.log(steps[t][1] / steps[t][0]) - np.log(truth[t] / truth[t - 1]) for t in targets]
    across = [np.log(steps[t][1] / steps[t + 1][0]) for t in targets if t + 1 in steps]
    against = [np.log(steps[t][1] / truth[t]) for t in targets]
    return {
        "within_call": float(np.std(within)),
        "across_calls": float(np.sqrt(np.mean(np.square(across)))),
        "against_truth": float(np.std(against)),
        "direction_across_calls_deg": float(np.mean([_angle(ahead[t], behind[t + 1]) for t in targets if t + 1 in T])),
        "direction_against_truth_deg": float(np.mean([_angle(ahead[t], centres[t]) for t in targets])),
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("checkpoints", nargs="+", help="weights or stage-rigid checkpoints")
    args = p.parse_args(argv)
    print(
        "| checkpoint | sequence | step: within a call | across calls | against the truth "
        "| direction, degrees: across calls | against the truth |"
    )
    print("|---|---|---|---|---|---|---|")
    for checkpoint in args.checkpoints:
        for sequence, targets in TARGETS.items():
            j = jitter(checkpoint, sequence, targets)
            print(
                f"| {checkpoint} | {sequence} | {j['within_call']:.3f} | {j['across_calls']:.3f} | "
                f"{j['against_truth']:.3f} | {j['direction_across_calls_deg']:.2f} | "
                f"{j['direction_against_truth_deg']:.2f} |"
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

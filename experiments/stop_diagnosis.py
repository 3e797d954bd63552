"""Issue 53: why did every stop round lose held-out pose and the KITTI 2015 flow pair while the footage
checks improved? Decomposes both scores for the bundled model and each candidate.

    python -m experiments.stop_diagnosis --model bundled=geonet_infer/models/small_synth \\
        --model round1=runs/stop/model --model round2=runs/stop2/model --model round3=runs/stop3/model \\
        --json docs/stop_diagnosis.json --md docs/stop_diagnosis.md

Pose, on the odometry snippets no model trained on (``experiments.real_pose_experiment.held_out``), per
sequence: the official snippet ATE; the mean predicted step; how much the 4 step lengths of a 5-frame
snippet vary (std / mean, the truth's beside it); the angle between each predicted and true step. Then
the ATE re-scored with one model's step directions and another's step lengths (the first model is the
reference), and with unit lengths: which of the two a model loses the ATE to. A constant forward step
(no model) is scored beside them.

Flow, on KITTI 2015 000010 (non-occluded ground truth): EPE of the full and of the rigid flow, and the
median length of each against the truth's (1.0 = the right size).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

import geonet_infer
from benchmarks.eval_all import KITTI_2015_ASSUMED_K
from experiments.real_pose_experiment import held_out
from geonet_infer.eval import evaluation, metrics
from geonet_infer.eval.datasets import load_dataset
from geonet_infer.io.images import read_image

REALDATA = Path("../shared/realdata")
SEQUENCES = ("06", "01", "00")


def _steps(xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(unit directions (4, 3), lengths (4,)) of a 5-position snippet's steps."""
    d = np.diff(xyz, axis=0)
    lengths = np.linalg.norm(d, axis=1)
    return d / np.maximum(lengths, 1e-12)[:, None], lengths


def _path(directions: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    return np.vstack([np.zeros(3), np.cumsum(directions * lengths[:, None], axis=0)])


def snippets(model: Path) -> dict[str, list[tuple[np.ndarray, np.ndarray]]]:
    """Per sequence, (true, predicted) positions (5, 3) of each held-out snippet."""
    predictor = geonet_infer.load(model, precision="fp32", mode="latency")
    fn = evaluation.model_fn("pose", predictor)
    out: dict[str, list] = {}
    for seq in SEQUENCES:
        name = f"KITTI odometry {seq}"
        dataset = load_dataset("pose", REALDATA / f"kitti_odometry_{seq}/sequences/{seq}", "kitti-odometry")
        dataset.items = [it for it in dataset.items if held_out(name, it.name)]
        pairs = out.setdefault(seq, [])
        evaluation.evaluate_pose(fn, dataset, observe=lambda _i, gt, pred, _r, p=pairs: p.append((gt, pred)))
        out[seq] = [(gt[:, :3, 3] - gt[0, :3, 3], pred[:, :3, 3] - pred[0, :3, 3]) for gt, pred in pairs]
    return out


def ate(gt: np.ndarray, pred: np.ndarray) -> float:
    return evaluation.ate_rows(gt, pred)["ate_snippet"]


def pose_figures(own: dict, reference: dict) -> dict:
    figures: dict = {}
    swaps: dict[str, list[float]] = {
        k: [] for k in ("own", "own_dirs_ref_lengths", "ref_dirs_own_lengths", "own_dirs_unit_lengths")
    }
    for seq, rows in own.items():
        ates, steps, cv, cv_true, angles = [], [], [], [], []
        for (gt, pred), (_, ref) in zip(rows, reference[seq]):
            (u_true, l_true), (u, lengths), (u_ref, l_ref) = _steps(gt), _steps(pred), _steps(ref)
            ates.append(ate(gt, pred))
            steps.append(lengths.mean())
            cv.append(lengths.std() / lengths.mean())
            cv_true.append(l_true.std() / l_true.mean())
            angles.append(np.degrees(np.arccos(np.clip((u * u_true).sum(axis=1), -1.0, 1.0))).mean())
            swaps["own"].append(ates[-1])
            swaps["own_dirs_ref_lengths"].append(ate(gt, _path(u, l_ref)))
            swaps["ref_dirs_own_lengths"].append(ate(gt, _path(u_ref, lengths)))
            swaps["own_dirs_unit_lengths"].append(ate(gt, _path(u, np.ones(4))))
        figures[seq] = {
            "snippets": len(rows),
            "ate": float(np.mean(ates)),
            "mean_step": float(np.mean(steps)),
            "step_cv": float(np.mean(cv)),
            "true_step_cv": float(np.mean(cv_true)),
            "direction_error_deg": float(np.mean(angles)),
        }
    figures["all held out"] = {k: float(np.mean(v)) for k, v in swaps.items()} | {"snippets": len(swaps["own"])}
    return figures


def constant_step(reference: dict) -> dict:
    """The ATE of a camera stepping straight forward (+z) by one unit per frame, every snippet."""
    forward = np.outer(np.arange(5), [0.0, 0.0, 1.0])
    per = {seq: [ate(gt, forward) for gt, _ in rows] for seq, rows in reference.items()}
    return {seq: float(np.mean(v)) for seq, v in per.items()} | {
        "all held out": float(np.mean([x for v in per.values() for x in v]))
    }


def flow_figures(model: Path) -> dict:
    dataset = load_dataset("flow", REALDATA / "kitti2015_flow_000010", "kitti")
    item = dataset.items[0]
    predictor = geonet_infer.load(model, precision="fp32", mode="latency")
    frames = [read_image(p) for p in item.frames][-predictor.seq_length :]
    if len(frames) < predictor.seq_length:
        frames = frames[-2:]
    fx, fy, cx, cy = KITTI_2015_ASSUMED_K
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    result = predictor.flow(frames, K)
    gt, valid = item.load_gt("noc")
    true_length = np.median(np.linalg.norm(gt[valid], axis=1))
    out = {}
    for name, flow in (("full", result.flow), ("rigid", result.rigid_flow)):
        flow = metrics.resize_flow_nearest(flow, gt.shape[:2]) if flow.shape[:2] != gt.shape[:2] else flow
        out[f"{name}_epe_noc"] = metrics.flow_epe(gt, valid, flow)["epe"]
        out[f"{name}_length_ratio"] = float(np.median(np.linalg.norm(flow[valid], axis=1)) / true_length)
    return out


def _row(label: str, values: list[float], fmt: str) -> str:
    return f"| {label} | " + " | ".join(format(v, fmt) for v in values) + " |"


def markdown(result: dict) -> str:
    names = list(result["models"])
    models = [result["models"][n] for n in names]
    L = ["# Why the stop rounds lost held-out pose and flow (issue 53)", "", f"`{result['command']}`", ""]
    L += ["## Pose, odometry snippets no model trained on", ""]
    L += ["| sequence | figure | " + " | ".join(names) + " |", "|---|---|" + "---|" * len(names)]
    rows = (
        ("ate", "snippet ATE"),
        ("mean_step", "mean step (own unit)"),
        ("step_cv", "step-length spread (std/mean)"),
        ("true_step_cv", "the truth's spread"),
        ("direction_error_deg", "step direction error, degrees"),
    )
    for seq in SEQUENCES:
        for key, label in rows:
            L.append(
                _row(
                    f"{seq} ({models[0]['pose'][seq]['snippets']}) | {label}",
                    [m["pose"][seq][key] for m in models],
                    ".4g",
                )
            )
    constant = result["constant_step"]
    per_sequence = ", ".join(f"{s} {constant[s]:.4f}" for s in SEQUENCES)
    L += ["", f"Constant forward step, no model: ATE {constant['all held out']:.4f} over all; {per_sequence}.", ""]
    L += [f"## Directions or lengths? ATE over all held-out snippets, lengths swapped with {names[0]}'s", ""]
    L += ["| | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]
    swaps = (
        ("own", "own steps"),
        ("own_dirs_ref_lengths", f"own directions, {names[0]}'s lengths"),
        ("ref_dirs_own_lengths", f"{names[0]}'s directions, own lengths"),
        ("own_dirs_unit_lengths", "own directions, equal lengths"),
    )
    L += [_row(label, [m["pose"]["all held out"][key] for m in models], ".4f") for key, label in swaps]
    L += ["", "## KITTI 2015 flow 000010 (non-occluded)", ""]
    L += ["| | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]
    flows = (
        ("full_epe_noc", "full flow EPE, px"),
        ("full_length_ratio", "full flow length / truth's (median)"),
        ("rigid_epe_noc", "rigid flow EPE, px"),
        ("rigid_length_ratio", "rigid flow length / truth's (median)"),
    )
    L += [_row(label, [m["flow"][key] for m in models], ".3g") for key, label in flows]
    return "\n".join(L) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--model", action="append", required=True, metavar="NAME=DIR", help="the first is the reference")
    p.add_argument("--json", type=Path, required=True)
    p.add_argument("--md", type=Path, required=True)
    args = p.parse_args(argv)
    models = dict(m.split("=", 1) for m in args.model)
    poses = {name: snippets(Path(d)) for name, d in models.items()}
    reference = poses[next(iter(models))]
    result = {
        "command": "python -m experiments.stop_diagnosis "
        + " ".join(f"--model {m}" for m in args.model)
        + f" --json {args.json} --md {args.md}",
        "models": {
            name: {"dir": d, "pose": pose_figures(poses[name], reference), "flow": flow_figures(Path(d))}
            for name, d in models.items()
        },
        "constant_step": constant_step(reference),
    }
    args.json.write_text(json.dumps(result, indent=1) + "\n")
    args.md.write_text(markdown(result))
    print(args.md.read_text())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

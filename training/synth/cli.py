"""``python -m training.synth``: flags -> :class:`SynthConfig` -> :func:`generate`, with a progress bar."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from geonet_infer.errors import GeoNetError
from training.synth.scene import TRAFFIC
from training.synth.sequence import SynthConfig, generate, open_folder


def build_parser() -> argparse.ArgumentParser:
    D = SynthConfig  # argparse defaults are the config's defaults
    p = argparse.ArgumentParser(
        prog="python -m training.synth",
        description="Generate synthetic KITTI-like driving sequences with exact depth, optical-flow, "
        "motion-mask and camera-pose ground truth, written in KITTI encodings. "
        "Each sequence goes to OUT/seq_NNNN/ (image/, depth/, flow_occ/, flow_noc/, "
        "motion_mask/, poses.txt, calib.txt); see docs/synthetic_data.md.",
        epilog="Deterministic: the same --seed gives identical files for any --workers. Resumable: "
        "complete sequences are skipped, interrupted ones (OUT/.tmp_seq_NNNN) are redone. "
        "Exit codes: 0 written, 2 bad usage or settings (one line naming the item).",
    )
    p.add_argument("--out", required=True, type=Path, help="output folder (created)")
    p.add_argument("--sequences", type=int, default=D.sequences, help="number of sequences (default %(default)s)")
    p.add_argument("--frames", type=int, default=D.frames, help="frames per sequence, >= 2 (default %(default)s)")
    p.add_argument("--seed", type=int, default=D.seed, help="master seed (default %(default)s)")
    p.add_argument("--height", type=int, default=D.height, help="image height (default %(default)s)")
    p.add_argument("--width", type=int, default=D.width, help="image width (default %(default)s)")
    p.add_argument("--workers", type=int, default=D.workers, help="processes, one sequence each (default %(default)s)")
    p.add_argument(
        "--traffic",
        choices=tuple(TRAFFIC),
        default=D.traffic,
        help="light: the lead car 14-35 m ahead, few cars (the original scenes); dense: queues 5-15 m "
        "ahead and beside the camera, a third of the vehicles trucks; queue: dense traffic on a one-way "
        "road, the camera stopping and crawling (0-0.6 m per frame) while the lanes beside it move on "
        "(default %(default)s)",
    )
    return p


def main(argv=None) -> int:
    cfg = SynthConfig(**vars(build_parser().parse_args(argv)))
    try:
        open_folder(cfg)  # bad settings fail before the progress bar is drawn
    except GeoNetError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    from tqdm import tqdm

    t0 = time.perf_counter()
    with tqdm(total=cfg.sequences, unit="seq", desc="synth") as bar:
        done = 0

        def progress(status: str) -> None:
            nonlocal done
            done += status == "done"
            bar.update(1)
            bar.set_postfix(frames_per_s=f"{done * cfg.frames / (time.perf_counter() - t0):.1f}")

        counts = generate(cfg, progress)
    print(f"{counts['done']} sequence(s) written, {counts['skipped']} already complete, in {cfg.out}")
    return 0

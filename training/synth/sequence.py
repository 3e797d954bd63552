"""Sequences: render the frames of a scene, write them in KITTI encodings, generate a whole folder.

from training.synth import SynthConfig, generate
generate(SynthConfig(out=Path("data/synth"), sequences=4, frames=100))
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from geonet_infer.conventions import REFERENCE_HEIGHT, REFERENCE_WIDTH
from geonet_infer.errors import InputError
from geonet_infer.io import (
    DEPTH_SCALE,
    atomic_write,
    write_calib_K,
    write_depth_kitti,
    write_flow_kitti,
    write_image,
    write_kitti_poses,
    write_mask,
)
from training.synth.render import Renderer
from training.synth.scene import TRAFFIC, make_scene
from training.synth.truth import flow_gt, frame_geometry

GENERATOR_VERSION = 1
MAX_PNG_DEPTH = 65535 / DEPTH_SCALE  # largest depth a KITTI uint16 PNG can hold
RESUME_KEYS = ("generator_version", "seed", "frames", "height", "width", "traffic")  # must match to add to a folder
KEY_DEFAULTS = {"traffic": "light"}  # for folders written before the key existed


@dataclass
class SynthConfig:
    """A synthetic data folder: ``sequences`` sequences of ``frames`` frames at height x width.

    Deterministic: the same seed gives identical files for any ``workers``.
    """

    out: Path
    sequences: int = 4
    frames: int = 100  # per sequence, >= 2 (flow needs pairs)
    seed: int = 0
    height: int = REFERENCE_HEIGHT
    width: int = REFERENCE_WIDTH
    workers: int = 1  # processes, one sequence each
    traffic: str = "light"  # "light" (the original), "dense" (queues, trucks), "queue" (stop-and-go): scene.TRAFFIC


# ---------------------------------------------------------------------------- one sequence
def sequence_rng(seed: int, index: int) -> np.random.Generator:
    """Independent RNG per (seed, sequence index): output does not depend on --workers."""
    return np.random.default_rng(np.random.SeedSequence([int(seed), int(index)]))


def iter_frames(
    seed: int,
    index: int,
    frames: int,
    height: int = REFERENCE_HEIGHT,
    width: int = REFERENCE_WIDTH,
    traffic: str = "light",
) -> Iterator[dict]:
    """Render one sequence frame by frame.

    Yields per frame t: image (H, W, 3) uint8, depth (H, W) float32 metres (sky ~1000 m),
    ids (H, W) int32, motion_mask (H, W) bool, and for t < M-1 flow (H, W, 2) float32,
    flow_noc / flow_occ (H, W) bool (t -> t+1); plus K and pose (4, 4) camera-to-world in
    the frame-0 camera coordinates (first pose = identity).
    """
    if frames < 2:
        raise InputError(None, f"--frames must be >= 2 (got {frames})", "flow needs frame pairs")
    scene = make_scene(sequence_rng(seed, index), frames, height, width, traffic)
    r = Renderer(scene)
    poses = np.linalg.inv(scene.T_wc[0]) @ scene.T_wc  # relative to frame 0
    poses[0] = np.eye(4)  # exactly, not up to rounding
    prev = frame_geometry(r, 0)
    for t in range(frames):
        nxt = frame_geometry(r, t + 1) if t + 1 < frames else None
        out = {
            "image": r.colour(t),
            "depth": prev.depth.astype(np.float32),
            "ids": prev.ids,
            "motion_mask": prev.moving,
            "K": scene.K,
            "pose": poses[t],
        }
        if nxt is not None:
            out["flow"], out["flow_noc"], out["flow_occ"] = flow_gt(scene, t, prev, nxt)
        yield out
        prev = nxt


def generate_sequence(
    seed: int,
    index: int,
    frames: int,
    height: int = REFERENCE_HEIGHT,
    width: int = REFERENCE_WIDTH,
    traffic: str = "light",
) -> dict:
    """Whole sequence in memory (for tests and small previews).

    Returns dict: image (M, H, W, 3) uint8, depth (M, H, W) float32, ids (M, H, W) int32,
    motion_mask (M, H, W) bool, flow (M-1, H, W, 2) float32, flow_noc / flow_occ (M-1, H, W) bool,
    poses (M, 4, 4) float64 camera-to-world (frame 0 = identity), K (3, 3) float64.
    """
    fr = list(iter_frames(seed, index, frames, height, width, traffic))
    out = {k: np.stack([f[k] for f in fr]) for k in ("image", "depth", "ids", "motion_mask")}
    for k in ("flow", "flow_noc", "flow_occ"):
        out[k] = np.stack([f[k] for f in fr[:-1]])
    out["poses"] = np.stack([f["pose"] for f in fr])
    out["K"] = fr[0]["K"]
    return out


def sequence_name(index: int) -> str:
    return f"seq_{index:04d}"


def _write_frame(folder: Path, t: int, fr: dict) -> None:
    stem = f"{t:06d}.png"
    write_image(folder / "image" / stem, fr["image"])
    depth = np.where(fr["depth"] <= MAX_PNG_DEPTH, fr["depth"], 0.0)  # sky / far: no measurement
    write_depth_kitti(folder / "depth" / stem, depth)
    write_mask(folder / "motion_mask" / stem, fr["motion_mask"])
    if "flow" in fr:
        write_flow_kitti(folder / "flow_occ" / stem, fr["flow"], fr["flow_occ"])
        write_flow_kitti(folder / "flow_noc" / stem, fr["flow"], fr["flow_noc"])


def write_sequence(out_dir, seed: int, index: int, frames: int, height: int, width: int, traffic: str = "light") -> str:
    """Render sequence `index` into out_dir/seq_NNNN (via out_dir/.tmp_seq_NNNN + rename).

    Returns the status: "done" or "skipped" (already complete).
    """
    out_dir = Path(out_dir)
    name = sequence_name(index)
    final = out_dir / name
    if final.is_dir():
        return "skipped"
    tmp = out_dir / f".tmp_{name}"
    if tmp.exists():  # left by an interrupted run: start this sequence again
        shutil.rmtree(tmp)
    poses = []
    K = None
    for t, fr in enumerate(iter_frames(seed, index, frames, height, width, traffic)):
        _write_frame(tmp, t, fr)
        poses.append(fr["pose"])
        K = fr["K"]
    write_kitti_poses(tmp / "poses.txt", np.stack(poses))
    write_calib_K(tmp / "calib.txt", K)
    os.replace(tmp, final)
    return "done"


# ---------------------------------------------------------------------------- a folder
def _worker(args):
    return write_sequence(*args)


def check_config(cfg: SynthConfig) -> None:
    if cfg.frames < 2 or cfg.sequences < 1 or cfg.height < 8 or cfg.width < 8 or cfg.workers < 1:
        raise InputError(
            None,
            f"bad settings: frames {cfg.frames}, sequences {cfg.sequences}, "
            f"size {cfg.height}x{cfg.width}, workers {cfg.workers}",
            "need --frames >= 2, --sequences >= 1, --height/--width >= 8, --workers >= 1",
        )
    if cfg.traffic not in TRAFFIC:
        raise InputError(None, f"unknown traffic {cfg.traffic!r}", f"choose one of {', '.join(TRAFFIC)}")


def _record_config(cfg: SynthConfig) -> None:
    """Refuse to mix sequences made with other settings in one folder (resuming needs the same ones)."""
    config = {
        "generator_version": GENERATOR_VERSION,
        "seed": cfg.seed,
        "frames": cfg.frames,
        "height": cfg.height,
        "width": cfg.width,
        "sequences": cfg.sequences,
        "traffic": cfg.traffic,
    }
    path = Path(cfg.out) / "synth_config.json"
    if path.exists():
        old = KEY_DEFAULTS | json.loads(path.read_text())
        if any(old.get(k) != config[k] for k in RESUME_KEYS):
            settings = ", ".join(f"{k}={old.get(k)}" for k in RESUME_KEYS)
            raise InputError(
                path, f"folder was generated with {settings}", "Use a new --out folder, or the same settings to resume"
            )
        config["sequences"] = max(config["sequences"], old.get("sequences", 0))
    with atomic_write(path) as tmp:
        tmp.write_text(json.dumps(config, indent=1) + "\n")


def open_folder(cfg: SynthConfig) -> None:
    """Check the settings, create ``cfg.out`` and record them there (idempotent; GeoNetError if
    the folder holds sequences made with other settings)."""
    check_config(cfg)
    try:
        Path(cfg.out).mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(
            cfg.out, f"cannot create the output folder ({exc.strerror or exc})", "choose a writable --out"
        ) from None
    _record_config(cfg)


def generate(cfg: SynthConfig, on_sequence: Callable[[str], None] | None = None) -> dict[str, int]:
    """Write ``cfg.sequences`` sequences into ``cfg.out``; complete ones are skipped (resumable).

    ``on_sequence(status)`` is called as each sequence finishes ("done" / "skipped").
    Returns {"done": n, "skipped": n}. Raises GeoNetError on bad settings or a folder
    generated with other settings.
    """
    open_folder(cfg)
    jobs = [(str(cfg.out), cfg.seed, i, cfg.frames, cfg.height, cfg.width, cfg.traffic) for i in range(cfg.sequences)]
    counts = {"done": 0, "skipped": 0}

    def record(status: str) -> None:
        counts[status] += 1
        if on_sequence is not None:
            on_sequence(status)

    if cfg.workers == 1:
        for job in jobs:
            record(_worker(job))
        return counts
    import multiprocessing as mp

    # spawn: no fork-inherited state; the pool is terminated if a worker fails.
    # One OpenCV thread per worker process: the workers are the parallelism.
    with mp.get_context("spawn").Pool(
        min(cfg.workers, len(jobs)), initializer=cv2.setNumThreads, initargs=(1,)
    ) as pool:
        for status in pool.imap_unordered(_worker, jobs):
            record(status)
    return counts

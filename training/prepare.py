"""Turn image sequences into GeoNet's training format (the official ``prepare_train_data.py``).

Output under ``--out DIR`` (read back by :class:`training.data.SequenceDataset`)::

    DIR/<folder>/<frame>.jpg         seq_length frames at H x W side by side: (H, seq_length*W, 3),
                                     temporal order, target (middle frame) in the middle; JPEG q95
    DIR/<folder>/<frame>_cam.txt     one line "fx,0.,cx,0.,fy,cy,0.,0.,1.": the target's K at H x W
    DIR/<folder>/<frame>_depth.png   synth held-out samples (and, with --train-depth, every synth
                                     sample): target depth (KITTI 16-bit, m*256) resized to H x W
                                     with nearest neighbour; with --teacher-depth (real footage)
                                     the triangulated depth, no metric scale (median 10)
    DIR/<folder>/<frame>_flow.png    synth train/val samples with --train-flow: the non-occluded
                                     flow target -> next frame (KITTI flow PNG), resized to H x W
                                     with nearest neighbour and scaled by the resize ratios
    DIR/<folder>/<frame>_pose.txt    --train-pose (odometry, synth): the true motion target -> each
                                     source, one row-major 3x4 matrix per source (KITTI poses format,
                                     sources in temporal order; the POSE convention, metres)
    DIR/train.txt, DIR/val.txt       "<folder> <frame>" per line
    DIR/heldout.txt                  synth only: held-out samples (never in train.txt / val.txt)

``<folder>`` is ``<drive>_02`` / ``<drive>_03`` for KITTI raw, the sequence name for odometry and
synthetic data; ``<frame>`` is the target frame's file stem.

Every file goes through :func:`geonet_infer.io.atomic_write`, so an interrupted run never
leaves half a sample; a re-run skips samples whose files all exist (resumable).
"""

from __future__ import annotations

import argparse
import logging
import sys
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from geonet_infer.conventions import REFERENCE_HEIGHT, REFERENCE_WIDTH, rigid_inverse, scale_intrinsics
from geonet_infer.errors import GeoNetError, InputError
from geonet_infer.eval.metrics import resize_flow_gt
from geonet_infer.io import (
    IMAGE_SUFFIXES,
    VIDEO_SUFFIXES,
    atomic_write,
    list_images,
    open_frames,
    read_calib_file,
    read_calib_K,
    read_camera,
    read_depth_kitti,
    read_flow_kitti,
    read_image,
    read_kitti_poses,
    require_key,
    write_cam_txt,
    write_depth_kitti,
    write_flow_kitti,
    write_image,
    write_kitti_poses,
)
from training.motion_mix import chosen, parse_motion_mix, static_labels, still_copy, variant_window
from training.teachers import (
    TEACHER_DEPTHS,
    TEACHER_FLOWS,
    TEACHER_POSES,
    teacher_depth,
    teacher_flow,
    teacher_motion,
)

log = logging.getLogger(__name__)

KINDS = ("synth", "kitti_raw", "kitti_odom", "video", "frames")
SPLITS = ("eigen", "stereo", "odom", "none")
DEFAULT_SPLIT = {"kitti_raw": "eigen", "kitti_odom": "odom", "synth": "none", "video": "none", "frames": "none"}
VALID_SPLITS = {
    "kitti_raw": ("eigen", "stereo", "none"),
    "kitti_odom": ("odom", "none"),
    "synth": ("none",),
    "video": ("none",),
    "frames": ("none",),
}
FRAME_CACHE = ".frames"  # video/frames: the undistorted, cropped, resized, non-static frames
LISTS_DIR = Path(__file__).with_name("kitti_lists")
RAW_CAMS = ("02", "03")  # KITTI raw colour cameras: left, right
ODOM_TEST_SEQS = ("09", "10")  # the pose benchmark sequences (spec §8), never trained on
JPEG_QUALITY = 95
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
TEST_DRIVE = "kitti_raw_2011_09_26_sfnd"  # ../shared/realdata's test set (DEVELOPERS.md): no labels, no training
PREPARE_HINT = "see python -m training.prepare --help"


# --------------------------------------------------------------------------- config
@dataclass
class PrepareConfig:
    """What :func:`prepare` reads, how it cuts it and where it writes (see the module docstring)."""

    kind: str  # one of KINDS
    src: Path
    out: Path
    seq_length: int | None = None  # odd; None = 5 for kitti_odom, else 3
    height: int = REFERENCE_HEIGHT
    width: int = REFERENCE_WIDTH
    split: str | None = None  # None = DEFAULT_SPLIT[kind]
    remove_static: bool = False  # kitti_raw: drop the frames of static_frames.txt first
    workers: int = 1  # processes writing samples
    val_fraction: float = 0.1  # probability of a sample going to val.txt
    seed: int = 8964  # train/val split seed of the official script
    heldout: int = 2  # synth: the last N sequences go to heldout.txt
    train_depth: bool = False  # synth: also write the target depth of train/val samples (depth supervision)
    train_flow: bool = False  # synth: also write the target's flow to t+1 of train/val samples (flow supervision)
    train_pose: bool = False  # kitti_odom/synth: also write the true motion target -> sources (pose supervision)
    teacher_flow: str | None = None  # real footage: label flow target -> next with this classical method (teachers)
    teacher_pose: str | None = None  # real footage: label motion target -> sources with this classical method
    teacher_depth: str | None = None  # real footage: label the target depth with this classical method
    max_frames: int | None = None  # only the first N frames of each sequence (quick runs)
    strict: bool = False  # the first bad input is an error instead of a skip
    calib: Path | None = None  # video/frames: the camera (any format of geonet_infer.io.read_camera)
    crop: tuple[int, int, int, int] | None = None  # video/frames: x, y, w, h kept after undistortion
    static_threshold: float = 1.0  # video/frames: drop a frame whose mean |grey difference| to the
    #                                last kept one is below this (0..255 levels, at H x W); 0 keeps all
    motion_mix: dict = field(default_factory=dict)  # variant -> probability (training.motion_mix)
    mix_seed: int = 53  # seed of the motion-mix draws


# --------------------------------------------------------------------------- data records
@dataclass
class Sequence:
    """One camera's frames: the unit inside which snippets are formed."""

    folder: str  # output folder name
    image_dir: Path
    frames: list[Path]  # image files, sorted by frame number
    K: np.ndarray  # (3, 3) intrinsics at the frames' original resolution
    scene: str = ""  # KITTI raw drive folder name, e.g. 2011_09_26_drive_0001_sync (static_frames.txt)
    heldout: bool = False
    depth_dir: Path | None = None  # synth: depth/ folder (held-out GT; every sample with --train-depth)
    flow_dir: Path | None = None  # synth with --train-flow: flow_noc/ folder (<t>.png = flow t -> t+1)
    static_removed: set = field(default_factory=set)  # frame numbers dropped by --remove-static
    poses: np.ndarray | None = None  # --train-pose: (M, 4, 4) camera-to-world, row = frame number


@dataclass
class Snippet:
    """One training sample: seq_length consecutive frames, target in the middle."""

    folder: str
    frame: str  # target frame stem
    paths: tuple[Path, ...]  # temporal order
    K: np.ndarray  # (3, 3) target intrinsics at original resolution
    heldout: bool = False
    depth_path: Path | None = None
    flow_path: Path | None = None  # flow target -> next frame (KITTI flow PNG)
    poses: np.ndarray | None = None  # (N_src, 4, 4) true motion target -> source, sources in temporal order
    teacher_flow: str | None = None  # label the flow to the next frame with this teacher (training.teachers)
    teacher_pose: str | None = None  # label the motion to the sources with this teacher
    teacher_depth: str | None = None  # label the target's depth with this teacher
    variant: str = ""  # "" (the normal snippet) or one of training.motion_mix.VARIANTS

    @property
    def name(self) -> str:
        return f"{self.folder} {self.frame}"


@dataclass
class Skip:
    where: Path
    reason: str

    def __str__(self) -> str:
        return f"{self.where}: {self.reason}"


@dataclass
class PrepareResult:
    """What :func:`prepare` did. Names are "<folder> <frame>"."""

    out: Path
    train: list[str] = field(default_factory=list)
    val: list[str] = field(default_factory=list)
    heldout: list[str] = field(default_factory=list)
    written: int = 0
    existing: int = 0  # already complete from an earlier run (resume)
    skipped: list[Skip] = field(default_factory=list)

    def summary(self) -> str:
        lines = [
            f"prepare: {self.written} samples written, {self.existing} already present, "
            f"{len(self.skipped)} skipped -> {self.out}",
            f"  train {len(self.train)}, val {len(self.val)}, heldout {len(self.heldout)}",
        ]
        if self.skipped:
            lines.append("  skipped:")
            lines += [f"    - {s}" for s in self.skipped]
        return "\n".join(lines)


class Skips:
    """Collects skip reasons; with ``strict`` the first one raises instead."""

    def __init__(self, strict: bool):
        self.strict = strict
        self.items: list[Skip] = []

    def add(self, where, reason: str, hint: str = "") -> None:
        if self.strict:
            raise InputError(where, reason, hint or "fix or remove the file, or run without --strict to skip it")
        self.items.append(Skip(Path(where), reason))
        log.warning("skip %s: %s", where, reason)


# --------------------------------------------------------------------------- small helpers
def frame_number(path: Path) -> int | None:
    """Frame index from a file stem like 0000000042; None for non-numeric names."""
    return int(path.stem) if path.stem.isdigit() else None


def list_frames(folder: Path, skips: Skips) -> list[Path]:
    """Image files of a folder in frame order (:func:`geonet_infer.io.list_images`); [] and a skip
    if it holds none."""
    try:
        return list_images(folder)
    except GeoNetError as err:
        skips.add(err.path or folder, err.problem, err.hint)
        return []


def png_size(path: Path) -> tuple[int, int] | None:
    """(width, height) from a PNG header without decoding; None if unreadable.

    Raises ValueError for a PNG-named file whose header is not a PNG header.
    Non-PNG files return None (their size is checked when they are decoded).
    """
    if path.suffix.lower() != ".png":
        return None
    with open(path, "rb") as f:
        head = f.read(24)
    if len(head) < 24 or head[:8] != PNG_SIGNATURE or head[12:16] != b"IHDR":
        raise ValueError("not a valid PNG header (truncated or corrupt file)")
    return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")


def read_scene_list(name: str) -> set[str]:
    """Scene names from training/kitti_lists/<name> (blank lines ignored)."""
    path = LISTS_DIR / name
    if not path.is_file():
        raise InputError(path, "scene list missing from the repository", "restore training/kitti_lists/")
    return {line.strip() for line in path.read_text().splitlines() if line.strip()}


def read_static_frames() -> set[tuple[str, str]]:
    """{(drive folder, frame stem)} from static_frames.txt ("date drive frame" lines)."""
    path = LISTS_DIR / "static_frames.txt"
    if not path.is_file():
        raise InputError(path, "static frame list missing from the repository", "restore training/kitti_lists/")
    out = set()
    for line in path.read_text().splitlines():
        parts = line.split()
        if len(parts) == 3:
            out.add((parts[1], parts[2]))
    return out


def resize(img: np.ndarray, height: int, width: int) -> np.ndarray:
    """(h, w, 3) uint8 -> (height, width, 3) uint8.

    The official dump used scipy.misc.imresize (PIL bilinear). scipy.misc is gone, so we use
    INTER_AREA when shrinking (box filter, no aliasing; matches TF resize_area used elsewhere)
    and INTER_LINEAR when enlarging; pixels differ slightly from the official dump.
    """
    shrink = height <= img.shape[0] and width <= img.shape[1]
    return cv2.resize(img, (width, height), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)


# --------------------------------------------------------------------------- finding sequences
def _has_any(folder: Path, names) -> bool:
    return any((folder / n).is_dir() for n in names)


def _raw_drives(src: Path) -> list[Path]:
    """Drive folders under a KITTI raw root (date/drive), a date folder, or one drive folder."""
    cam_dirs = [f"image_{c}" for c in RAW_CAMS]
    if _has_any(src, cam_dirs):
        return [src]
    drives = []
    for d in sorted(p for p in src.iterdir() if p.is_dir()):
        if _has_any(d, cam_dirs):
            drives.append(d)
            continue
        drives += [dd for dd in sorted(p for p in d.iterdir() if p.is_dir()) if _has_any(dd, cam_dirs)]
    return drives


def collect_kitti_raw(src: Path, split: str, skips: Skips) -> list[Sequence]:
    """One Sequence per (drive, camera 02/03); K = P_rect_0X[:3, :3] of calib_cam_to_cam.txt."""
    drives = _raw_drives(src)
    if not drives:
        raise InputError(
            src,
            "no KITTI raw drive found (no image_02/ or image_03/ folder here or 1-2 levels down)",
            "pass a KITTI raw root (<date>/<drive>/image_02/data/*.png) or one drive folder",
        )
    test_scenes = read_scene_list(f"test_scenes_{split}.txt") if split in ("eigen", "stereo") else set()
    seqs = []
    for drive in drives:
        # The official loader compares the drive name minus "_sync" with the scene lists.
        scene = drive.name[:-5] if drive.name.endswith("_sync") else drive.name
        if scene in test_scenes:
            log.info("exclude %s: test scene of the %s split", drive.name, split)
            continue
        # Calibration sits in the date folder of a raw root, or beside image_02 in a lone drive.
        calib_path = next(
            (p for p in (drive / "calib_cam_to_cam.txt", drive.parent / "calib_cam_to_cam.txt") if p.is_file()), None
        )
        if calib_path is None:
            skips.add(
                drive,
                "no calib_cam_to_cam.txt in the drive folder or its parent",
                "copy the date's calibration files next to the drive folders",
            )
            continue
        calib = read_calib_file(calib_path)
        for cam in RAW_CAMS:
            cam_dir = drive / f"image_{cam}"
            if not cam_dir.is_dir():
                continue
            image_dir = cam_dir / "data" if (cam_dir / "data").is_dir() else cam_dir
            try:
                P = require_key(calib, f"P_rect_{cam}", calib_path)
            except GeoNetError as err:
                skips.add(calib_path, err.problem, f"camera {cam} of {drive.name} needs it")
                continue
            seqs.append(
                Sequence(
                    folder=f"{drive.name}_{cam}",
                    image_dir=image_dir,
                    frames=list_frames(image_dir, skips),
                    K=np.asarray(P, dtype=np.float64).reshape(3, 4)[:, :3].copy(),
                    scene=drive.name,
                )
            )
    return seqs


def remove_static_frames(seqs: list[Sequence]) -> None:
    """Drop the frames of static_frames.txt (official --remove_static), before snippets are formed."""
    static = read_static_frames()
    for s in seqs:
        kept = [p for p in s.frames if (s.scene, p.stem) not in static]
        s.static_removed = {frame_number(p) for p in s.frames if (s.scene, p.stem) in static}
        if len(kept) != len(s.frames):
            log.info("%s: %d static frames removed", s.folder, len(s.frames) - len(kept))
        s.frames = kept


def collect_kitti_odom(src: Path, split: str, skips: Skips, train_pose: bool = False) -> list[Sequence]:
    """One Sequence per odometry sequence; image_2 + P2, else grey image_0 + P0.

    With ``train_pose`` a sequence carries the dev kit's ``poses/XX.txt`` (beside ``sequences/``),
    the motion of the left grey camera; the colour camera is rigidly mounted beside it, so the two
    share rotations and, on a straight drive, translations (a few cm apart in turns).
    """
    if (src / "calib.txt").is_file() or _has_any(src, ("image_2", "image_0")):
        seq_dirs = [src]
    else:
        root = src / "sequences" if (src / "sequences").is_dir() else src
        seq_dirs = [
            d
            for d in sorted(root.iterdir())
            if d.is_dir() and not d.name.startswith(".") and _has_any(d, ("image_2", "image_0"))
        ]
    if not seq_dirs:
        raise InputError(
            src,
            "no KITTI odometry sequence found (expected sequences/XX/image_2 or image_0)",
            "pass the odometry root that holds sequences/",
        )
    seqs = []
    for d in seq_dirs:
        if split == "odom" and d.name in ODOM_TEST_SEQS:
            log.info("exclude sequence %s: pose test sequence (use --split none to include it)", d.name)
            continue
        colour = d / "image_2"
        if colour.is_dir() and any(p.suffix.lower() in IMAGE_SUFFIXES for p in colour.iterdir()):
            image_dir, key = colour, "P2"
        else:
            # Only greyscale frames: read_image expands them to 3 identical channels.
            image_dir, key = d / "image_0", "P0"
            log.warning(
                "sequence %s: no colour frames in image_2/, using greyscale image_0/ (P0) converted to 3 channels",
                d.name,
            )
        calib_path = d / "calib.txt"
        try:
            K = read_calib_K(calib_path, key)
        except GeoNetError as err:
            skips.add(err.path or calib_path, err.problem, f"sequence {d.name} needs {key}")
            continue
        poses = _sequence_poses(d.parent.parent / "poses" / f"{d.name}.txt", skips) if train_pose else None
        seqs.append(
            Sequence(folder=d.name, image_dir=image_dir, frames=list_frames(image_dir, skips), K=K, poses=poses)
        )
    return seqs


def _sequence_poses(path: Path, skips: Skips) -> np.ndarray | None:
    """Camera-to-world poses of a sequence, or None and a skip: its samples then train without."""
    try:
        return read_kitti_poses(path)
    except GeoNetError as err:
        skips.add(err.path or path, err.problem, "its samples get no _pose.txt (--train-pose)")
        return None


def collect_synth(
    src: Path,
    heldout: int,
    skips: Skips,
    train_depth: bool = False,
    train_flow: bool = False,
    train_pose: bool = False,
) -> list[Sequence]:
    """One Sequence per generator folder (image/, depth/, calib.txt); the last ``heldout`` are held out.

    Held-out sequences carry their depth/ folder for evaluation; the others only with ``train_depth``.
    With ``train_flow`` the training sequences carry their flow_noc/ folder (held-out flow is
    scored from the generator's folder by the evaluation, never written here).
    """
    if (src / "image").is_dir():
        seq_dirs = [src]
    else:
        # Hidden folders are unfinished work (e.g. the generator's .tmp_seq_NNNN).
        seq_dirs = [
            d for d in sorted(src.iterdir()) if d.is_dir() and not d.name.startswith(".") and (d / "image").is_dir()
        ]
    if not seq_dirs:
        raise InputError(
            src,
            "no synthetic sequence found (expected <seq>/image/*.png and <seq>/calib.txt)",
            "pass the output root of the synthetic generator (training.synth)",
        )
    if heldout >= len(seq_dirs):
        raise InputError(
            src,
            f"{len(seq_dirs)} sequences but --heldout {heldout}: nothing left to train on",
            "generate more sequences or lower --heldout",
        )
    held = {d.name for d in seq_dirs[len(seq_dirs) - heldout :]}
    seqs = []
    for d in seq_dirs:
        try:
            K = read_calib_K(d / "calib.txt", "K")
        except GeoNetError as err:
            skips.add(err.path or d, err.problem, err.hint)
            continue
        seqs.append(
            Sequence(
                folder=d.name,
                image_dir=d / "image",
                frames=list_frames(d / "image", skips),
                K=K,
                heldout=d.name in held,
                depth_dir=d / "depth" if train_depth or d.name in held else None,
                flow_dir=d / "flow_noc" if train_flow and d.name not in held else None,
                poses=_sequence_poses(d / "poses.txt", skips) if train_pose and d.name not in held else None,
            )
        )
    return seqs


# --------------------------------------------------------------------------- snippets
# --------------------------------------------------------------------------- video / frames
def _video_inputs(src: Path, kind: str) -> list[Path]:
    """kind video: a video file or a folder of them; kind frames: one folder of frames."""
    if kind == "frames":
        return [src]
    if src.is_file():
        return [src]
    videos = sorted(p for p in src.iterdir() if p.suffix.lower() in VIDEO_SUFFIXES)
    if not videos:
        raise InputError(src, f"no video ({', '.join(VIDEO_SUFFIXES)}) in this folder", PREPARE_HINT)
    return videos


def crop_intrinsics(K: np.ndarray, crop: tuple[int, int, int, int] | None, frame_size: tuple[int, int]) -> np.ndarray:
    """K of the cropped frames (cx, cy shift by the crop's corner); checks the crop fits."""
    K = K.copy()
    if crop is None:
        return K
    x, y, w, h = crop
    if x < 0 or y < 0 or w < 8 or h < 8 or x + w > frame_size[0] or y + h > frame_size[1]:
        raise InputError(
            None,
            f"--crop {x},{y},{w},{h} does not fit the {frame_size[0]}x{frame_size[1]} frames",
            "give X,Y,W,H inside the frame (after undistortion, same size)",
        )
    K[0, 2] -= x
    K[1, 2] -= y
    return K


def collect_video(cfg: PrepareConfig, skips: Skips) -> list[Sequence]:
    """Decode each input, undistort, crop, resize to H x W and drop static frames into a cache.

    The cache (``OUT/.frames/<name>/NNNNNN.png``, numbered consecutively over the kept
    frames) becomes an ordinary sequence with K at H x W, so snippets are cut as for KITTI.
    """
    if cfg.calib is None:
        raise InputError(
            None, f"--kind {cfg.kind} needs --calib FILE", "a calibration with K (and distortion, if the lens has any)"
        )
    camera = read_camera(cfg.calib)
    seqs = []
    for path in _video_inputs(Path(cfg.src), cfg.kind):
        source = open_frames(path)
        cache = Path(cfg.out) / FRAME_CACHE / source.name
        cache.mkdir(parents=True, exist_ok=True)
        K_out, kept, last, size = None, [], None, None
        for i, frame in enumerate(source):
            if cfg.max_frames is not None and i >= cfg.max_frames:
                break
            if not frame.ok:
                skips.add(path, f"frame {frame.name}: {frame.error.problem}")
                continue
            rgb = frame.rgb
            if size is None:
                size = (rgb.shape[1], rgb.shape[0])
                cam_here = camera.scaled_to(*size)
                K_crop = crop_intrinsics(cam_here.K, cfg.crop, size)
                crop_size = (cfg.crop[2], cfg.crop[3]) if cfg.crop else size
                K_out = scale_intrinsics(K_crop, cfg.width / crop_size[0], cfg.height / crop_size[1])
            elif (rgb.shape[1], rgb.shape[0]) != size:
                skips.add(path, f"frame {frame.name} is {rgb.shape[1]}x{rgb.shape[0]}, the first {size[0]}x{size[1]}")
                continue
            rgb = cam_here.undistort(rgb)  # same K after undistortion (what the runtime does too)
            if cfg.crop:
                x, y, w, h = cfg.crop
                rgb = rgb[y : y + h, x : x + w]
            small = resize(rgb, cfg.height, cfg.width)
            grey = cv2.cvtColor(small, cv2.COLOR_RGB2GRAY).astype(np.float32)
            if last is not None and float(np.abs(grey - last).mean()) < cfg.static_threshold:
                continue  # the car stands still: no parallax to learn from
            last = grey
            out_path = cache / f"{len(kept):06d}.png"
            if not out_path.is_file():
                write_image(out_path, small)
            kept.append(out_path)
        if not kept:
            skips.add(path, "no decodable frame")
            continue
        seqs.append(Sequence(folder=source.name, image_dir=cache, frames=kept, K=K_out))
    return seqs


def check_frames(seq: Sequence, skips: Skips) -> bool:
    """Drop frames with an unreadable header; refuse a sequence with mixed resolutions.

    Reads only PNG headers (24 bytes), so this is cheap; a frame that decodes badly later
    is caught by the worker. Returns False if the whole sequence must be skipped.
    """
    good, first = [], None
    for p in seq.frames:
        try:
            size = png_size(p)
        except (OSError, ValueError) as err:
            skips.add(p, f"unreadable frame ({err})")
            continue
        if size is not None:
            if first is None:
                first = (p, size)
            elif size != first[1]:
                skips.add(
                    seq.image_dir,
                    f"mixed resolutions: {p.name} is {size[0]}x{size[1]}, "
                    f"{first[0].name} is {first[1][0]}x{first[1][1]}; whole sequence skipped",
                    "one calibration fits one resolution; split the sequence into separate folders",
                )
                return False
        good.append(p)
    seq.frames = good
    return True


def make_snippets(
    seq: Sequence, seq_length: int, skips: Skips, mix: dict[str, float] | None = None, mix_seed: int = 0
) -> list[Snippet]:
    """All snippets of a sequence: target at the middle, neighbours = adjacent kept frames.

    Frames removed as static are simply absent from ``seq.frames`` (neighbours skip them, as in
    the official loader); a gap in the file numbering (missing or unreadable file) ends a run,
    because frames across it are not consecutive. ``mix`` (variant -> probability) adds the still,
    slowed and reversed copies of :mod:`training.motion_mix` after each normal snippet.
    """
    half = seq_length // 2
    runs: list[list[Path]] = []
    prev = None
    for p in seq.frames:
        n = frame_number(p)
        if runs and prev is not None and n is not None and n - prev > 1 and not _static_gap(seq, prev, n):
            runs.append([])
        if not runs:
            runs.append([])
        runs[-1].append(p)
        prev = n
    out = []
    for run in runs:
        for i in range(half, len(run) - half):
            window = tuple(run[i - half : i + half + 1])
            tgt = window[half]
            depth = seq.depth_dir / f"{tgt.stem}.png" if seq.depth_dir is not None else None
            flow = seq.flow_dir / f"{tgt.stem}.png" if seq.flow_dir is not None else None
            poses = snippet_motion(seq.poses, window, half) if seq.poses is not None else None
            out.append(Snippet(seq.folder, tgt.stem, window, seq.K, seq.heldout, depth, flow, poses))
            name = f"{seq.folder} {tgt.stem}"
            for variant, probability in (mix or {}).items():
                copy = variant_window(run, i, half, variant)
                if copy is None or seq.heldout or not chosen(name, variant, probability, mix_seed):
                    continue
                # Static and reversed snippets' true motions follow from the window (identity, inverse);
                # a synthetic flow label is for t -> t+1 only, so a variant keeps none but the still one's.
                motion = snippet_motion(seq.poses, copy, half) if seq.poses is not None else None
                snip = Snippet(seq.folder, f"{tgt.stem}_{variant}", copy, seq.K, poses=motion, variant=variant)
                out.append(snip)
    if not out:
        longest = max((len(r) for r in runs), default=0)
        skips.add(
            seq.image_dir,
            f"sequence too short: at most {longest} consecutive usable frames, a snippet needs {seq_length}",
            "add frames or use a shorter --seq-length",
        )
    return out


def snippet_motion(camera_to_world: np.ndarray, window: tuple[Path, ...], half: int) -> np.ndarray | None:
    """(N_src, 4, 4) true motion target -> each source, ``inv(C_source) @ C_target`` (it maps a point
    in the target camera's frame into the source camera's: the POSE convention's direction), or
    None when a frame has no numbered pose."""
    numbers = [frame_number(p) for p in window]
    if any(n is None or n >= len(camera_to_world) for n in numbers):
        return None
    target = camera_to_world[numbers[half]]
    sources = [camera_to_world[n] for k, n in enumerate(numbers) if k != half]
    return np.stack([rigid_inverse(c) @ target for c in sources])


def _static_gap(seq: Sequence, prev: int, n: int) -> bool:
    """True if every frame between prev and n was removed as static (neighbours may skip those)."""
    return all(k in seq.static_removed for k in range(prev + 1, n))


# --------------------------------------------------------------------------- one sample (worker)
def sample_paths(out: Path, snip: Snippet) -> dict[str, Path]:
    base = out / snip.folder
    paths = {"jpg": base / f"{snip.frame}.jpg", "cam": base / f"{snip.frame}_cam.txt"}
    if snip.variant == "static":  # its labels are known: zero flow, identity motion; no depth
        return {**paths, "flow": base / f"{snip.frame}_flow.png", "pose": base / f"{snip.frame}_pose.txt"}
    if snip.depth_path is not None or snip.teacher_depth:
        paths["depth"] = base / f"{snip.frame}_depth.png"
    if snip.flow_path is not None or snip.teacher_flow:
        paths["flow"] = base / f"{snip.frame}_flow.png"
    if snip.poses is not None or snip.teacher_pose:
        paths["pose"] = base / f"{snip.frame}_pose.txt"
    return paths


def _read_truth(path: Path, kind: str, read, h0: int, w0: int):
    """``read(path)``: an array, or read_flow_kitti's (flow, valid), whose first array must be
    h0 x w0 like the image; GeoNetError naming the file otherwise."""
    truth = read(path)
    shape = (truth[0] if isinstance(truth, tuple) else truth).shape
    if shape[:2] != (h0, w0):
        raise InputError(path, f"{kind} is {shape[1]}x{shape[0]}, image {w0}x{h0}")
    return truth


def write_snippet(snip: Snippet, out: Path, height: int, width: int) -> tuple[str, Path | None, str | None]:
    """Read, resize and write one sample. Runs in a worker process.

    Everything is read and checked before the first write, and each file is written
    atomically, so a failure leaves either nothing new or complete files.

    Returns:
        ("written" | "exists" | "skipped", offending file or None, reason or None)
    """
    paths = sample_paths(out, snip)
    if all(p.is_file() for p in paths.values()):
        return "exists", None, None
    frames = []
    for p in snip.paths:
        try:
            frames.append(read_image(p))
        except GeoNetError as err:
            return "skipped", p, f"{err.problem} (needed by sample '{snip.name}')"
    h0, w0 = frames[len(frames) // 2].shape[:2]
    for p, f in zip(snip.paths, frames):
        if f.shape[:2] != (h0, w0):
            return (
                "skipped",
                p,
                (f"frame is {f.shape[1]}x{f.shape[0]} but the target is {w0}x{h0} (mixed resolutions in one snippet)"),
            )
    half = len(frames) // 2
    strip_frames = [resize(f, height, width) for f in frames]
    if snip.variant == "static":  # a still camera: the sources are noisy, jittered copies of the target
        strip_frames = [f if k == half else still_copy(f, snip.name, k) for k, f in enumerate(strip_frames)]
    strip = np.concatenate(strip_frames, axis=1)  # (H, seq*W, 3)
    ok, jpg = cv2.imencode(".jpg", cv2.cvtColor(strip, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    if not ok:
        return "skipped", snip.paths[len(frames) // 2], "JPEG encoding failed"
    # K is scaled by the target frame's own resize factors (official: zoom_x, zoom_y of the target).
    K = scale_intrinsics(snip.K, width / w0, height / h0)
    depth = flow = valid = None
    try:
        if snip.depth_path is not None:
            depth = _read_truth(snip.depth_path, "depth", read_depth_kitti, h0, w0)
            # Nearest keeps measured values (no blending of depth across edges / with 0 = none).
            depth = cv2.resize(depth, (width, height), interpolation=cv2.INTER_NEAREST)
        if snip.flow_path is not None:
            flow, valid = _read_truth(snip.flow_path, "flow", read_flow_kitti, h0, w0)
            flow, valid = resize_flow_gt(flow, valid, (height, width))
    except GeoNetError as err:
        return "skipped", err.path, err.problem
    poses = snip.poses
    if snip.variant == "static":  # labels known exactly
        flow, valid, poses = static_labels(len(frames) - 1, height, width)
    elif snip.teacher_flow:
        label = teacher_flow(strip_frames[half], strip_frames[half + 1], snip.teacher_flow)
        flow, valid = label.flow, label.valid
    if snip.teacher_pose and snip.variant != "static":
        # Full resolution: ORB finds few corners at 128 x 416. None (a failed pair): no pose label.
        poses = teacher_motion(frames, snip.K, half, snip.teacher_pose)
    if snip.teacher_depth and snip.variant != "static":
        # Full resolution, like the pose teacher; None (failed motion, too few pixels): no depth label.
        label = teacher_depth(frames[half], frames[half + 1], snip.K, snip.teacher_depth)
        if label is not None:
            depth = cv2.resize(label.depth, (width, height), interpolation=cv2.INTER_NEAREST)
    with atomic_write(paths["jpg"]) as tmp:
        tmp.write_bytes(jpg.tobytes())
    write_cam_txt(paths["cam"], K)
    if depth is not None:
        write_depth_kitti(paths["depth"], depth)
    if flow is not None:
        write_flow_kitti(paths["flow"], flow, valid)
    if poses is not None:
        write_kitti_poses(paths["pose"], poses)
    return "written", None, None


def _write_snippet_args(args):
    return write_snippet(*args)


# --------------------------------------------------------------------------- driver
def split_train_val(names: list[str], val_fraction: float, seed: int) -> tuple[list[str], list[str]]:
    """Each sample goes to val with probability val_fraction (as the official script), seeded.

    Names are sorted first so the split does not depend on directory listing order. If that
    leaves val empty while val_fraction > 0 and there are >= 2 samples, one sample is moved to
    val so a tiny dataset still has something to validate on.
    """
    names = sorted(names)
    rng = np.random.RandomState(seed)
    to_val = rng.random_sample(len(names)) < val_fraction
    train = [n for n, v in zip(names, to_val) if not v]
    val = [n for n, v in zip(names, to_val) if v]
    if not val and val_fraction > 0 and len(train) >= 2:
        val.append(train.pop(int(rng.randint(len(train)))))
    return train, val


def write_list(path: Path, names: list[str]) -> None:
    with atomic_write(path) as tmp:
        tmp.write_text("".join(n + "\n" for n in names))


def _check(cfg: PrepareConfig) -> tuple[int, str]:
    """Validate ``cfg``; returns (seq_length, split) with the per-kind defaults filled in."""
    if cfg.kind not in KINDS:
        raise InputError(None, f"unknown --kind {cfg.kind!r}", f"choose one of {', '.join(KINDS)}")
    if cfg.kind == "video" and Path(cfg.src).is_file():
        pass
    elif not Path(cfg.src).is_dir():
        raise InputError(
            cfg.src,
            "source folder not found" if cfg.kind != "video" else "video file or folder not found",
            PREPARE_HINT,
        )
    video_only = {"calib": cfg.calib is not None, "crop": cfg.crop is not None}
    if cfg.kind not in ("video", "frames") and any(video_only.values()):
        raise InputError(
            None,
            f"--{next(k for k, v in video_only.items() if v)} only applies to --kind video|frames",
            "the KITTI and synthetic layouts carry their calibration",
        )
    seq_length = cfg.seq_length or (5 if cfg.kind == "kitti_odom" else 3)
    if seq_length < 3 or seq_length % 2 == 0:
        raise InputError(None, f"--seq-length must be odd and >= 3, got {seq_length}", "use 3 (depth/flow) or 5 (pose)")
    split = cfg.split or DEFAULT_SPLIT[cfg.kind]
    if split not in VALID_SPLITS[cfg.kind]:
        raise InputError(
            None,
            f"--split {split} does not apply to --kind {cfg.kind}",
            f"choose one of {', '.join(VALID_SPLITS[cfg.kind])}",
        )
    if cfg.remove_static and cfg.kind != "kitti_raw":
        raise InputError(None, "--remove-static only applies to --kind kitti_raw", "drop the flag")
    if cfg.train_depth and cfg.kind != "synth":
        raise InputError(None, "--train-depth only applies to --kind synth", "real footage has no dense depth")
    if cfg.train_flow and cfg.kind != "synth":
        raise InputError(
            None, "--train-flow only applies to --kind synth", "label real footage with --teacher-flow dis"
        )
    if cfg.train_pose and cfg.kind not in ("kitti_odom", "synth"):
        raise InputError(None, "--train-pose only applies to --kind kitti_odom|synth", "the others have no true poses")
    chosen = (("flow", cfg.teacher_flow), ("pose", cfg.teacher_pose), ("depth", cfg.teacher_depth))
    teachers = [f"--teacher-{k}" for k, v in chosen if v]
    if teachers and cfg.kind == "synth":
        raise InputError(
            None, f"{teachers[0]} is for real footage", "synthetic scenes have --train-flow/--train-pose/--train-depth"
        )
    full_res = [t for t in teachers if t != "--teacher-flow"]
    if full_res and cfg.kind in ("video", "frames"):
        raise InputError(
            None,
            f"{full_res[0]} needs full-resolution frames (kitti_odom, kitti_raw)",
            f"video frames are cached at {cfg.height}x{cfg.width}, too small for two-view geometry",
        )
    if cfg.teacher_pose and cfg.train_pose:
        raise InputError(None, "--teacher-pose and --train-pose both write <frame>_pose.txt", "choose one")
    if (teachers or cfg.motion_mix) and TEST_DRIVE in Path(cfg.src).resolve().parts:
        raise InputError(cfg.src, "is the real-data test drive: never train on it", "label other footage")
    if cfg.height < 8 or cfg.width < 8 or cfg.workers < 1:
        raise InputError(
            None,
            f"need --height/--width >= 8 and --workers >= 1 (got {cfg.height}, {cfg.width}, {cfg.workers})",
            PREPARE_HINT,
        )
    return seq_length, split


def collect_snippets(cfg: PrepareConfig, seq_length: int, split: str, skips: Skips) -> list[Snippet]:
    """Every snippet of the source, in sequence order (frames limited, static frames removed)."""
    src = Path(cfg.src)
    if cfg.kind == "kitti_raw":
        seqs = collect_kitti_raw(src, split, skips)
    elif cfg.kind == "kitti_odom":
        seqs = collect_kitti_odom(src, split, skips, cfg.train_pose)
    elif cfg.kind in ("video", "frames"):
        seqs = collect_video(cfg, skips)  # --max-frames applied while decoding
    else:
        seqs = collect_synth(src, cfg.heldout, skips, cfg.train_depth, cfg.train_flow, cfg.train_pose)
    if cfg.max_frames is not None:
        for seq in seqs:
            seq.frames = seq.frames[: cfg.max_frames]
    if cfg.remove_static:
        remove_static_frames(seqs)
    snippets = [
        snip
        for seq in seqs
        if check_frames(seq, skips)
        for snip in make_snippets(seq, seq_length, skips, cfg.motion_mix, cfg.mix_seed)
    ]
    for snip in snippets:
        snip.teacher_flow, snip.teacher_pose, snip.teacher_depth = cfg.teacher_flow, cfg.teacher_pose, cfg.teacher_depth
    return snippets


def write_snippets(jobs: list[tuple], workers: int, desc: str):
    """Run :func:`write_snippet` over ``jobs``; yields (snippet, status, offending file, reason)."""
    bar = tqdm(total=len(jobs), desc=desc, unit="sample", disable=None)
    try:
        if workers <= 1:
            for job in jobs:
                yield job[0], *write_snippet(*job)
                bar.update(1)
            return
        with ProcessPoolExecutor(max_workers=workers) as pool:
            futures = {pool.submit(_write_snippet_args, job): job[0] for job in jobs}
            try:
                for fut in as_completed(futures):
                    yield futures[fut], *fut.result()
                    bar.update(1)
            except BaseException:
                pool.shutdown(wait=True, cancel_futures=True)
                raise
    finally:
        bar.close()


def prepare(cfg: PrepareConfig) -> PrepareResult:
    """Prepare one dataset; see the module docstring for the output. Returns what was done.

    Raises GeoNetError on a bad config, a missing source or when no sample could be made;
    inputs that are skipped (``cfg.strict`` off) are listed in the result.
    """
    seq_length, split = _check(cfg)
    src, out = Path(cfg.src), Path(cfg.out)
    skips = Skips(cfg.strict)
    snippets = collect_snippets(cfg, seq_length, split, skips)
    result = PrepareResult(out=out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(
            out, f"cannot create the output folder ({exc.strerror or exc})", "choose a writable --out"
        ) from None
    done: list[Snippet] = []
    jobs = [(snip, out, cfg.height, cfg.width) for snip in snippets]
    for snip, status, where, reason in write_snippets(jobs, cfg.workers, f"prepare {cfg.kind}"):
        if status == "skipped":
            skips.add(where or snip.paths[len(snip.paths) // 2], reason or "unknown error")
            continue
        done.append(snip)
        result.written += status == "written"
        result.existing += status == "exists"
    result.skipped = skips.items
    if not done:
        raise InputError(
            src,
            f"no sample could be made ({len(skips.items)} skipped)",
            "; ".join(str(s) for s in skips.items[:5]) or PREPARE_HINT,
        )
    result.heldout = sorted(s.name for s in done if s.heldout)
    result.train, result.val = split_train_val([s.name for s in done if not s.heldout], cfg.val_fraction, cfg.seed)
    write_list(out / "train.txt", result.train)
    write_list(out / "val.txt", result.val)
    if cfg.kind == "synth":
        write_list(out / "heldout.txt", result.heldout)
    return result


EPILOG = """\
kinds:
  kitti_raw   --src = a KITTI raw root (<date>/<drive>_sync/image_02/data/*.png, calibration in
              <date>/calib_cam_to_cam.txt) or one drive folder (calibration beside image_02 or in
              its parent). Cameras 02 and 03 both become sequences (<drive>_02, <drive>_03);
              K = P_rect_0X[:3,:3]. --split eigen (default) drops the 28 Eigen test scenes,
              --split stereo the 29 KITTI-2015 scenes (flow experiments); --remove-static drops
              the frames in training/kitti_lists/static_frames.txt before forming snippets.
      python -m training.prepare --kind kitti_raw --src ../shared/realdata/kitti_raw_2011_09_26_sfnd \\
          --out data/prepared_raw --split eigen
  kitti_odom  --src = an odometry root with sequences/XX/{image_2,calib.txt}; K = P2. Sequences with
              only greyscale image_0 use P0, converted to 3 channels. Default --seq-length 5;
              --split odom (default) leaves out the pose test sequences 09 and 10.
      python -m training.prepare --kind kitti_odom --src ../shared/realdata/kitti_odometry_00 \\
          --out data/prepared_odom
  video       --src = a video file or a folder of videos; --calib FILE (any format of
              geonet_infer.io.read_camera: K, distortion, image size). Frames are undistorted (same K)
              when the calibration has distortion, cropped to --crop X,Y,W,H (e.g. to cut a car
              bonnet), resized to HxW with K scaled, and a frame whose mean grey difference to the
              last kept one is below --static-threshold is dropped (a standing car). One sequence per
              video; the kept frames are cached in OUT/.frames/.
      python -m training.prepare --kind video --src ../shared/realdata/udacity_dashcam/challenge.mp4 \
          --calib ../shared/realdata/udacity_dashcam/calib_advanced_lane_lines.txt \
          --crop 0,229,1280,394 --out data/prepared_dashcam
  frames      the same for one folder of frames (sorted by name).
      python -m training.prepare --kind frames --src FRAMES_DIR --calib calib.txt --out data/prepared_frames
  synth       --src = the synthetic generator's output root (<seq>/image/*.png, depth/, calib.txt
              with "K: fx 0 cx 0 fy cy 0 0 1"). The last --heldout sequences (sorted by name) go to
              heldout.txt, with the target depth copied as <frame>_depth.png, never to train/val.
              --train-depth also copies the depth of train/val samples, for depth-supervised
              pre-training (python -m training.train --depth-supervision W); --train-flow writes
              the non-occluded flow to the next frame as <frame>_flow.png, for flow-supervised
              pre-training (python -m training.train --stage flow --flow-supervision W).
              --train-pose (synth, kitti_odom) writes the true motion target -> sources as
              <frame>_pose.txt, for python -m training.train --pose-supervision W.
      python -m training.prepare --kind synth --src data/synth --out data/prepared_synth --heldout 2

classical teachers (real footage, never the test drive kitti_raw_2011_09_26_sfnd; docs/training.md):
  --teacher-flow dis         DIS flow (medium) target -> next at HxW, forward-backward checked,
                             as <frame>_flow.png (any real kind)
  --teacher-pose orbvo       two-view ORB odometry target -> sources, unit steps, as
                             <frame>_pose.txt (kitti_odom, kitti_raw: full-resolution frames)
  --teacher-depth triangulate  the target's depth triangulated from DIS flow to the next frame and
                             the motion it implies, at full resolution, kept where the parallax is
                             >= 5 px and the flow is within 1 px of its epipolar line; resized to
                             HxW with nearest neighbour as <frame>_depth.png (kitti_odom, kitti_raw).
                             No metric scale (monocular): each label is scaled to a median of 10,
                             which training.train --depth-supervision (scale invariant) ignores. A
                             sample with under 5 % of its pixels labelled gets no depth file.
      python -m training.prepare --kind kitti_odom --src data/real_odom_src --out data/t_odom_depth \\
          --seq-length 3 --val-fraction 0 --teacher-flow dis --teacher-depth triangulate

Skipped inputs (unreadable frames, missing calibration keys, too-short or mixed-resolution
sequences) are listed at the end; --strict makes the first one an error. Re-running resumes.
"""


def build_parser() -> argparse.ArgumentParser:
    D = PrepareConfig  # argparse defaults are the config's defaults
    p = argparse.ArgumentParser(
        prog="python -m training.prepare",
        description="Cut image sequences into GeoNet training samples: seq_length frames resized to "
        "HxW side by side in one JPEG, the target's intrinsics in <frame>_cam.txt, and "
        "train.txt / val.txt lists.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--kind", required=True, choices=KINDS, help="input layout (see below)")
    p.add_argument("--src", required=True, type=Path, help="input root (see below)")
    p.add_argument("--out", required=True, type=Path, help="output folder (created; re-running resumes)")
    p.add_argument(
        "--seq-length",
        type=int,
        default=D.seq_length,
        help="frames per sample, odd: 3 (default) or 5 (kitti_odom default)",
    )
    p.add_argument("--height", type=int, default=D.height, help="frame height (default %(default)s)")
    p.add_argument("--width", type=int, default=D.width, help="frame width (default %(default)s)")
    p.add_argument(
        "--split",
        choices=SPLITS,
        default=D.split,
        help="test scenes to leave out: eigen|stereo (kitti_raw, default eigen), odom "
        "(kitti_odom: sequences 09, 10; the default), none",
    )
    p.add_argument("--remove-static", action="store_true", help="kitti_raw: drop static frames first")
    p.add_argument("--workers", type=int, default=D.workers, help="processes (default %(default)s)")
    p.add_argument(
        "--val-fraction",
        type=float,
        default=D.val_fraction,
        help="probability of a sample going to val.txt (default %(default)s)",
    )
    p.add_argument(
        "--seed", type=int, default=D.seed, help="seed of the train/val split (default: the official %(default)s)"
    )
    p.add_argument(
        "--heldout",
        type=int,
        default=D.heldout,
        help="synth: last N sequences held out for evaluation (default %(default)s)",
    )
    p.add_argument(
        "--train-depth",
        action="store_true",
        help="synth: also write the ground-truth depth of train/val samples (for training.train --depth-supervision)",
    )
    p.add_argument(
        "--train-flow",
        action="store_true",
        help="synth: also write the ground-truth flow to the next frame of train/val samples "
        "(for training.train --stage flow --flow-supervision)",
    )
    p.add_argument(
        "--train-pose",
        action="store_true",
        help="kitti_odom (the dev kit's poses/XX.txt) and synth (poses.txt): also write the true motion "
        "target -> sources of train/val samples (for training.train --pose-supervision)",
    )
    p.add_argument(
        "--teacher-flow",
        choices=TEACHER_FLOWS,
        default=D.teacher_flow,
        help="real footage: label the flow target -> next frame with OpenCV DIS (medium, forward-backward "
        "checked) as <frame>_flow.png (for training.train --stage flow --flow-supervision)",
    )
    p.add_argument(
        "--teacher-pose",
        choices=TEACHER_POSES,
        default=D.teacher_pose,
        help="real footage: label the motion target -> sources with two-view ORB odometry (unit steps) as "
        "<frame>_pose.txt (for training.train --pose-supervision, which aligns the scale)",
    )
    p.add_argument(
        "--teacher-depth",
        choices=TEACHER_DEPTHS,
        default=D.teacher_depth,
        help="kitti_odom, kitti_raw: label the target depth triangulated from DIS flow and ORB motion to the "
        "next frame as <frame>_depth.png, without metric scale (see below; for training.train --depth-supervision)",
    )
    p.add_argument(
        "--max-frames", type=int, default=D.max_frames, help="use only the first N frames of each sequence (quick runs)"
    )
    p.add_argument("--strict", action="store_true", help="stop at the first bad input instead of skipping it")
    p.add_argument("--calib", type=Path, default=D.calib, help="video/frames: the camera calibration file")
    p.add_argument(
        "--crop",
        type=_crop,
        default=D.crop,
        metavar="X,Y,W,H",
        help="video/frames: the region kept after undistortion, in input pixels",
    )
    p.add_argument(
        "--static-threshold",
        type=float,
        default=D.static_threshold,
        help="video/frames: drop frames whose mean grey difference to the last kept one is "
        "below this, in levels of 255 at HxW (default %(default)s; 0 keeps every frame)",
    )
    p.add_argument(
        "--motion-mix",
        type=_motion_mix,
        default={},
        metavar="VARIANT=P,...",
        help="add still (static), twice-as-fast (stride2) and time-reversed (reverse) copies of each "
        "train/val snippet, each with probability P, e.g. static=0.3,stride2=0.3,reverse=0.3; still copies "
        "are labelled zero flow and identity motion (training.motion_mix, docs/training.md)",
    )
    p.add_argument("--mix-seed", type=int, default=D.mix_seed, help="seed of the --motion-mix draws")
    return p


def _motion_mix(text: str) -> dict[str, float]:
    try:
        return parse_motion_mix(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None


def _crop(text: str) -> tuple[int, int, int, int]:
    try:
        x, y, w, h = (int(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected X,Y,W,H in pixels, got {text!r}") from None
    return x, y, w, h


def main(argv=None) -> int:
    """Exit codes: 0 every input used, 1 some inputs skipped (listed), 2 bad usage or input."""
    args = build_parser().parse_args(argv)
    if not logging.getLogger().handlers:
        logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    try:
        result = prepare(PrepareConfig(**vars(args)))
    except GeoNetError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(result.summary())
    return 1 if result.skipped else 0


if __name__ == "__main__":
    sys.exit(main())

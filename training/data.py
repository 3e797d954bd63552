"""Training data: reads the folder written by ``python -m training.prepare``.

Augmentation follows the official data loader (spec §6) with two documented differences:
one random draw per *sample* (the official draws once per batch), and the intrinsics are
scaled by the exact resize ratio (out_w / W) rather than by the drawn factor.
"""

from __future__ import annotations

import random
from pathlib import Path

import cv2
import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset

from geonet_infer.conventions import REFERENCE_HEIGHT, REFERENCE_WIDTH, scale_intrinsics
from geonet_infer.core.cascade import snippet_indices
from geonet_infer.errors import GeoNetError, InputError
from geonet_infer.eval.metrics import resize_flow_gt
from geonet_infer.io import read_cam_txt, read_depth_kitti, read_flow_kitti, read_image, read_kitti_poses

SPLITS = ("train", "val", "heldout")
PREPARE_CMD = "run python -m training.prepare --kind synth|kitti_raw|kitti_odom --src DIR --out ROOT first"

# Augmentation ranges (official data_loader.py).
SCALE_RANGE = (1.0, 1.15)
COLOR_PROB = 0.5
GAMMA_RANGE = (0.8, 1.2)
BRIGHTNESS_RANGE = (0.5, 2.0)
GAIN_RANGE = (0.8, 1.2)


# --------------------------------------------------------------------------- augmentation
def random_scale_crop(
    frames: np.ndarray, K: np.ndarray, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, dict]:
    """Scale x and y independently by U[1, 1.15], then crop back to the input size.

    One draw is shared by all frames, so the geometry between them is unchanged.

    Args:
        frames: (N, H, W, 3) float32 in [0, 1].
        K: (3, 3) intrinsics at H x W.
        rng: numpy Generator (per-sample).
    Returns:
        frames (N, H, W, 3) float32, K (3, 3) float64 for the cropped frames,
        info {"sx", "sy", "x0", "y0"}: the exact resize ratios and the crop offset.
    """
    n, h, w, _ = frames.shape
    fx, fy = rng.uniform(*SCALE_RANGE, size=2)
    out_w, out_h = int(w * fx), int(h * fy)  # floor, as tf.cast(int32) in the official code
    # cv2's INTER_AREA on enlargement degenerates to near-nearest-neighbour (blocky); TF's
    # resize_area interpolates, and bilinear is the closest cv2 filter for a <= 15 % zoom.
    scaled = np.stack([cv2.resize(f, (out_w, out_h), interpolation=cv2.INTER_LINEAR) for f in frames])
    y0 = int(rng.integers(0, out_h - h + 1))
    x0 = int(rng.integers(0, out_w - w + 1))
    cropped = scaled[:, y0 : y0 + h, x0 : x0 + w]
    # Exact ratios of the resize that was done (the official uses the drawn factor; < 0.3 % apart).
    sx, sy = out_w / w, out_h / h
    K = scale_intrinsics(K, sx, sy)
    K[0, 2] -= x0  # cropping moves the principal point, focal lengths stay
    K[1, 2] -= y0
    return np.ascontiguousarray(cropped), K, {"sx": sx, "sy": sy, "x0": x0, "y0": y0}


def random_color(frames: np.ndarray, rng: np.random.Generator, share_gain: bool) -> np.ndarray:
    """Gamma U[0.8, 1.2], brightness U[0.5, 2], per-channel gain U[0.8, 1.2], clip to [0, 1].

    Gamma and brightness are shared by all frames. The official code draws the gain for all
    3*N channels of the stacked sample, so every frame gets its own gain (``share_gain=False``
    reproduces that quirk); ``share_gain=True`` uses one gain for all frames.

    Args:
        frames: (N, H, W, 3) float32 in [0, 1].
    Returns:
        (N, H, W, 3) float32 in [0, 1].
    """
    n = frames.shape[0]
    gamma = rng.uniform(*GAMMA_RANGE)
    brightness = rng.uniform(*BRIGHTNESS_RANGE)
    gains = rng.uniform(*GAIN_RANGE, size=(1 if share_gain else n, 1, 1, 3))
    out = np.power(frames, gamma) * brightness * gains
    return np.clip(out, 0.0, 1.0).astype(np.float32)


def augment(
    frames: np.ndarray,
    K: np.ndarray,
    rng: np.random.Generator,
    share_gain: bool,
    depth: np.ndarray | None = None,
    flow: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Official training augmentation: scale + crop (always), colour with p = 0.5.

    Args:
        frames: (N, H, W, 3) float32 in [0, 1]; K: (3, 3).
        depth: optional (H, W) target depth (0 = none), given the same scale and crop.
        flow: optional (H, W, 3) target flow (u, v px, valid 0/1), given the same scale and crop
            (vectors scaled by the resize ratios; cropping does not change them).
    Returns:
        frames (N, H, W, 3) float32 in [0, 1], K (3, 3), depth (H, W) or None, flow (H, W, 3) or None.
    """
    h, w = frames.shape[1:3]
    frames, K, crop = random_scale_crop(frames, K, rng)
    out_w, out_h = round(w * crop["sx"]), round(h * crop["sy"])
    window = np.s_[crop["y0"] : crop["y0"] + h, crop["x0"] : crop["x0"] + w]
    if depth is not None:
        # Nearest: no depth blended across object edges or with 0 = none.
        depth = cv2.resize(depth, (out_w, out_h), interpolation=cv2.INTER_NEAREST)
        depth = np.ascontiguousarray(depth[window])
    if flow is not None:
        uv, valid = resize_flow_gt(flow[..., :2], flow[..., 2] > 0, (out_h, out_w))
        flow = np.ascontiguousarray(np.concatenate([uv, valid[..., None].astype(np.float32)], axis=2)[window])
    if rng.uniform() < COLOR_PROB:
        frames = random_color(frames, rng, share_gain)
    return frames, K, depth, flow


# --------------------------------------------------------------------------- reading
def read_list(path: Path) -> list[str]:
    """Lines "<folder> <frame>" -> names; GeoNetError on a malformed line."""
    names = []
    for lineno, line in enumerate(path.read_text().splitlines(), 1):
        parts = line.split()
        if not parts:
            continue
        if len(parts) != 2:
            raise InputError(path, f"line {lineno} is not '<folder> <frame>': {line.strip()[:60]!r}", PREPARE_CMD)
        names.append(f"{parts[0]} {parts[1]}")
    return names


def read_cam(path: Path) -> np.ndarray:
    """<frame>_cam.txt "fx,0.,cx,0.,fy,cy,0.,0.,1." -> (3, 3) float64 (:func:`geonet_infer.io.read_cam_txt`)."""
    try:
        return read_cam_txt(path)
    except GeoNetError as err:
        raise InputError(err.path, err.problem, PREPARE_CMD) from None


class SequenceDataset(Dataset):
    """GeoNet training samples from a ``training.prepare`` folder.

    Item keys:
        ``target``      float32 (3, H, W) in [0, 1], the middle frame.
        ``sources``     float32 (N_src, 3, H, W) in [0, 1], temporal order:
                        seq 3 -> [t-1, t+1]; seq 5 -> [t-2, t-1, t+1, t+2].
        ``intrinsics``  float32 (3, 3), K at H x W (after augmentation).
        ``name``        str "<folder> <frame>".
        ``depth_gt``    float32 (1, H, W) metres, 0 = none; split "heldout" when
                        ``<frame>_depth.png`` exists, and every split with ``load_depth``
                        (all zeros for a sample without that file, e.g. real footage).
        ``flow_gt``     float32 (3, H, W): flow target -> next frame (u, v px) and valid 0/1,
                        with ``load_flow`` (all zeros without ``<frame>_flow.png``).
        ``pose_gt``     float32 (N_src, 4, 4): true motion target -> each source (POSE
                        convention, metres), with ``load_pose`` (all zeros without
                        ``<frame>_pose.txt``). Augmentation (scale, crop, colour) leaves it as is.
        ``twin_target``, ``twin_sources``, ``has_twin`` with ``load_twins``: for a ``stride2`` copy
                        (``<frame>_stride2``, ``training.motion_mix``) whose normal snippet
                        ``<frame>`` is in the folder, that snippet's frames under the same
                        augmentation and ``has_twin`` True; otherwise the sample's own frames and
                        False (batches mix both). For ``GeoNet.rigid_loss``'s stride term.
        ``next_target``, ``next_sources``, ``has_next`` with ``load_next``: for a plain snippet
                        (``<frame>`` of digits) whose next target's snippet (``<frame + 1>``) is in
                        the same split, that snippet's frames under the same augmentation and
                        ``has_next`` True; otherwise the sample's own frames and False. For
                        ``GeoNet.rigid_loss``'s overlap term.

    Augmentation (``augment=True`` and split "train" only) draws once per sample from an RNG
    seeded by (seed, epoch, index), so an item is reproducible whatever worker loads it; call
    :meth:`set_epoch` before each epoch to get new draws. Samples listed in ``heldout.txt``
    are refused for "train" and "val".
    """

    def __init__(
        self,
        root,
        split: str = "train",
        seq_length: int = 3,
        height: int = REFERENCE_HEIGHT,
        width: int = REFERENCE_WIDTH,
        augment: bool = True,
        share_color_gain: bool = False,
        seed: int = 0,
        load_depth: bool = False,
        load_flow: bool = False,
        load_pose: bool = False,
        load_twins: bool = False,
        load_next: bool = False,
    ):
        if split not in SPLITS:
            raise InputError(None, f"unknown split {split!r}", f"choose one of {', '.join(SPLITS)}")
        if seq_length < 3 or seq_length % 2 == 0:
            raise InputError(None, f"seq_length must be odd and >= 3, got {seq_length}", "use 3 or 5")
        self.root = Path(root)
        self.split = split
        self.seq_length = seq_length
        self.height, self.width = height, width
        self.augment = augment and split == "train"
        self.share_color_gain = share_color_gain
        self.seed = seed
        self.load_depth = load_depth or split == "heldout"
        self.load_flow = load_flow
        self.load_pose = load_pose
        self.load_twins = load_twins
        self.load_next = load_next
        self.epoch = 0

        if not self.root.is_dir():
            raise InputError(self.root, "dataset folder not found", PREPARE_CMD)
        list_path = self.root / f"{split}.txt"
        if not list_path.is_file():
            hint = ("only --kind synth writes held-out samples; " + PREPARE_CMD) if split == "heldout" else PREPARE_CMD
            raise InputError(list_path, f"no {split}.txt in the dataset folder", hint)
        self.names = read_list(list_path)
        self._listed = set(self.names)
        if not self.names:
            raise InputError(
                list_path, f"the {split} split is empty", "prepare more data or a larger --val-fraction; " + PREPARE_CMD
            )
        heldout_path = self.root / "heldout.txt"
        if split != "heldout" and heldout_path.is_file():
            leaked = set(self.names) & set(read_list(heldout_path))
            if leaked:
                raise InputError(
                    list_path,
                    f"{len(leaked)} samples are also in heldout.txt "
                    f"(e.g. {sorted(leaked)[0]!r}); held-out data must never be trained on",
                    "re-run python -m training.prepare into a fresh folder",
                )

    def __len__(self) -> int:
        return len(self.names)

    def set_epoch(self, epoch: int) -> None:
        """New augmentation draws per epoch (deterministic given seed and epoch)."""
        self.epoch = int(epoch)

    def load_frames(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """-> frames (seq_length, H, W, 3) float32 in [0, 1], K (3, 3) float64 at H x W."""
        folder, frame = name.split(" ")
        jpg = self.root / folder / f"{frame}.jpg"
        img = read_image(jpg)  # raises GeoNetError naming the file if missing/corrupt
        h, w = self.height, self.width
        if img.shape[:2] != (h, self.seq_length * w):
            held = (
                f"it holds {img.shape[1] // w} frames of width {w}; "
                if img.shape[1] % w == 0 and img.shape[0] == h
                else ""
            )
            raise InputError(
                jpg,
                f"snippet is {img.shape[1]}x{img.shape[0]} but seq_length={self.seq_length} at "
                f"{h}x{w} needs {self.seq_length * w}x{h}",
                f"{held}pass the seq_length/height/width used by training.prepare, "
                f"or re-run it with --seq-length {self.seq_length}",
            )
        frames = img.reshape(h, self.seq_length, w, 3).transpose(1, 0, 2, 3)  # split the horizontal strip
        frames = frames.astype(np.float32) / 255.0
        return frames, read_cam(self.root / folder / f"{frame}_cam.txt")

    def _read_truth(self, name: str, kind: str, read) -> np.ndarray | None:
        """-> ``read(<frame>_<kind>.png)`` as float32, its first two axes checked against H x W, or
        None without the file."""
        folder, frame = name.split(" ")
        path = self.root / folder / f"{frame}_{kind}.png"
        if not path.is_file():
            return None
        truth = read(path)
        if truth.shape[:2] != (self.height, self.width):
            raise InputError(
                path, f"{kind} is {truth.shape[1]}x{truth.shape[0]}, expected {self.width}x{self.height}", PREPARE_CMD
            )
        return truth.astype(np.float32)

    def load_depth_gt(self, name: str) -> np.ndarray | None:
        """-> (H, W) float32 target depth in metres (0 = none), or None without ``<frame>_depth.png``."""
        return self._read_truth(name, "depth", read_depth_kitti)

    def load_flow_gt(self, name: str) -> np.ndarray | None:
        """-> (H, W, 3) float32 flow target -> next frame (u, v px, valid 0/1), or None without
        ``<frame>_flow.png``."""
        return self._read_truth(name, "flow", lambda path: np.dstack(read_flow_kitti(path)))

    def load_pose_gt(self, name: str) -> np.ndarray | None:
        """-> (N_src, 4, 4) float32 true motion target -> sources, or None without ``<frame>_pose.txt``."""
        folder, frame = name.split(" ")
        path = self.root / folder / f"{frame}_pose.txt"
        if not path.is_file():
            return None
        poses = read_kitti_poses(path)
        if len(poses) != self.seq_length - 1:
            raise InputError(path, f"{len(poses)} poses, expected one per source ({self.seq_length - 1})", PREPARE_CMD)
        return poses.astype(np.float32)

    def _twin_of(self, name: str) -> str | None:
        """The normal snippet of a ``stride2`` copy's target, if the folder holds it."""
        folder, frame = name.split(" ")
        base = frame.removesuffix("_stride2")
        if base == frame or not (self.root / folder / f"{base}.jpg").is_file():
            return None
        return f"{folder} {base}"

    def _next_of(self, name: str) -> str | None:
        """The snippet of the next target in the same folder, if this split lists it (so a held-out
        or other split's snippet is never loaded)."""
        folder, frame = name.split(" ")
        if not frame.isdigit():  # motion-mix copies (_static, _stride2, _reverse) have no neighbour
            return None
        following = f"{folder} {int(frame) + 1:0{len(frame)}d}"
        return following if following in self._listed else None

    def _split(self, frames: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        """(seq_length, H, W, 3) -> target (3, H, W), sources (N_src, 3, H, W) in temporal order."""
        chw = torch.from_numpy(np.ascontiguousarray(frames.transpose(0, 3, 1, 2)))
        order = snippet_indices(self.seq_length // 2, self.seq_length, self.seq_length)  # [target] + sources
        return chw[order[0]], chw[order[1:]]

    def __getitem__(self, index: int) -> dict:
        name = self.names[index]
        frames, K = self.load_frames(name)
        depth = self.load_depth_gt(name) if self.load_depth else None
        flow = self.load_flow_gt(name) if self.load_flow else None
        twin = self._twin_of(name) if self.load_twins else None
        twin_frames = None if twin is None else self.load_frames(twin)[0]
        following = self._next_of(name) if self.load_next else None
        next_frames = None if following is None else self.load_frames(following)[0]
        if self.augment:
            draws = [self.seed, self.epoch, index]
            # the partners get the same draws: only the frames' speed (twin) or time (next) differs
            if twin_frames is not None:
                twin_frames = augment(twin_frames, K, np.random.default_rng(draws), self.share_color_gain)[0]
            if next_frames is not None:
                next_frames = augment(next_frames, K, np.random.default_rng(draws), self.share_color_gain)[0]
            frames, K, depth, flow = augment(
                frames, K, np.random.default_rng(draws), self.share_color_gain, depth, flow
            )
        target, sources = self._split(frames)
        item = {
            "target": target,
            "sources": sources,
            "intrinsics": torch.from_numpy(K.astype(np.float32)),
            "name": name,
        }
        if self.load_twins:
            item["twin_target"], item["twin_sources"] = (
                (target, sources) if twin_frames is None else self._split(twin_frames)
            )
            item["has_twin"] = torch.tensor(twin_frames is not None)
        if self.load_next:
            item["next_target"], item["next_sources"] = (
                (target, sources) if next_frames is None else self._split(next_frames)
            )
            item["has_next"] = torch.tensor(next_frames is not None)
        if depth is None and self.load_depth and self.split != "heldout":
            depth = np.zeros((self.height, self.width), np.float32)  # batches mix samples with and without
        if depth is not None:
            item["depth_gt"] = torch.from_numpy(depth[None])
        if self.load_flow:
            if flow is None:
                flow = np.zeros((self.height, self.width, 3), np.float32)
            item["flow_gt"] = torch.from_numpy(np.ascontiguousarray(flow.transpose(2, 0, 1)))
        if self.load_pose:
            poses = self.load_pose_gt(name)
            item["pose_gt"] = torch.from_numpy(
                poses if poses is not None else np.zeros((self.seq_length - 1, 4, 4), np.float32)
            )
        return item


# --------------------------------------------------------------------------- loader
def _seed_worker(worker_id: int) -> None:
    """Seed the global RNGs of a loader worker from torch's per-worker seed (for any code that
    uses them; our augmentation has its own per-item RNG) and keep OpenCV single-threaded so
    workers do not oversubscribe the CPU."""
    seed = torch.initial_seed() % 2**32
    np.random.seed(seed)
    random.seed(seed)
    cv2.setNumThreads(1)


LOADER_TIMEOUT_S = 300  # a batch takes well under a second to load: 5 minutes without one is a hang


def make_loader(
    dataset: Dataset,
    batch_size: int,
    shuffle: bool,
    num_workers: int = 0,
    seed: int = 0,
    drop_last: bool = False,
    sampler=None,
) -> DataLoader:
    """DataLoader whose shuffling order is fixed by ``seed`` (seeded torch.Generator).

    ``sampler`` (an iterable of indices, e.g. a DistributedSampler's) replaces shuffling; pass
    ``shuffle=False`` with it. ``seed`` still fixes the workers' base seeds.
    Batches are dicts of the item keys with a leading batch dimension; "name" becomes a list.
    """
    generator = torch.Generator()
    generator.manual_seed(seed)
    workers = {}
    if num_workers > 0:
        # Workers come from a forkserver, not fork(): a new loader is made every epoch, by then the
        # trainer holds running threads (torch's OpenMP pool, tqdm's monitor) and a fork() of a
        # threaded process can leave a lock held in the child forever (issue 46: a worker idle for
        # 8 minutes at an epoch boundary). LOADER_TIMEOUT_S turns any other hang into an error.
        workers = {"multiprocessing_context": "forkserver", "timeout": LOADER_TIMEOUT_S}
    return DataLoader(
        dataset,
        batch_size=batch_size,
        shuffle=shuffle,
        sampler=sampler,
        num_workers=num_workers,
        generator=generator,
        worker_init_fn=_seed_worker,
        drop_last=drop_last,
        **workers,
    )

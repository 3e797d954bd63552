"""Camera trajectories: KITTI odometry poses (3x4 per line) and TUM trajectories, quaternion helpers."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from geonet_infer.errors import InputError
from geonet_infer.io.atomic import atomic_write

__all__ = [
    "read_kitti_poses",
    "write_kitti_poses",
    "rotation_to_quaternion",
    "quaternion_to_rotation",
    "write_tum_poses",
    "read_tum_poses",
]


def _to_4x4(mats34: np.ndarray) -> np.ndarray:
    n = mats34.shape[0]
    out = np.zeros((n, 4, 4), dtype=np.float64)
    out[:, :3, :] = mats34
    out[:, 3, 3] = 1.0
    return out


def read_kitti_poses(path) -> np.ndarray:
    """Read KITTI odometry poses -> (N, 4, 4) float64 camera-to-world matrices."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "pose file not found", "check the path")
    try:
        with warnings.catch_warnings():  # an empty file: the error below says so, not numpy's warning
            warnings.simplefilter("ignore", UserWarning)
            vals = np.loadtxt(path, dtype=np.float64, ndmin=2)
    except ValueError as err:
        raise InputError(path, f"could not parse poses ({err})", "expected 12 numbers per line") from None
    if vals.size == 0 or vals.shape[1] != 12:
        raise InputError(
            path,
            f"expected 12 numbers per line, got shape {vals.shape}",
            "KITTI odometry poses are row-major 3x4 camera-to-world matrices",
        )
    return _to_4x4(vals.reshape(-1, 3, 4))


def write_kitti_poses(path, poses: np.ndarray) -> None:
    """Write (N, 4, 4) (or (N, 3, 4)) camera-to-world poses, 12 values per line."""
    poses = np.asarray(poses, dtype=np.float64)
    rows = poses[:, :3, :4].reshape(-1, 12)
    text = "".join(" ".join(f"{v:.9e}" for v in r) + "\n" for r in rows)
    with atomic_write(path) as tmp:
        tmp.write_text(text)


def rotation_to_quaternion(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation -> (..., 4) unit quaternion (qx, qy, qz, qw), qw >= 0.

    Shepperd's method: pick the largest of (w, x, y, z) to divide by, which is
    stable for all rotations (incl. 180 degrees).
    """
    R = np.asarray(R, dtype=np.float64)
    flat = R.reshape(-1, 3, 3)
    q = np.empty((flat.shape[0], 4))
    for i, m in enumerate(flat):
        tr = np.trace(m)
        cands = [tr, m[0, 0], m[1, 1], m[2, 2]]
        k = int(np.argmax(cands))
        if k == 0:
            s = np.sqrt(max(tr + 1.0, 0.0)) * 2
            q[i] = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s]
        elif k == 1:
            s = np.sqrt(max(1.0 + m[0, 0] - m[1, 1] - m[2, 2], 0.0)) * 2
            q[i] = [0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s]
        elif k == 2:
            s = np.sqrt(max(1.0 + m[1, 1] - m[0, 0] - m[2, 2], 0.0)) * 2
            q[i] = [(m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s]
        else:
            s = np.sqrt(max(1.0 + m[2, 2] - m[0, 0] - m[1, 1], 0.0)) * 2
            q[i] = [(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s, (m[1, 0] - m[0, 1]) / s]
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[q[:, 3] < 0] *= -1
    return q.reshape(R.shape[:-2] + (4,))


def quaternion_to_rotation(q: np.ndarray) -> np.ndarray:
    """(..., 4) quaternion (qx, qy, qz, qw), any norm > 0 -> (..., 3, 3) rotation."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = np.moveaxis(q, -1, 0)
    R = np.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - z * w),
            2 * (x * z + y * w),
            2 * (x * y + z * w),
            1 - 2 * (x * x + z * z),
            2 * (y * z - x * w),
            2 * (x * z - y * w),
            2 * (y * z + x * w),
            1 - 2 * (x * x + y * y),
        ],
        axis=-1,
    )
    return R.reshape(q.shape[:-1] + (3, 3))


def write_tum_poses(path, timestamps: np.ndarray, poses: np.ndarray) -> None:
    """Write TUM trajectory lines ``time tx ty tz qx qy qz qw``.

    Args:
        timestamps: (N,) seconds.
        poses: (N, 4, 4) or (N, 3, 4) pose matrices (TUM convention: camera-to-world).
    """
    poses = np.asarray(poses, dtype=np.float64)
    timestamps = np.asarray(timestamps, dtype=np.float64).reshape(-1)
    if len(timestamps) != len(poses):
        raise ValueError(f"{len(timestamps)} timestamps for {len(poses)} poses")
    q = rotation_to_quaternion(poses[:, :3, :3])
    t = poses[:, :3, 3]
    lines = [f"{ts:.6f} " + " ".join(f"{v:.9f}" for v in (*ti, *qi)) + "\n" for ts, ti, qi in zip(timestamps, t, q)]
    with atomic_write(path) as tmp:
        tmp.write_text("".join(lines))


def read_tum_poses(path) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM trajectory -> (timestamps (N,) float64, poses (N, 4, 4) float64).

    Lines starting with '#' and blank lines are skipped.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "trajectory file not found", "check the path")
    rows = []
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:  # found by tests/runtime/io/test_fuzz_parsers.py
        raise InputError(path, "not a text trajectory file", "is this a TUM trajectory?") from None
    for lineno, line in enumerate(text.splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.replace(",", " ").split()
        try:
            vals = [float(p) for p in parts]
        except ValueError:
            vals = []
        if len(vals) != 8:
            raise InputError(
                path, f"line {lineno}: expected 8 numbers 'time tx ty tz qx qy qz qw'", "is this a TUM trajectory?"
            )
        rows.append(vals)
    if not rows:
        raise InputError(path, "no poses in file", "is this a TUM trajectory?")
    a = np.array(rows)
    poses = np.tile(np.eye(4), (len(a), 1, 1))
    poses[:, :3, :3] = quaternion_to_rotation(a[:, 4:8])
    poses[:, :3, 3] = a[:, 1:4]
    return a[:, 0], poses

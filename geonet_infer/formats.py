"""File formats shared by training, evaluation, the runtime and the synthetic data.

numpy + OpenCV only. Every writer goes through :func:`atomic_write`, so a crash
never leaves a half-written file where a reader would trust it. Every reader
raises :class:`~geonet_infer.errors.GeoNetInputError` naming the file.

Encodings (see ``docs/synthetic_data.md``):

* Images: 8-bit RGB in memory (OpenCV's BGR order only inside this module).
* KITTI flow PNG: 16-bit, 3 channels, R = u*64 + 2**15, G = v*64 + 2**15,
  B = 1 valid / 0 invalid; invalid pixels are written as (0, 0, 0).
* KITTI depth PNG: 16-bit, 1 channel, round(depth_m * 256); 0 = no measurement.
* Middlebury ``.flo``: float32 tag 202021.25, int32 width, int32 height,
  then interleaved (u, v) float32, little-endian, row-major.
* KITTI odometry poses: 12 values per line, row-major 3x4 camera-to-world.
* TUM poses: ``time tx ty tz qx qy qz qw`` (Hamilton quaternion, w last).
* KITTI calibration: ``key: v1 v2 ...`` lines; our own files hold
  ``K: fx 0 cx 0 fy cy 0 0 1`` (row-major 3x3).
"""
from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np

from geonet_infer.errors import GeoNetInputError


FLOW_SCALE = 64.0  # KITTI flow: 1/64 px steps
FLOW_OFFSET = 2 ** 15
DEPTH_SCALE = 256.0  # KITTI depth: 1/256 m steps
FLO_MAGIC = 202021.25


# --------------------------------------------------------------------------- atomic writes
@contextlib.contextmanager
def atomic_write(path) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; rename it onto ``path`` on success.

    The temp file lives in the same directory (so the rename is atomic on POSIX)
    and keeps the same suffix (so cv2.imwrite picks the right encoder). If the
    body raises, the temp file is deleted and ``path`` is left untouched.
    Parent directories are created.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=path.suffix or ".tmp")
    os.close(fd)
    tmp = Path(tmp)
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        raise


def _imwrite(path: Path, array: np.ndarray) -> None:
    """cv2.imwrite that raises instead of returning False."""
    if not cv2.imwrite(str(path), array):
        raise GeoNetInputError(path, "OpenCV could not write this image", "check the suffix and that the folder is writable")


def _imread(path, flags: int = cv2.IMREAD_UNCHANGED) -> np.ndarray:
    path = Path(path)
    if not path.is_file():
        raise GeoNetInputError(path, "image not found", "check the path")
    img = cv2.imread(str(path), flags)
    if img is None:
        raise GeoNetInputError(path, "OpenCV could not decode this image", "is it a valid PNG/JPEG file?")
    return img


# --------------------------------------------------------------------------- RGB images
def read_image(path) -> np.ndarray:
    """Read an image as uint8 RGB.

    Returns:
        (H, W, 3) uint8, RGB order. Grey images are expanded to 3 channels,
        16-bit images are reduced to 8 bits by OpenCV, alpha is dropped.
    """
    return cv2.cvtColor(_imread(path, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)


def write_image(path, rgb: np.ndarray) -> None:
    """Write (H, W, 3) uint8 RGB (or (H, W) grey) atomically; format from the suffix."""
    rgb = np.asarray(rgb)
    if rgb.dtype != np.uint8:
        raise GeoNetInputError(path, f"image to write must be uint8, got {rgb.dtype}", "convert with np.clip(x, 0, 255).astype(np.uint8)")
    out = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR) if rgb.ndim == 3 else rgb
    with atomic_write(path) as tmp:
        _imwrite(tmp, out)


def write_mask(path, mask: np.ndarray) -> None:
    """Write an (H, W) bool mask as an 8-bit grey PNG, 0 / 255."""
    m = np.asarray(mask)
    if m.ndim != 2:
        raise ValueError(f"mask must be (H, W), got {m.shape}")
    with atomic_write(path) as tmp:
        _imwrite(tmp, (m != 0).astype(np.uint8) * 255)


def read_mask(path) -> np.ndarray:
    """Read an 8-bit mask PNG -> (H, W) bool (any non-zero value is True)."""
    img = _imread(path)
    if img.ndim == 3:
        img = img[..., :3].max(axis=2)
    return img != 0


# --------------------------------------------------------------------------- KITTI flow PNG
def encode_flow_kitti(flow: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
    """(H, W, 2) float flow in px + (H, W) bool valid -> (H, W, 3) uint16 in **RGB** order.

    Values are rounded to the 1/64 px grid and clipped to the uint16 range;
    invalid (or non-finite) pixels become (0, 0, 0).
    """
    flow = np.asarray(flow, dtype=np.float64)
    if flow.ndim != 3 or flow.shape[2] != 2:
        raise ValueError(f"flow must be (H, W, 2), got {flow.shape}")
    finite = np.isfinite(flow).all(axis=2)
    valid = finite if valid is None else (np.asarray(valid, dtype=bool) & finite)
    enc = np.zeros(flow.shape[:2] + (3,), dtype=np.uint16)
    uv = np.clip(np.round(np.where(finite[..., None], flow, 0.0) * FLOW_SCALE + FLOW_OFFSET), 0, 65535)
    enc[..., 0] = np.where(valid, uv[..., 0], 0)
    enc[..., 1] = np.where(valid, uv[..., 1], 0)
    enc[..., 2] = valid
    return enc


def decode_flow_kitti(rgb16: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(H, W, 3) uint16 RGB-ordered KITTI flow -> (flow (H, W, 2) float32 px, valid (H, W) bool).

    Invalid pixels get flow 0.
    """
    valid = rgb16[..., 2] != 0
    flow = (rgb16[..., :2].astype(np.float32) - FLOW_OFFSET) / FLOW_SCALE
    flow[~valid] = 0.0
    return flow, valid


def write_flow_kitti(path, flow: np.ndarray, valid: np.ndarray | None = None) -> None:
    """Write KITTI flow PNG (16-bit, R=u*64+2^15, G=v*64+2^15, B=valid).

    Args:
        flow: (H, W, 2) float, pixels (u right, v down).
        valid: (H, W) bool; None = every finite pixel.
    """
    enc = encode_flow_kitti(flow, valid)
    with atomic_write(path) as tmp:
        _imwrite(tmp, enc[..., ::-1].copy())  # cv2 writes BGR


def read_flow_kitti(path) -> tuple[np.ndarray, np.ndarray]:
    """Read KITTI flow PNG -> (flow (H, W, 2) float32 px, valid (H, W) bool)."""
    img = _imread(path)
    if img.dtype != np.uint16 or img.ndim != 3 or img.shape[2] != 3:
        raise GeoNetInputError(path, f"not a KITTI flow PNG (need 16-bit 3-channel, got {img.dtype} shape {img.shape})",
                               "KITTI flow is stored as 16-bit RGB PNG (flow_occ / flow_noc)")
    return decode_flow_kitti(img[..., ::-1])  # BGR -> RGB


# --------------------------------------------------------------------------- KITTI depth PNG
def write_depth_kitti(path, depth: np.ndarray, too_far: str = "zero") -> None:
    """Write (H, W) depth in metres (0 = none) as 16-bit PNG of round(depth * 256).

    Non-finite or non-positive values are written as 0 (none). Depths beyond
    the format's range (65535 / 256 = 255.996 m) become 0 with ``too_far="zero"``
    (default: a clipped value would be a wrong measurement) or 65535 with
    ``too_far="clip"`` (e.g. for predictions).
    """
    if too_far not in ("zero", "clip"):
        raise ValueError(f"too_far must be 'zero' or 'clip', got {too_far!r}")
    depth = np.asarray(depth, dtype=np.float64)
    if depth.ndim != 2:
        raise ValueError(f"depth must be (H, W), got {depth.shape}")
    depth = np.where(np.isfinite(depth) & (depth > 0), depth, 0.0)
    enc = np.round(depth * DEPTH_SCALE)
    enc = np.where(enc > 65535, 0 if too_far == "zero" else 65535, enc).astype(np.uint16)
    with atomic_write(path) as tmp:
        _imwrite(tmp, enc)


def read_depth_kitti(path) -> np.ndarray:
    """Read KITTI depth PNG -> (H, W) float32 metres, 0 = no measurement."""
    img = _imread(path)
    if img.dtype != np.uint16 or img.ndim != 2:
        raise GeoNetInputError(path, f"not a KITTI depth PNG (need 16-bit 1-channel, got {img.dtype} shape {img.shape})",
                               "KITTI depth is stored as 16-bit grey PNG of depth*256")
    return img.astype(np.float32) / DEPTH_SCALE


# --------------------------------------------------------------------------- Middlebury .flo
def write_flo(path, flow: np.ndarray) -> None:
    """Write (H, W, 2) float flow as Middlebury .flo (little-endian float32)."""
    flow = np.asarray(flow, dtype="<f4")
    if flow.ndim != 3 or flow.shape[2] != 2:
        raise ValueError(f"flow must be (H, W, 2), got {flow.shape}")
    h, w = flow.shape[:2]
    with atomic_write(path) as tmp, open(tmp, "wb") as f:
        np.array([FLO_MAGIC], dtype="<f4").tofile(f)
        np.array([w, h], dtype="<i4").tofile(f)
        np.ascontiguousarray(flow).tofile(f)


def read_flo(path) -> np.ndarray:
    """Read Middlebury .flo -> (H, W, 2) float32 (u, v) px.

    Values above 1e9 mark unknown flow in Middlebury files; they are returned as is.
    """
    path = Path(path)
    if not path.is_file():
        raise GeoNetInputError(path, "flow file not found", "check the path")
    raw = path.read_bytes()
    if len(raw) < 12:
        raise GeoNetInputError(path, "file too short for a .flo header", "is it a Middlebury .flo file?")
    magic = np.frombuffer(raw, dtype="<f4", count=1)[0]
    if magic != np.float32(FLO_MAGIC):
        raise GeoNetInputError(path, f"bad .flo magic {magic!r} (expected {FLO_MAGIC})", "is it a Middlebury .flo file?")
    w, h = (int(x) for x in np.frombuffer(raw, dtype="<i4", count=2, offset=4))
    if w <= 0 or h <= 0 or len(raw) != 12 + 8 * w * h:
        raise GeoNetInputError(path, f".flo header says {w}x{h} but file has {len(raw)} bytes", "the file is truncated or corrupt")
    return np.frombuffer(raw, dtype="<f4", offset=12).reshape(h, w, 2).astype(np.float32)


# --------------------------------------------------------------------------- poses
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
        raise GeoNetInputError(path, "pose file not found", "check the path")
    try:
        vals = np.loadtxt(path, dtype=np.float64, ndmin=2)
    except ValueError as err:
        raise GeoNetInputError(path, f"could not parse poses ({err})", "expected 12 numbers per line") from None
    if vals.size == 0 or vals.shape[1] != 12:
        raise GeoNetInputError(path, f"expected 12 numbers per line, got shape {vals.shape}",
                               "KITTI odometry poses are row-major 3x4 camera-to-world matrices")
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
    R = np.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
        2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
        2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y),
    ], axis=-1)
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
        raise GeoNetInputError(path, "trajectory file not found", "check the path")
    rows = []
    for lineno, line in enumerate(path.read_text().splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.replace(",", " ").split()
        try:
            vals = [float(p) for p in parts]
        except ValueError:
            vals = []
        if len(vals) != 8:
            raise GeoNetInputError(path, f"line {lineno}: expected 8 numbers 'time tx ty tz qx qy qz qw'", "is this a TUM trajectory?")
        rows.append(vals)
    if not rows:
        raise GeoNetInputError(path, "no poses in file", "is this a TUM trajectory?")
    a = np.array(rows)
    poses = np.tile(np.eye(4), (len(a), 1, 1))
    poses[:, :3, :3] = quaternion_to_rotation(a[:, 4:8])
    poses[:, :3, 3] = a[:, 1:4]
    return a[:, 0], poses


# --------------------------------------------------------------------------- calibration
def read_calib_file(path) -> dict[str, np.ndarray | str]:
    """Read a KITTI-style ``key: v1 v2 ...`` file.

    Returns:
        {key: (n,) float64 array} for numeric values, {key: str} otherwise
        (e.g. ``calib_time``). Blank lines are skipped.
    Raises:
        GeoNetInputError naming the file for a line without ``:``.
    """
    path = Path(path)
    if not path.is_file():
        raise GeoNetInputError(path, "calibration file not found", "check the path")
    out: dict[str, np.ndarray | str] = {}
    for lineno, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip():
            continue
        key, sep, value = line.partition(":")
        key = key.strip()
        if not sep or not key:
            raise GeoNetInputError(path, f"line {lineno} is not 'key: values' ({line.strip()[:60]!r})",
                                   "KITTI calibration files have one 'key: v1 v2 ...' per line")
        try:
            out[key] = np.array([float(v) for v in value.split()], dtype=np.float64)
        except ValueError:
            out[key] = value.strip()
    return out


def require_key(calib: dict, key: str, path) -> np.ndarray:
    """``calib[key]`` or GeoNetInputError naming the file and the missing key."""
    if key not in calib:
        raise GeoNetInputError(path, f"missing calibration key '{key}'",
                               f"keys present: {', '.join(sorted(calib)) or 'none'}")
    return calib[key]


def write_calib_K(path, K: np.ndarray) -> None:
    """Write one line ``K: fx 0 cx 0 fy cy 0 0 1`` (row-major 3x3)."""
    K = np.asarray(K, dtype=np.float64).reshape(3, 3)
    with atomic_write(path) as tmp:
        tmp.write_text("K: " + " ".join(f"{v:.9g}" for v in K.reshape(-1)) + "\n")


def read_calib_K(path, key: str = "K") -> np.ndarray:
    """Read a 3x3 intrinsics matrix stored under ``key`` -> (3, 3) float64.

    A 12-value entry (KITTI ``P2`` / ``P_rect_02`` projection matrix) gives its
    left 3x3 block, which is K for rectified images.
    """
    calib = read_calib_file(path)
    v = require_key(calib, key, path)
    if isinstance(v, str) or v.size not in (9, 12):
        raise GeoNetInputError(path, f"'{key}' must hold 9 (3x3) or 12 (3x4) numbers", "e.g. 'K: fx 0 cx 0 fy cy 0 0 1'")
    return v.reshape(3, -1)[:, :3].copy()


# --------------------------------------------------------------------------- visualisation
def _make_color_wheel() -> np.ndarray:
    """Middlebury colour wheel (Baker et al. 2011): (55, 3) float RGB in [0, 255]."""
    RY, YG, GC, CB, BM, MR = 15, 6, 4, 11, 13, 6
    segments = []
    for n, start, ch_up, ch_down in ((RY, (255, 0, 0), 1, None), (YG, (255, 255, 0), None, 0),
                                     (GC, (0, 255, 0), 2, None), (CB, (0, 255, 255), None, 1),
                                     (BM, (0, 0, 255), 0, None), (MR, (255, 0, 255), None, 2)):
        seg = np.tile(np.array(start, dtype=np.float64), (n, 1))
        ramp = np.floor(255 * np.arange(n) / n)
        if ch_up is not None:
            seg[:, ch_up] = ramp
        else:
            seg[:, ch_down] = 255 - ramp
        segments.append(seg)
    return np.concatenate(segments)


_COLOR_WHEEL = _make_color_wheel()


def flow_to_color(flow: np.ndarray, max_flow: float | None = None, valid: np.ndarray | None = None) -> np.ndarray:
    """Middlebury colour coding of flow: hue = direction, saturation = magnitude.

    Same wheel as the Middlebury/KITTI visualisations (Baker et al., ``flowToColor``):
    +x (right) is red, -x cyan, +y (down) orange-yellow, -y blue-violet.

    Args:
        flow: (H, W, 2) float px.
        max_flow: magnitude shown at full saturation; None = max over valid pixels.
        valid: (H, W) bool; invalid pixels are drawn black.
    Returns:
        (H, W, 3) uint8 RGB.
    """
    flow = np.asarray(flow, dtype=np.float64)
    u, v = flow[..., 0], flow[..., 1]
    ok = np.isfinite(u) & np.isfinite(v)
    if valid is not None:
        ok &= np.asarray(valid, dtype=bool)
    u = np.where(ok, u, 0.0)
    v = np.where(ok, v, 0.0)
    mag = np.hypot(u, v)
    if max_flow is None:
        max_flow = float(mag[ok].max()) if ok.any() else 0.0
    max_flow = max(max_flow, 1e-9)
    u, v = u / max_flow, v / max_flow
    rad = np.hypot(u, v)
    ncols = len(_COLOR_WHEEL)
    a = np.arctan2(-v, -u) / np.pi  # in [-1, 1]
    fk = (a + 1) / 2 * (ncols - 1)
    k0 = np.floor(fk).astype(int)
    k1 = (k0 + 1) % ncols
    f = (fk - k0)[..., None]
    col = (1 - f) * _COLOR_WHEEL[k0] / 255 + f * _COLOR_WHEEL[k1] / 255
    r = rad[..., None]
    inside = r <= 1
    # Saturation grows with magnitude; beyond max_flow the colour darkens.
    col = np.where(inside, 1 - r * (1 - col), col * 0.75)
    img = np.floor(255 * col).astype(np.uint8)
    img[~ok] = 0
    return img


def depth_to_color(depth_or_disp: np.ndarray, is_disparity: bool = False, vmax: float | None = None,
                   colormap: int = cv2.COLORMAP_MAGMA) -> np.ndarray:
    """Colour a depth (or disparity) map like monodepth/GeoNet figures: near = bright.

    Depth is converted to inverse depth, normalised by its 95th percentile (or
    ``vmax`` in inverse-depth units) and mapped with an OpenCV colormap (magma).

    Args:
        depth_or_disp: (H, W) float; depth in metres (0/non-finite = none) or disparity.
        is_disparity: True if the input already is inverse depth / disparity.
        vmax: value (inverse depth) at the top of the colormap; None = 95th percentile.
    Returns:
        (H, W, 3) uint8 RGB; pixels without depth are black.
    """
    x = np.asarray(depth_or_disp, dtype=np.float64)
    ok = np.isfinite(x) & (x > 0)
    inv = np.zeros_like(x)
    inv[ok] = x[ok] if is_disparity else 1.0 / x[ok]
    if vmax is None:
        vmax = float(np.percentile(inv[ok], 95)) if ok.any() else 1.0
    norm = np.clip(inv / max(vmax, 1e-12), 0, 1)
    bgr = cv2.applyColorMap((norm * 255).astype(np.uint8), colormap)
    bgr[~ok] = 0
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)

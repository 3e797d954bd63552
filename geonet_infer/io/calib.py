"""Camera calibration files and :class:`Camera` (K + lens distortion + the image size K belongs to).

* KITTI-style ``key: v1 v2 ...`` files (:func:`read_calib_file`); our own files hold
  ``K: fx 0 cx 0 fy cy 0 0 1`` (row-major 3x3, :func:`write_calib_K` / :func:`read_calib_K`).
* GeoNet's official ``<frame>_cam.txt``: one line ``fx,0.,cx,0.,fy,cy,0.,0.,1.``
  (:func:`write_cam_txt` / :func:`read_cam_txt`), as written by ``training.prepare``.
* :func:`read_camera` recognises the formats in :data:`CAMERA_FORMATS` and returns a :class:`Camera`.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from geonet_infer.errors import InputError
from geonet_infer.io.atomic import atomic_write
from geonet_infer.io.camera import (  # noqa: F401  (re-exported: this module's names before the split)
    FOCAL_RANGE,
    MAX_DISTORTION,
    OPENCV_DIST_LENGTHS,
    PRINCIPAL_POINT_MARGIN,
    Camera,
    _undistort_maps,
)

__all__ = [
    "CAMERA_FORMATS",
    "Camera",
    "read_camera",
    "read_calib_file",
    "require_key",
    "read_calib_K",
    "write_calib_K",
    "cam_txt_line",
    "write_cam_txt",
    "read_cam_txt",
]

CAMERA_FORMATS = (
    "KITTI raw calib_cam_to_cam.txt (P_rect_02, size from S_rect_02)",
    "KITTI odometry calib.txt (P2, or P0 for grey sequences)",
    "'K: fx 0 cx 0 fy cy 0 0 1' (geonet / training.synth calib.txt)",
    "a plain 3x3 matrix (9 numbers, whitespace or commas; also GeoNet's <frame>_cam.txt)",
    "'key values' lines: K (9 numbers) or fx fy cx cy, optional dist, image_width, image_height; # comments",
    "EuRoC / Kalibr sensor.yaml (intrinsics: [fu, fv, cu, cv], distortion_coefficients, resolution)",
)
_FORMATS_HINT = "supported: " + "; ".join(CAMERA_FORMATS)


# --------------------------------------------------------------------------- KITTI-style key: value files
def read_calib_file(path) -> dict[str, np.ndarray | str]:
    """Read a KITTI-style ``key: v1 v2 ...`` file.

    Returns:
        {key: (n,) float64 array} for numeric values, {key: str} otherwise
        (e.g. ``calib_time``). Blank lines are skipped.
    Raises:
        GeoNetError naming the file for a line without ``:``.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "calibration file not found", "check the path")
    out: dict[str, np.ndarray | str] = {}
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:  # found by tests/runtime/io/test_fuzz_parsers.py
        raise InputError(path, "not a text calibration file", "KITTI calibration files are text") from None
    for lineno, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        key, sep, value = line.partition(":")
        key = key.strip()
        if not sep or not key:
            raise InputError(
                path,
                f"line {lineno} is not 'key: values' ({line.strip()[:60]!r})",
                "KITTI calibration files have one 'key: v1 v2 ...' per line",
            )
        try:
            out[key] = np.array([float(v) for v in value.split()], dtype=np.float64)
        except ValueError:
            out[key] = value.strip()
    return out


def require_key(calib: dict, key: str, path) -> np.ndarray:
    """``calib[key]`` or GeoNetError naming the file and the missing key."""
    if key not in calib:
        raise InputError(
            path, f"missing calibration key '{key}'", f"keys present: {', '.join(sorted(calib)) or 'none'}"
        )
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
        raise InputError(path, f"'{key}' must hold 9 (3x3) or 12 (3x4) numbers", "e.g. 'K: fx 0 cx 0 fy cy 0 0 1'")
    return v.reshape(3, -1)[:, :3].copy()


def write_kitti_camera(path, K: np.ndarray, width: int, height: int) -> None:
    """The intrinsics used, in KITTI raw's calibration form, atomically: ``P_rect_02`` (3x4, no
    baseline) and ``S_rect_02`` (width height). :func:`read_camera` reads it back (``--calib``)."""
    P = np.hstack([np.asarray(K, np.float64).reshape(3, 3), np.zeros((3, 1))])
    text = "P_rect_02: " + " ".join(f"{v:.12e}" for v in P.ravel()) + f"\nS_rect_02: {width:.6e} {height:.6e}\n"
    with atomic_write(path) as tmp:
        tmp.write_text(text)


# --------------------------------------------------------------------------- GeoNet <frame>_cam.txt
def cam_txt_line(K: np.ndarray) -> str:
    """Official _cam.txt line "fx,0.,cx,0.,fy,cy,0.,0.,1." (full float precision)."""
    K = np.asarray(K, dtype=np.float64).reshape(3, 3)
    fx, cx, fy, cy = (float(v) for v in (K[0, 0], K[0, 2], K[1, 1], K[1, 2]))
    return f"{fx!r},0.,{cx!r},0.,{fy!r},{cy!r},0.,0.,1."


def write_cam_txt(path, K: np.ndarray) -> None:
    """Write GeoNet's ``<frame>_cam.txt``: :func:`cam_txt_line` plus a newline, atomically."""
    line = cam_txt_line(K)
    with atomic_write(path) as tmp:
        tmp.write_text(line + "\n")


def read_cam_txt(path) -> np.ndarray:
    """<frame>_cam.txt "fx,0.,cx,0.,fy,cy,0.,0.,1." -> (3, 3) float64 (commas or whitespace)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "intrinsics file not found", "check the path")
    try:
        vals = [float(v) for v in path.read_text().replace(",", " ").split()]
    except ValueError:
        vals = []
    if len(vals) != 9:
        raise InputError(path, "expected 9 comma-separated numbers 'fx,0.,cx,0.,fy,cy,0.,0.,1.'")
    return np.array(vals, dtype=np.float64).reshape(3, 3)


# --------------------------------------------------------------------------- read_camera
_KEY = re.compile(r"[A-Za-z_][A-Za-z0-9_]*\Z")


def _floats(values, path, key: str, counts: tuple[int, ...]) -> np.ndarray:
    """Parse ``values`` (list of str) as floats; GeoNetError unless the count is in ``counts``."""
    try:
        arr = np.array([float(v) for v in values], dtype=np.float64)
    except ValueError:
        arr = None
    if arr is None or arr.size not in counts:
        want = " or ".join(str(c) for c in counts)
        raise InputError(path, f"'{key}' must hold {want} numbers, got {' '.join(values)[:80]!r}", _FORMATS_HINT)
    return arr


def _size(width, height, path, what: str) -> tuple[int, int]:
    vals = (float(width), float(height))
    if not all(v.is_integer() and v > 0 for v in vals):
        raise InputError(path, f"image size {what} is not two positive whole numbers: {vals}", _FORMATS_HINT)
    return int(vals[0]), int(vals[1])


def _key_values(text: str) -> dict[str, list[str]] | None:
    """``key: v1 v2`` or ``key v1 v2`` lines (``#`` comments) -> {key: [tokens]}; None if not such a file."""
    out: dict[str, list[str]] = {}
    for line in text.splitlines():
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        key, sep, rest = line.partition(":")
        if not sep or not _KEY.match(key.strip()):  # 'key values' (a ':' further on is part of the values)
            key, rest = (line.split(None, 1) + [""])[:2]
        key = key.strip()
        if not _KEY.match(key):
            return None
        out[key] = rest.replace(",", " ").split()
    return out or None


def _camera_from_key_values(kv: dict[str, list[str]], path: Path, key: str | None = None) -> Camera | None:
    if key is not None:  # the caller knows which camera the frames are (KITTI odometry image_0: P0)
        if key not in kv:
            raise InputError(path, f"missing calibration key '{key}'", "the frames' camera needs its own entry")
        P = _floats(kv[key], path, key, (12,))
        return Camera(P.reshape(3, 4)[:, :3], None, None, f"{path} (KITTI, {key})")
    if "P_rect_02" in kv:  # KITTI raw calib_cam_to_cam.txt: rectified images, no distortion
        P = _floats(kv["P_rect_02"], path, "P_rect_02", (12,))
        size = None
        if "S_rect_02" in kv:
            width, height = _floats(kv["S_rect_02"], path, "S_rect_02", (2,))
            size = _size(width, height, path, "S_rect_02")
        return Camera(P.reshape(3, 4)[:, :3], None, size, f"{path} (KITTI raw, P_rect_02)")
    for key in ("P2", "P0"):  # KITTI odometry calib.txt: colour cam 2, else grey cam 0
        if key in kv:
            P = _floats(kv[key], path, key, (12,))
            return Camera(P.reshape(3, 4)[:, :3], None, None, f"{path} (KITTI odometry, {key})")
    if "K" in kv:
        K = _floats(kv["K"], path, "K", (9, 12)).reshape(3, -1)[:, :3]
        what = "K"
    elif all(k in kv for k in ("fx", "fy", "cx", "cy")):
        fx, fy, cx, cy = (_floats(kv[k], path, k, (1,))[0] for k in ("fx", "fy", "cx", "cy"))
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        what = "fx fy cx cy"
    else:
        return None
    dist = _floats(kv["dist"], path, "dist", OPENCV_DIST_LENGTHS) if "dist" in kv else None
    size = None
    if "image_width" in kv or "image_height" in kv:
        w = _floats(kv.get("image_width", []), path, "image_width", (1,))[0]
        h = _floats(kv.get("image_height", []), path, "image_height", (1,))[0]
        size = _size(w, h, path, "image_width/image_height")
    return Camera(K, dist, size, f"{path} ({what})")


def _yaml_list(text: str, key: str) -> list[str] | None:
    m = re.search(rf"^[ \t]*{key}[ \t]*:[ \t]*\[([^\]]*)\]", text, re.M)
    if m is None:
        return None
    body = "\n".join(line.split("#", 1)[0] for line in m.group(1).splitlines())
    return [v.strip() for v in body.split(",") if v.strip()]


def _yaml_scalar(text: str, key: str) -> str | None:
    m = re.search(rf"^[ \t]*{key}[ \t]*:[ \t]*([^\s#]+)", text, re.M)
    return m.group(1).strip("'\"") if m else None


def _camera_from_euroc_yaml(text: str, path: Path) -> Camera | None:
    """EuRoC / Kalibr ``sensor.yaml`` (pinhole + radial-tangential), parsed with regexes (no YAML dependency)."""
    intr = _yaml_list(text, "intrinsics")
    if intr is None:
        return None
    model = _yaml_scalar(text, "camera_model")
    if model is not None and model != "pinhole":
        raise InputError(path, f"camera_model '{model}' is not a pinhole camera", "only pinhole models are supported")
    fu, fv, cu, cv = _floats(intr, path, "intrinsics", (4,))
    dist = None
    coeffs = _yaml_list(text, "distortion_coefficients")
    if coeffs is not None:
        dist_model = _yaml_scalar(text, "distortion_model")
        if dist_model is not None and dist_model not in ("radial-tangential", "radtan", "plumb_bob"):
            raise InputError(
                path,
                f"distortion_model '{dist_model}' is not OpenCV's radial-tangential (k1 k2 p1 p2)",
                "undistort the frames with the matching model first",
            )
        dist = _floats(coeffs, path, "distortion_coefficients", OPENCV_DIST_LENGTHS)
    size = None
    res = _yaml_list(text, "resolution")
    if res is not None:
        width, height = _floats(res, path, "resolution", (2,))
        size = _size(width, height, path, "resolution")
    K = np.array([[fu, 0.0, cu], [0.0, fv, cv], [0.0, 0.0, 1.0]])
    return Camera(K, dist, size, f"{path} (EuRoC sensor.yaml)")


def _camera_from_plain_matrix(text: str, path: Path) -> Camera | None:
    body = "\n".join(line.split("#", 1)[0] for line in text.splitlines())
    tokens = body.replace(",", " ").replace(";", " ").replace("[", " ").replace("]", " ").split()
    if len(tokens) != 9:
        return None
    try:
        vals = [float(t) for t in tokens]
    except ValueError:
        return None
    return Camera(np.array(vals).reshape(3, 3), None, None, f"{path} (3x3 matrix)")


def read_camera(path, key: str | None = None) -> Camera:
    """Read a camera calibration file, detecting its format -> validated :class:`Camera`.

    Formats (:data:`CAMERA_FORMATS`):

    * KITTI raw ``calib_cam_to_cam.txt``: K = left 3x3 of ``P_rect_02``, size from
      ``S_rect_02``, no distortion (the images are rectified).
    * KITTI odometry ``calib.txt``: K = left 3x3 of ``P2`` (``P0`` if there is no P2,
      e.g. grey-only sequences); size unknown; no distortion.
    * ``K: fx 0 cx 0 fy cy 0 0 1`` (:func:`write_calib_K`).
    * A plain 3x3 matrix: 9 numbers separated by whitespace or commas (so also
      GeoNet's ``<frame>_cam.txt``).
    * ``key values`` lines with ``#`` comments: ``K`` (9 numbers) or ``fx fy cx cy``,
      optional ``dist`` (OpenCV order), ``image_width`` and ``image_height``.
    * EuRoC / Kalibr ``sensor.yaml``: ``intrinsics: [fu, fv, cu, cv]``,
      ``distortion_coefficients: [k1, k2, p1, p2]``, ``resolution: [w, h]``.

    ``key`` names the projection matrix of a KITTI file to use (``P0`` for odometry ``image_0`` frames).

    Raises:
        GeoNetError naming the file if it is missing, in none of these formats,
        or holds invalid values (:meth:`Camera.validate`).
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "calibration file not found", "check the path")
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise InputError(path, "not a text calibration file", _FORMATS_HINT) from None
    cam = None if key is not None else _camera_from_euroc_yaml(text, path)
    if cam is None and key is None:
        cam = _camera_from_plain_matrix(text, path)
    kv = None
    if cam is None:
        kv = _key_values(text)
        cam = _camera_from_key_values(kv, path, key) if kv else None
    if cam is None:
        found = f" (keys: {', '.join(list(kv)[:12])})" if kv else ""
        raise InputError(path, f"unrecognised calibration format{found}", _FORMATS_HINT)
    return Camera(cam.K, cam.dist, cam.size, cam.source, "calibration file").validate(path)

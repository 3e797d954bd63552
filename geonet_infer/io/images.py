"""8-bit RGB images, 0/255 masks and image folders (OpenCV's BGR order only inside this module)."""

from __future__ import annotations

import re
import struct
from pathlib import Path

import cv2
import numpy as np

from geonet_infer.errors import InputError
from geonet_infer.io.atomic import atomic_write
from geonet_infer.io.png import encode_png

__all__ = [
    "IMAGE_SUFFIXES",
    "MAX_IMAGE_PIXELS",
    "check_pixels",
    "encoded_size",
    "list_images",
    "read_image",
    "read_mask",
    "write_image",
    "write_mask",
]

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".ppm")  # compared lower-case


# Decoded frames above this many pixels are refused before decoding (50 Mpx: an 8K frame is 33 Mpx;
# 50 Mpx of RGB is 150 MB, a few times that in the predictor). A small compressed file can claim
# gigapixels (a 876 KB PNG of 30000x30000 decodes to 2.7 GB); OpenCV's own cap is 1 Gpx.
MAX_IMAGE_PIXELS = 50_000_000


def _imwrite(path: Path, array: np.ndarray) -> None:
    """Encode (H, W) grey or (H, W, 3) RGB pixels (format from the suffix), then write the bytes with Python.

    PNG goes through :func:`~geonet_infer.io.png.encode_png` (several times faster than OpenCV's
    encoder on our outputs, which made writing the largest cost of ``predict``); other formats
    through OpenCV. An encoder that refuses the array is a GeoNetError; the write itself raises the
    OSError the OS gave (disk full, read-only), which cv2.imwrite would hide behind False.
    Python opens the file, so any file name the OS accepts works (OpenCV's C++ path
    conversion crashes on names that are not valid UTF-8).
    """
    array = np.asarray(array)
    encoded: bytes | None = None
    if path.suffix.lower() == ".png":
        try:
            encoded = encode_png(array)
        except ValueError:
            pass
    else:
        bgr = cv2.cvtColor(array, cv2.COLOR_RGB2BGR) if array.ndim == 3 and array.shape[2] == 3 else array
        try:
            ok, data = cv2.imencode(path.suffix, bgr)
        except cv2.error:
            ok = False
        encoded = data.tobytes() if ok else None
    if encoded is None:
        raise InputError(
            path,
            f"cannot encode a {array.dtype} image of shape {array.shape} as {path.suffix or '(no suffix)'}",
            f"use one of {' '.join(IMAGE_SUFFIXES)} (16-bit needs .png)",
        )
    with open(path, "wb") as f:
        f.write(encoded)


def encoded_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) from the header of a PNG, JPEG, BMP or PPM/PGM/PBM file, or None if not one of them.

    Reads only the header, so a frame's size can be checked before OpenCV allocates it.
    """
    if data[:8] == b"\x89PNG\r\n\x1a\n" and data[12:16] == b"IHDR" and len(data) >= 24:
        return struct.unpack(">II", data[16:24])
    if data[:2] == b"BM" and len(data) >= 26:
        if struct.unpack("<I", data[14:18])[0] == 12:  # OS/2 BITMAPCOREHEADER: 16-bit sizes
            return struct.unpack("<HH", data[18:22])
        width, height = struct.unpack("<ii", data[18:26])
        return abs(width), abs(height)  # a negative height means top-down rows
    netpbm = re.match(rb"P[1-6](?:\s|#[^\n]*\n)+(\d+)(?:\s|#[^\n]*\n)+(\d+)", data[:1024])
    if netpbm:
        return int(netpbm[1]), int(netpbm[2])
    if data[:2] == b"\xff\xd8":
        i = 2
        while i + 4 <= len(data) and data[i] == 0xFF:
            marker = data[i + 1]
            if marker == 0xFF:  # fill byte
                i += 1
            elif marker == 0x01 or 0xD0 <= marker <= 0xD8:  # markers without a length
                i += 2
            elif 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):  # start of frame
                if i + 9 > len(data):
                    return None
                height, width = struct.unpack(">HH", data[i + 5 : i + 9])
                return width, height
            else:
                i += 2 + int.from_bytes(data[i + 2 : i + 4], "big")
    return None


def check_pixels(path, width: int, height: int) -> None:
    """GeoNetError naming ``path`` if ``width`` x ``height`` is over :data:`MAX_IMAGE_PIXELS`."""
    if width * height > MAX_IMAGE_PIXELS:
        raise InputError(
            path,
            f"{width}x{height} is {width * height:,} pixels, over the limit of {MAX_IMAGE_PIXELS:,} pixels",
            "resize the frames (e.g. to 1920x1080)",
        )


def _imread(path, flags: int = cv2.IMREAD_UNCHANGED) -> np.ndarray:
    """Decode an image file; GeoNetError naming the file and the real reason when it cannot be.

    The bytes are read by Python and decoded with cv2.imdecode (any file name works), after the
    header's size was checked against :data:`MAX_IMAGE_PIXELS`. An OSError of the read (permission
    denied, I/O error) is raised as is.
    """
    path = Path(path)
    if not path.exists():
        raise InputError(path, "image not found", "check the path")
    if not path.is_file():
        raise InputError(path, "not a file", "pass an image file")
    data = path.read_bytes()
    if not data:
        raise InputError(path, "empty file (0 bytes)", "was it copied or downloaded completely?")
    size = encoded_size(data)
    if size is not None:
        check_pixels(path, *size)
    try:
        img = cv2.imdecode(np.frombuffer(data, np.uint8), flags)
    except cv2.error as exc:
        img, detail = None, f" ({str(exc).strip().splitlines()[-1]})"
    else:
        detail = ""
    if img is None:
        if size is None:
            raise InputError(
                path, "not an image OpenCV can read (unknown file header)", f"expected {' '.join(IMAGE_SUFFIXES)}"
            )
        raise InputError(
            path, f"OpenCV could not decode this {size[0]}x{size[1]} image{detail}", "is the file truncated or damaged?"
        )
    return img


# --------------------------------------------------------------------------- folders
def natural_key(name: str) -> tuple:
    """Sort key comparing digit runs as numbers: frame2.png < frame10.png (then by name, so 01 != 1)."""
    parts = re.split(r"(\d+)", name)  # even indices text, odd indices digits
    return [int(t) if i % 2 else t for i, t in enumerate(parts)], name


def list_images(folder) -> list[Path]:
    """Image files of a folder, sorted by file name with numbers in numeric order (:func:`natural_key`).

    Suffixes: .png .jpg .jpeg .bmp .ppm (any case). Hidden files (names starting
    with ``.``, e.g. the temp files of :func:`~geonet_infer.io.atomic.atomic_write`
    or macOS ``._*`` files) and sub-folders are not listed.

    Raises:
        GeoNetError naming the folder if it does not exist or holds no image.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(
            folder, "image folder not found" if not folder.exists() else "not a folder", "pass a folder of frames"
        )
    files = sorted(
        (
            p
            for p in folder.iterdir()
            if p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith(".") and p.is_file()
        ),
        key=lambda p: natural_key(p.name),
    )
    if not files:
        raise InputError(folder, "no images in this folder", f"expected {' '.join(IMAGE_SUFFIXES)} files")
    return files


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
        raise InputError(
            path, f"image to write must be uint8, got {rgb.dtype}", "convert with np.clip(x, 0, 255).astype(np.uint8)"
        )
    with atomic_write(path) as tmp:
        _imwrite(tmp, rgb)


# --------------------------------------------------------------------------- masks
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

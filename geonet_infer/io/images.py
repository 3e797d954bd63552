"""8-bit RGB images, 0/255 masks and image folders (OpenCV's BGR order only inside this module)."""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np

from geonet_infer.errors import GeoNetInputError
from geonet_infer.io.atomic import atomic_write

__all__ = ["IMAGE_SUFFIXES", "list_images", "read_image", "read_mask", "write_image", "write_mask"]

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".ppm")  # compared lower-case


def _imwrite(path: Path, array: np.ndarray) -> None:
    """cv2.imwrite that raises instead of returning False."""
    if not cv2.imwrite(str(path), array):
        raise GeoNetInputError(
            path, "OpenCV could not write this image", "check the suffix and that the folder is writable"
        )


def _imread(path, flags: int = cv2.IMREAD_UNCHANGED) -> np.ndarray:
    path = Path(path)
    if not path.is_file():
        raise GeoNetInputError(path, "image not found", "check the path")
    img = cv2.imread(str(path), flags)
    if img is None:
        raise GeoNetInputError(path, "OpenCV could not decode this image", "is it a valid PNG/JPEG file?")
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
        GeoNetInputError naming the folder if it does not exist or holds no image.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise GeoNetInputError(
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
        raise GeoNetInputError(folder, "no images in this folder", f"expected {' '.join(IMAGE_SUFFIXES)} files")
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
        raise GeoNetInputError(
            path, f"image to write must be uint8, got {rgb.dtype}", "convert with np.clip(x, 0, 255).astype(np.uint8)"
        )
    out = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR) if rgb.ndim == 3 else rgb
    with atomic_write(path) as tmp:
        _imwrite(tmp, out)


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

"""Render a `geonet-infer predict --point-cloud` PLY to a PNG, seen from above and behind the first camera.

    python scripts/render_point_cloud.py out/kitti/points_world.ply docs/img/point_cloud.png

Points are projected with OpenCV (cv2.projectPoints) by a virtual camera raised and pitched down
over the first camera, drawn far to near (a painter's z-buffer), one small square each.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

TYPES = {"float": "<f4", "uchar": "u1"}


def read_ply(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) float32 points and (N, 3) uint8 RGB of a binary little-endian PLY from predict."""
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode("ascii").splitlines()
    count = next(int(line.split()[2]) for line in header if line.startswith("element vertex"))
    fields = [(line.split()[2], TYPES[line.split()[1]]) for line in header if line.startswith("property")]
    table = np.frombuffer(data[end:], dtype=np.dtype(fields), count=count)
    xyz = np.stack([table[a] for a in "xyz"], axis=1)
    rgb = np.stack([table[c] for c in ("red", "green", "blue")], axis=1)
    return xyz, rgb


def render(xyz: np.ndarray, rgb: np.ndarray, size=(960, 540), height=0.6, back=0.8, pitch_deg=25.0) -> np.ndarray:
    """The cloud from a camera ``height`` and ``back`` (in the cloud's units, times its median depth)
    above and behind the origin, pitched down by ``pitch_deg``. Returns (H, W, 3) uint8 RGB."""
    scale = float(np.median(xyz[:, 2]))
    pitch = np.deg2rad(pitch_deg)
    R = cv2.Rodrigues(np.array([pitch, 0.0, 0.0]))[0]  # world -> virtual camera: looking down by pitch
    eye = np.array([0.0, -height * scale, -back * scale])  # y is down: negative y is up
    t = -R @ eye
    w, h = size
    K = np.array([[0.8 * w, 0, w / 2], [0, 0.8 * w, h / 2], [0, 0, 1]])
    cam = xyz @ R.T + t
    front = cam[:, 2] > 0.05 * scale
    uv = cv2.projectPoints(xyz[front].astype(np.float64), cv2.Rodrigues(R)[0], t, K, None)[0][:, 0]
    order = np.argsort(-cam[front, 2])  # far first: near points are drawn over them
    image = np.full((h, w, 3), 16, np.uint8)
    u, v = np.round(uv[order]).astype(int).T
    colours = rgb[front][order]
    for du in (0, 1):
        for dv in (0, 1):
            ok = (u + du >= 0) & (u + du < w) & (v + dv >= 0) & (v + dv < h)
            image[v[ok] + dv, u[ok] + du] = colours[ok]
    return image


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("ply", type=Path)
    parser.add_argument("png", type=Path)
    args = parser.parse_args(argv)
    xyz, rgb = read_ply(args.ply)
    image = render(xyz, rgb)
    args.png.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(args.png), cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
    print(f"{len(xyz)} points -> {args.png}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

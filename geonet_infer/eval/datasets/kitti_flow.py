"""``kitti``: KITTI 2015 (``image_2/``, ``calib_cam_to_cam/``) or 2012 (``colored_0/``, ``calib/``), flow.

``NNNNNN_10.png`` -> ``NNNNNN_11.png``, GT ``flow_noc/NNNNNN_10.png`` and ``flow_occ/NNNNNN_10.png``;
these folders directly in the folder given or in its ``training/`` (the benchmark as unpacked).
The cascade's 3-frame snippet takes ``NNNNNN_09.png`` from the multi-view extension (same folder,
or ``multiview`` DIR/<image folder>/) as GeoNet's official test does. **Fallback** where ``_09`` is
missing: the pair [_10, _11], which the runtime pads to [_10, _10, _11] exactly as at the start of
a video (the frame before is replaced by the target itself); each item records which snippet it used.
"""

from __future__ import annotations

from pathlib import Path

from geonet_infer.errors import InputError
from geonet_infer.eval.datasets.base import (
    FlowItem,
    Found,
    Layout,
    _require_dir,
    _require_file,
    benchmark_root,
)


class KittiFlow(Layout):
    name = "kitti"
    help = {  # geonet-infer eval --help: one entry per task, one string per line
        "flow": (
            "KITTI 2015 (image_2/, calib_cam_to_cam/) or 2012 (colored_0/, calib/),",
            "here or in training/: NNNNNN_10.png -> _11.png, flow_noc/, flow_occ/;",
            "the model's 3-frame snippet takes NNNNNN_09.png (multi-view extension:",
            "same folder or --multiview DIR); without it the pair is padded",
            "[_10, _10, _11] as at a video start",
        ),
    }
    tasks = ("flow",)

    @staticmethod
    def _base(root: Path) -> Path | None:
        """The folder holding the benchmark's sub-folders: ``root`` or its ``training/`` (as unpacked)."""
        return benchmark_root(root, "image_2", "flow_occ") or benchmark_root(root, "colored_0", "flow_occ")

    @staticmethod
    def detect(task: str, root: Path) -> bool:
        return KittiFlow._base(root) is not None

    @classmethod
    def items(cls, task: str, root: Path, *, sequences: list[str] | None, stride: int, multiview: Path | None) -> Found:
        items: list[FlowItem] = []
        notes: list[str] = []
        name = root.name
        root = cls._base(root) or root  # no such folder: the checks below name what is missing
        image_name = "image_2" if (root / "image_2").is_dir() else "colored_0"
        image_dir = _require_dir(
            root / image_name, "KITTI flow image folder", "expected image_2/ (KITTI 2015) or colored_0/ (KITTI 2012)"
        )
        version = "2015" if image_name == "image_2" else "2012"
        calib_dir = root / ("calib_cam_to_cam" if version == "2015" else "calib")
        firsts = sorted(image_dir.glob("*_10.png"))
        if not firsts:
            raise InputError(image_dir, "no NNNNNN_10.png frame", "KITTI flow pairs are NNNNNN_10.png -> NNNNNN_11.png")
        fallback = 0
        for first in firsts[::stride]:
            stem = first.name[: -len("_10.png")]
            second = _require_file(image_dir / f"{stem}_11.png", "second frame of the pair")
            prev = next(
                (
                    p
                    for p in (
                        image_dir / f"{stem}_09.png",
                        multiview / image_name / f"{stem}_09.png" if multiview else None,
                    )
                    if p is not None and p.is_file()
                ),
                None,
            )
            frames = [prev, first, second] if prev else [first, second]
            fallback += prev is None
            noc = _require_file(root / "flow_noc" / f"{stem}_10.png", "flow ground truth (noc)")
            occ = _require_file(root / "flow_occ" / f"{stem}_10.png", "flow ground truth (occ)")
            calib = calib_dir / f"{stem}.txt"
            items.append(
                FlowItem(
                    stem,
                    frames,
                    noc,
                    occ,
                    calib=calib if calib.is_file() else None,
                    snippet="_09, _10, _11" if prev else "_10, _10, _11 (no _09: sequence-start padding)",
                )
            )
        if fallback:
            notes.append(f"{fallback} of {len(items)} pairs have no _09 frame: the cascade saw [_10, _10, _11]")
        desc = f"KITTI {version} layout {name}"
        return Found(items, desc, notes)

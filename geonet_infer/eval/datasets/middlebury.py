"""``middlebury``: ``other-data[-gray]/<Seq>/frame10.png, frame11.png`` + ``other-gt-flow/<Seq>/flow10.flo``, flow.

Values > 1e9 = unknown. No occlusion masks, so Noc = All. No intrinsics: the cascade needs
``intrinsics`` passed in.
"""

from __future__ import annotations

from pathlib import Path

from geonet_infer.errors import InputError
from geonet_infer.eval.datasets.base import (
    FlowItem,
    Found,
    Layout,
    _require_dir,
)


class Middlebury(Layout):
    name = "middlebury"
    help = {  # geonet-infer eval --help: one entry per task, one string per line
        "flow": (
            "other-data[-gray]/<Seq>/frame10.png, frame11.png + other-gt-flow/<Seq>/flow10.flo",
            "(no intrinsics: the model needs --intrinsics)",
        ),
    }
    tasks = ("flow",)

    @staticmethod
    def detect(task: str, root: Path) -> bool:
        return (root / "other-gt-flow").is_dir()

    @classmethod
    def items(cls, task: str, root: Path, *, sequences: list[str] | None, stride: int, multiview: Path | None) -> Found:
        items: list[FlowItem] = []
        notes: list[str] = []
        gt_root = _require_dir(
            root / "other-gt-flow", "Middlebury GT folder", "expected other-gt-flow/<Seq>/flow10.flo"
        )
        for gt in sorted(gt_root.glob("*/flow10.flo"))[::stride]:
            seq = gt.parent.name
            image_dir = next(
                (
                    d
                    for d in (root / "other-data" / seq, root / "other-data-gray" / seq)
                    if (d / "frame11.png").is_file() and (d / "frame10.png").is_file()
                ),
                None,
            )
            if image_dir is None:
                raise InputError(
                    root / "other-data-gray" / seq / "frame11.png",
                    "frame pair for this GT not found",
                    "expected other-data[-gray]/<Seq>/frame10.png and frame11.png",
                )
            items.append(
                FlowItem(
                    seq,
                    [image_dir / "frame10.png", image_dir / "frame11.png"],
                    gt,
                    gt,
                    gt_format="flo",
                    snippet="10, 10, 11 (pair: sequence-start padding)",
                )
            )
        if not items:
            raise InputError(
                gt_root, "no <Seq>/flow10.flo ground truth", "Middlebury GT is other-gt-flow/<Seq>/flow10.flo"
            )
        notes.append("Middlebury has no occlusion masks: Noc = All")
        desc = f"Middlebury {', '.join(i.name for i in items)}"
        return Found(items, desc, notes)

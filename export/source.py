"""What an export starts from: :class:`Source` (the model and its provenance) and the graph-size rule.

Its own module so that :mod:`export.build` (which picks the source) and :mod:`export.from_tf` (which
makes one from TensorFlow checkpoints) both import it and neither imports the other's caller: the
two used to import each other inside functions (issue 42).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from geonet_infer.errors import InputError
from geonet_infer.models.manifest import SIZE_MULTIPLE


@dataclass
class Source:
    """The model to export and where it came from."""

    model: object  # training.model.GeoNet, eval mode
    arch: str
    height: int
    width: int
    seq_length: int
    random_init: bool
    checkpoint: Path | None = None
    ckpt: dict | None = None


def check_graph_size(height: int, width: int) -> None:
    """GeoNetError unless both sides are positive multiples of ``SIZE_MULTIPLE`` (DepthNet and
    ResFlowNet need them; the runtime refuses other manifests too)."""
    if height % SIZE_MULTIPLE or width % SIZE_MULTIPLE or height <= 0 or width <= 0:
        raise InputError(
            None,
            f"graph size {height}x{width} is not a positive multiple of {SIZE_MULTIPLE}",
            f"pass --height/--width divisible by {SIZE_MULTIPLE} (GeoNet and its released models use 128x416)",
        )

"""Bundled model directories (package data) and how a model argument is resolved.

Each sub-folder holding a ``manifest.json`` is a bundled model, named after the
folder. ``scripts/build_bundled_model.sh`` reproduces them from our own training
code; ``docs/models.md`` is their model card.
"""

from __future__ import annotations

from pathlib import Path

from geonet_infer.core.manifest import MANIFEST_NAME
from geonet_infer.errors import ModelError

MODELS_DIR = Path(__file__).resolve().parent
DEFAULT_MODEL = "small_synth"


def bundled_models() -> dict[str, Path]:
    """Name -> directory of every bundled model."""
    return {p.name: p for p in sorted(MODELS_DIR.iterdir()) if (p / MANIFEST_NAME).is_file()}


def resolve_model(model: str | Path | None = None) -> Path:
    """None -> the default bundled model; a bundled name -> its directory; else a model directory path."""
    bundled = bundled_models()
    name = DEFAULT_MODEL if model is None else str(model)
    if name in bundled:
        return bundled[name]
    path = Path(model) if model is not None else MODELS_DIR / DEFAULT_MODEL
    if path.is_dir():
        return path
    names = ", ".join(bundled) or "none installed"
    raise ModelError(
        path,
        "no such model directory or bundled model",
        f"pass a directory written by `python -m export` or a bundled name ({names})",
    )

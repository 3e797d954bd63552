"""The benchmark library behind ``geonet-infer bench``: its cases and the record of the machine.

Reports (``geonet-infer bench``, ``geonet-infer info``, the model card, export manifests)
record which commit they measured with :func:`git_commit`.
"""

from __future__ import annotations

import subprocess
from pathlib import Path

SOURCE_ROOT = Path(__file__).resolve().parents[1]  # the checkout, when running from one


def git_commit(root: Path | None = None, short: bool = False) -> str | None:
    """``git rev-parse [--short] HEAD`` in ``root`` (default: the checkout holding this package),
    or None where there is no git or no checkout (an installed wheel)."""
    root = SOURCE_ROOT if root is None else Path(root)
    if not (root / ".git").exists():
        return None
    cmd = ["git", "-C", str(root), "rev-parse", *(["--short"] if short else []), "HEAD"]
    try:
        out = subprocess.run(cmd, capture_output=True, text=True, timeout=10, check=False)
    except (OSError, subprocess.SubprocessError):
        return None
    if out.returncode != 0:
        return None
    return out.stdout.strip() or None

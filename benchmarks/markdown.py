"""Numbers and tables in Markdown, the one way every generated page writes them."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np


def sig3(x) -> str:
    """A number to 3 significant digits, without exponent for ordinary magnitudes."""
    if x is None:
        return "n/a"
    if isinstance(x, (bool, np.bool_)):
        return str(bool(x))
    if isinstance(x, (int, np.integer)):
        return str(int(x))
    x = float(x)
    if not math.isfinite(x):
        return str(x)
    if x == 0:
        return "0"
    r = float(f"{x:.3g}")
    if not 1e-4 <= abs(r) < 1e6:
        return f"{r:.3g}"
    decimals = max(0, 2 - int(math.floor(math.log10(abs(r)))))
    return f"{r:.{decimals}f}"


def signed3(x: float) -> str:
    """A difference to 3 significant digits with its sign."""
    s = sig3(x)
    return s if s.startswith("-") or s in ("0", "nan", "n/a") else "+" + s


def table(headers: Sequence[str], rows: Sequence[Sequence[str]]) -> list[str]:
    out = ["| " + " | ".join(headers) + " |", "|" + "|".join("---" for _ in headers) + "|"]
    out += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return out

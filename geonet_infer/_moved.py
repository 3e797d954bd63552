"""Aliases for the public names that moved in issue 42 (kept for one release, with a warning).

An old module keeps only ``__getattr__ = forward(__name__, "new.module", ...)``: the first use of a
name imports its new module (never at import time, so an alias loads nothing) and warns once per use.
"""

from __future__ import annotations

import importlib
import warnings
from collections.abc import Callable


def forward(old: str, *new: str, renamed: dict[str, str] | None = None) -> Callable[[str], object]:
    """A module ``__getattr__`` for ``old`` that finds each name in the first of ``new`` that has it
    (``renamed``: old name -> its new name there)."""

    def __getattr__(name: str) -> object:
        if name.startswith("__"):  # dunder look-ups (__path__, __file__ ...) are Python's, not users'
            raise AttributeError(name)
        now = (renamed or {}).get(name, name)
        for target in new:
            module = importlib.import_module(target)
            if hasattr(module, now):
                warnings.warn(
                    f"{old}.{name} moved to {target}.{now}; the old name goes in the next release",
                    DeprecationWarning,
                    stacklevel=2,
                )
                return getattr(module, now)
        raise AttributeError(f"module {old!r} has no attribute {name!r}")

    return __getattr__

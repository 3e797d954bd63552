"""Errors a user can act on: each names the offending file and what to do."""

from __future__ import annotations

from pathlib import Path


class GeoNetInputError(ValueError):
    """Bad input data or arguments. ``str(err)`` is '<path>: <problem>. <hint>'."""

    def __init__(self, path: str | Path | None, problem: str, hint: str = ""):
        self.path = None if path is None else Path(path)
        self.problem = problem
        self.hint = hint
        where = f"{self.path}: " if self.path is not None else ""
        super().__init__(f"{where}{problem}" + (f". {hint}" if hint else ""))

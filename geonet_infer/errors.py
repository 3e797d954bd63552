"""Errors a user can act on: each names the offending file and what to do.

``GeoNetError`` is the one class to catch; ``str(err)`` is '<path>: <problem>. <hint>'.
Under it, what went wrong decides the class:

- :class:`InputError`: bad input data or arguments (an unreadable frame, a 2x3 K);
- :class:`ModelError`: a model directory that cannot be used (manifest, graph files, hashes);
- :class:`BackendUnavailableError`: an optional inference backend that is not installed.

All are ``ValueError`` too, as the single ``GeoNetInputError`` of 0.x was.
"""

from __future__ import annotations

from pathlib import Path


class GeoNetError(ValueError):
    """Something the user can fix; ``path`` names the file or folder (None: an argument)."""

    def __init__(self, path: str | Path | None, problem: str, hint: str = ""):
        self.path = None if path is None else Path(path)
        self.problem = problem
        self.hint = hint
        where = f"{self.path}: " if self.path is not None else ""
        super().__init__(f"{where}{problem}" + (f". {hint}" if hint else ""))


class InputError(GeoNetError):
    """Bad input data or arguments: a frame, a calibration, a list file, a flag value."""


class ModelError(GeoNetError):
    """A model directory that cannot be loaded or lacks what a task needs."""


class BackendUnavailableError(GeoNetError):
    """An optional inference backend (OpenVINO) or runner (Ray) that is not installed."""


# Deprecated: the one error class before the hierarchy; kept for one release so that
# `except GeoNetInputError` still catches everything it used to.
GeoNetInputError = GeoNetError

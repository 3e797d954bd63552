"""Which files a run may write and remove: one rule for ``predict`` and ``batch``.

Before its first write a run lists, in a marker in its folder, every file it may write. The next run
into that folder removes exactly the listed files (and the temp files an interrupted writer left of
them), then the listed files' folders that are left empty; never a folder with anything else in it.
Every path a run writes is checked after symlinks are resolved: it must not be one of the run's
inputs, and must not be an existing file that no earlier run listed (a file the user made).
A ``--video-out`` outside the folder is listed with its path and, once complete, its sha256: an
identical re-run may replace that file while it is still the one the run wrote.
"""

from __future__ import annotations

import contextlib
import json
import os
from collections.abc import Iterable
from pathlib import Path

from geonet_infer.errors import InputError
from geonet_infer.io.atomic import leftover_temps
from geonet_infer.manifest import file_sha256


def real(path) -> Path:
    """``path`` with every symlink resolved (also for parts that do not exist yet)."""
    return Path(os.path.realpath(path))


def inside(path, folder) -> bool:
    """Whether ``path`` lies under ``folder``, both with symlinks resolved."""
    return real(folder) in real(path).parents


def read_marker(marker: Path) -> dict:
    """A run's marker: ``files`` (relative paths it may write) and ``outside`` ({path, sha256} of a
    video outside its folder); InputError (exit 2) when it cannot be read."""
    try:
        data = json.loads(marker.read_text())
        files, outside = data["files"], data.get("outside", [])
        assert isinstance(files, list) and all(isinstance(f, str) for f in files)
        assert isinstance(outside, list) and all(
            isinstance(o, dict) and isinstance(o.get("path"), str) for o in outside
        )
    except (OSError, ValueError, KeyError, TypeError, AssertionError, AttributeError, RecursionError):
        raise InputError(
            marker, "unreadable ownership marker", "pick another --out, or delete the folder yourself"
        ) from None
    return {"files": files, "outside": outside}


def listed_paths(folder: Path, rels: Iterable[str]) -> list[Path]:
    """The listed paths that lie in ``folder`` (symlinks resolved): an edited marker cannot reach elsewhere."""
    root = real(folder)
    out = []
    for rel in rels:
        path = folder / rel
        if Path(rel).is_absolute() or ".." in Path(rel).parts or root not in real(path).parents:
            continue
        out.append(path)
    return out


def remove_listed(folder: Path, rels: Iterable[str]) -> None:
    """Remove exactly the listed files under ``folder`` and the temp files of each that an interrupted
    writer left, then the folders between them and ``folder`` that are left empty."""
    parents: set[Path] = set()
    for path in listed_paths(folder, rels):
        if path.is_file() or path.is_symlink():
            path.unlink()
        for leftover in leftover_temps(path):
            leftover.unlink()
        parents.update(p for p in path.parents if folder in p.parents)
    for parent in sorted(parents, key=lambda p: len(p.parts), reverse=True):
        with contextlib.suppress(OSError):  # only when empty: a user's file there keeps it
            parent.rmdir()


def remove_outside_temps(outside: Iterable[dict]) -> None:
    """The temp files a killed run left next to its video outside the folder (the video itself stays)."""
    for entry in outside:
        for leftover in leftover_temps(entry["path"]):
            leftover.unlink()


def check_writes(
    folder: Path,
    writes: Iterable[str],
    previous: Iterable[str],
    inputs: Iterable[Path] = (),
    outside: Path | None = None,
    previous_outside: Iterable[dict] = (),
) -> None:
    """InputError (exit 2) before anything is written or removed when a file the run writes (``writes``,
    relative to ``folder``; ``outside``: its video elsewhere) or removes (``previous``) is one of its
    ``inputs``, or when a file it writes exists and no earlier run listed it (the user's)."""
    previous = set(previous)
    writes = set(writes)
    root = real(folder)
    for rel in sorted(writes):
        if root not in real(folder / rel).parents:
            raise InputError(
                folder / rel,
                f"leads out of {folder} (a symlink on the way)",
                "remove the symlink or pick another --out",
            )
    touched = {real(p): p for p in listed_paths(folder, writes | previous)}
    if outside is not None:
        touched[real(outside)] = outside
    for given in inputs:
        hit = touched.get(real(given))
        if hit is not None:
            raise InputError(
                given,
                f"this input is {hit}, a file this run would write or remove",
                "pick another --out (or --video-out): predict never writes over its input",
            )
    for rel in sorted(writes - previous):
        path = folder / rel
        if path.exists() or path.is_symlink():
            raise not_written(path)
    if outside is not None and outside.exists():
        recorded = {real(o["path"]): o.get("sha256") for o in previous_outside}
        digest = recorded.get(real(outside))
        if digest is None or file_sha256(outside) != digest:
            raise not_written(outside)


def not_written(path: Path) -> InputError:
    return InputError(
        path,
        "exists, and predict does not overwrite files it did not write",
        "move it away or pick another name (or another --out)",
    )

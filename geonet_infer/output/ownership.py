"""Which files a run may write and remove: one rule for ``predict`` and ``batch``.

Before its first write a run lists, in a marker in its folder, every file it may write. The next run
into that folder removes exactly the listed files (and the temp files an interrupted writer left of
them), then the listed files' folders that are left empty; never a folder with anything else in it.
Every path a run writes is checked after symlinks are resolved: it must not be one of the run's
inputs, and must not be an existing file that no earlier run listed (a file the user made).
A ``--video-out`` outside the folder is listed with its path and, once complete, its sha256: an
identical re-run may replace that file while it is still the one the run wrote.

One lock, too (:class:`PidLock`): a file created with O_EXCL that holds the writer's pid, removed at
exit; a lock whose process is gone (killed) is taken over. ``predict`` locks its OUT, ``batch`` its
job's OUT (each sequence's run inside it then writes under batch's lock: :class:`OwnedFolder`'s
``claimed_by``).
"""

from __future__ import annotations

import contextlib
import json
import os
from collections.abc import Iterable
from pathlib import Path

from geonet_infer.errors import InputError
from geonet_infer.io.atomic import atomic_write, leftover_temps
from geonet_infer.models.manifest import file_sha256


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


class PidLock:
    """``path`` as the lock of one writer: created with O_EXCL and holding its pid, removed at exit.

    A lock whose pid is alive refuses the second writer (InputError naming ``folder``: "``who`` is
    writing into this folder"); one whose process is gone (killed) is taken over.
    """

    def __init__(self, path: Path, who: str, hint: str):
        self.path, self.who, self.hint = Path(path), who, hint

    def __enter__(self) -> PidLock:
        for _ in range(2):
            try:
                fd = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
            except FileExistsError:
                pid = lock_pid(self.path)
                if pid is None or alive(pid):
                    who = f"{self.who} (pid {pid})" if pid else self.who
                    raise InputError(
                        self.path.parent,
                        f"{who} is writing into this folder",
                        f"{self.hint} (if none is running, delete {self.path})",
                    ) from None
                self.path.unlink(missing_ok=True)  # its process is gone (killed): a stale lock
                continue
            with os.fdopen(fd, "w") as f:
                f.write(f"{os.getpid()}\n")
            return self
        raise InputError(self.path.parent, f"{self.who} took this folder", self.hint)

    def __exit__(self, *exc) -> None:
        self.path.unlink(missing_ok=True)


def lock_pid(lock: Path) -> int | None:
    with contextlib.suppress(OSError, ValueError):
        return int(lock.read_text().strip())
    return None  # empty: its writer is between creating and filling it


def alive(pid: int) -> bool:
    if pid < 1:  # 0 and negative numbers name process groups, not a run
        return False
    try:
        os.kill(pid, 0)
    except (ProcessLookupError, OverflowError):  # Overflow: a number no pid reaches (an edited lock)
        return False
    except PermissionError:  # another user's process
        return True
    return True


class OwnedFolder:
    """OUT as the folder of one predict run: lock, ownership marker, removal of the previous run's files.

    * Lock: ``lock`` (:class:`PidLock`) for the run's lifetime.
    * Ownership: a non-empty OUT without ``marker`` is refused (its files are not ours).
      With the marker, the files it lists (and temp files of an interrupted writer) are removed,
      nothing else: files a user added to OUT stay. A file this run writes that exists and is not
      listed, or that is an input, refuses the run before anything is removed.
    * The marker is written before the first output and lists every file this run may write, so a
      run that is killed still leaves a marker that covers all it wrote.
    * ``claimed_by``: names of another owner's markers in OUT (batch's): that owner holds the lock and
      vouches for OUT; its files are never touched.
    """

    def __init__(
        self,
        out_dir: Path,
        files: set[str],
        input_path,
        *,
        marker: str,
        lock: str,
        record: dict,
        inputs: tuple[Path, ...] = (),
        outside: Path | None = None,
        claimed_by: tuple[str, ...] = (),
    ):
        self.out_dir, self.files, self.input = out_dir, set(files), str(input_path)
        self.inputs, self.claimed_by, self.record = inputs, claimed_by, record
        self.outside = None if outside is None else real(outside)  # the video, outside OUT
        self.outside_sha256: str | None = None  # once it is complete
        self.lock = PidLock(out_dir / lock, f"another {record['written_by']}", "wait for it or pick another --out")
        self.marker = out_dir / marker

    def __enter__(self) -> OwnedFolder:
        self.out_dir.mkdir(parents=True, exist_ok=True)
        if not self.claimed_by:
            self.lock.__enter__()
        try:
            self._clear_previous_run()
            self._write_marker()
        except BaseException:
            self.__exit__()
            raise
        return self

    def __exit__(self, *exc) -> None:
        if not self.claimed_by:
            self.lock.__exit__()

    def add(self, files: set[str]) -> None:
        """Record more files before writing them (a video that decodes more frames than it lists)."""
        if not files <= self.files:
            check_writes(self.out_dir, files - self.files, (), self.inputs)
            # the marker first: cut short (Ctrl-C), the names are not taken as recorded and are claimed again
            self._write_marker(self.files | files)
            self.files |= files

    def video_written(self, path: Path) -> None:
        """Record the digest of the finished video outside OUT: an identical re-run may replace it."""
        if self.outside is not None and real(path) == self.outside:
            self.outside_sha256 = file_sha256(path)
            self._write_marker()

    def _clear_previous_run(self) -> None:
        others = [p for p in self.out_dir.iterdir() if p.name not in (self.lock.path.name, *self.claimed_by)]
        previous: dict = {"files": [], "outside": []}
        if self.marker.is_file():
            previous = read_marker(self.marker)
        elif others and not (set(self.claimed_by) & {p.name for p in self.out_dir.iterdir()}):
            raise InputError(
                self.out_dir,
                f"this folder is not empty and was not written by {self.record['written_by']}",
                "pick another --out (predict never overwrites files it did not write)",
            )
        check_writes(self.out_dir, self.files, previous["files"], self.inputs, self.outside, previous["outside"])
        remove_listed(self.out_dir, previous["files"])
        remove_outside_temps(previous["outside"])

    def _write_marker(self, files: set[str] | None = None) -> None:
        marker: dict[str, object] = {**self.record, "input": self.input}
        marker["files"] = sorted(self.files if files is None else files)
        marker["outside"] = [] if self.outside is None else [{"path": str(self.outside), "sha256": self.outside_sha256}]
        with atomic_write(self.marker) as tmp:
            tmp.write_text(json.dumps(marker) + "\n")

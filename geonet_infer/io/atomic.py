"""Atomic writes: a crash never leaves a half-written file where a reader would trust it. Blocks that a
Ctrl-C or SIGTERM does not cut in two (:func:`signals_noted`, :func:`interrupts_held`)."""

from __future__ import annotations

import contextlib
import errno
import math
import os
import re
import secrets
import signal
import threading
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

__all__ = ["atomic_write", "create_temp", "interrupts_held", "leftover_temps", "save_npy_atomic", "signals_noted"]


def _temp_affixes(path: Path) -> tuple[str, str]:
    """(prefix, suffix) of the temp names of ``path``: :func:`create_temp` puts 8 random characters between them."""
    return f".{path.stem}.", path.suffix or ".tmp"


def leftover_temps(path) -> list[Path]:
    """The temp files an :func:`atomic_write` of ``path`` that was killed mid-write may have left."""
    path = Path(path)
    if not path.parent.is_dir():
        return []
    prefix, suffix = _temp_affixes(path)
    name = re.compile(re.escape(prefix) + r"[a-z0-9_]{8}" + re.escape(suffix))
    return [p for p in path.parent.iterdir() if name.fullmatch(p.name) and p.is_file()]


_UMASK_LOCK = threading.Lock()


def _umask() -> int:
    # os.umask can only be read by setting it: two threads doing this at once could leave it at 0.
    with _UMASK_LOCK:
        mask = os.umask(0)
        os.umask(mask)
    return mask


_TEMP_CHARS = "abcdefghijklmnopqrstuvwxyz0123456789_"


def create_temp(path: Path, hold: Callable[[Path | None], object]) -> Path:
    """Create a new empty file (0600, O_EXCL, as mkstemp) named like ``path``'s temps, and return its name.

    ``hold(name)`` is called before the file exists (and ``hold(None)`` when another file has that name):
    the caller holds the name from then on, so an exception a signal handler raises at any point (a batch
    worker's SIGTERM) still lets it remove the temp. With mkstemp such an exception could come after its
    open and before its return, and the temp stayed behind (seen in a CI run, issue 43).
    """
    prefix, suffix = _temp_affixes(path)
    for _ in range(100):
        name = path.parent / (prefix + "".join(secrets.choice(_TEMP_CHARS) for _ in range(8)) + suffix)
        hold(name)
        try:
            os.close(os.open(name, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600))
        except FileExistsError:  # another's file: never ours to remove
            hold(None)
            continue
        return name
    raise FileExistsError(errno.EEXIST, "no free temporary name", str(path))


@contextlib.contextmanager
def atomic_write(path) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; rename it onto ``path`` on success.

    The temp file lives in the same directory (so the rename is atomic on POSIX)
    and keeps the same suffix (readers that go by the suffix see the right one). If the
    body raises, the temp file is deleted and ``path`` is left untouched.
    Parent directories are created.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    held: list[Path | None] = [None]
    try:  # an interrupt (Ctrl-C, SIGTERM) at any point from the temp's creation on still removes it
        tmp = create_temp(path, lambda name: held.__setitem__(0, name))
        yield tmp
        # the temp is 0600; outputs get the mode a plain open() would give (0666 & ~umask).
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    except BaseException as exc:
        if held[0] is not None:
            with contextlib.suppress(FileNotFoundError):
                held[0].unlink()
        if isinstance(exc, OSError) and exc.filename is None:  # the error names the file it failed on
            # numpy's short write (a full disk) says only "N requested and M written", without errno
            why = exc.strerror or f"{exc} (a short write: is the disk full?)"
            raise OSError(exc.errno, why, str(path)) from exc
        raise


def save_npy_atomic(path, array) -> None:
    """Write ``array`` as a ``.npy`` file at exactly ``path``, atomically.

    ``np.save`` writes to an open file handle, so no ``.npy`` suffix is appended
    to the name. Object arrays are refused (``allow_pickle=False``): a ``.npy``
    holding pickles can run code when loaded.
    """
    arr = np.asarray(array)
    with atomic_write(path) as tmp, open(tmp, "wb") as f:
        np.save(f, arr, allow_pickle=False)


@contextlib.contextmanager
def signals_noted() -> Iterator[list[int]]:
    """Ctrl-C and SIGTERM only noted (not acted on) inside the block; yields the list that gets the signals
    that came. Their handlers are put back at the end. Signal handlers run on the main thread only:
    elsewhere this does nothing (and the list stays empty)."""
    caught: list[int] = []
    if threading.current_thread() is not threading.main_thread():
        yield caught
        return
    previous: dict[int, Callable | int] = {}
    try:
        for signum in (signal.SIGINT, signal.SIGTERM):
            handler = signal.getsignal(signum)
            if handler is not None:  # None: set outside Python, it could not be put back
                signal.signal(signum, lambda number, frame: caught.append(number))
                previous[signum] = handler
        yield caught
    finally:
        for installed, handler in previous.items():
            signal.signal(installed, handler)


@contextlib.contextmanager
def interrupts_held() -> Iterator[None]:
    """Ctrl-C and SIGTERM held back until the block ends, then delivered to their own handlers, as if they
    came just after it. Python runs a signal's handler between any two bytecodes of the main thread: this
    keeps bookkeeping that must happen together from being cut in two. Keep the block short: a wait
    inside it cannot be interrupted."""
    caught: list[int] = []
    try:
        with signals_noted() as caught:
            yield
    finally:
        for signum in caught:
            signal.raise_signal(signum)


def json_safe(value):
    """``value`` as strict JSON holds it: NaN and infinity become None, tuples and arrays lists, numpy
    (and torch) scalars Python numbers, paths strings (manifests, eval results, summaries)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if isinstance(value, Path):
        return str(value)
    if hasattr(value, "tolist") and not isinstance(value, (str, bytes)):  # numpy arrays and scalars, torch tensors
        return json_safe(value.tolist())
    return value

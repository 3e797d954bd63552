"""What a batch job runs on: its inputs (folders, videos, KITTI drives, list files) as work units."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from geonet_infer.errors import InputError
from geonet_infer.io.layouts import find_layout
from geonet_infer.output.layout import SUMMARY_NAME

# The names batch keeps in OUT beside the sequence folders (a sequence is never named so).
MARKER_NAME = ".done"
OWNER_NAME = ".geonet-batch"
FAILURES_NAME = "failures.jsonl"
LOCK_NAME = ".lock"
_RESERVED = {SUMMARY_NAME, FAILURES_NAME, LOCK_NAME, MARKER_NAME, OWNER_NAME}


LIST_SUFFIX = ".txt"
CALIB_SEPARATOR = "|"  # in an input list: INPUT | ITS CALIBRATION


# ----------------------------------------------------------------------------- work units
@dataclass(frozen=True)
class WorkUnit:
    """One sequence: ``index`` = position in the input order, ``name`` = its folder under OUT."""

    index: int
    name: str
    path: str  # absolute
    calib: str = ""  # absolute: its calibration from the input list ("": none given there)


def read_input_list(path: Path) -> list[Path]:
    """The inputs listed in a text file (:func:`read_input_pairs`, without their calibrations)."""
    return [p for p, _ in read_input_pairs(path)]


def read_input_pairs(path: Path) -> list[tuple[Path, Path | None]]:
    """(input, its calibration or None) listed in a text file, one input a line, optionally followed
    by ``|`` and its calibration file (``clip_a.mp4 | camera_a.txt``); blank lines and ``#`` comments
    skipped; relative paths are relative to the list file's folder."""
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(
            path,
            f"cannot read this input list ({exc.__class__.__name__})",
            "pass a text file with one input path a line",
        ) from None

    def located(text: str) -> Path:
        p = Path(text.strip()).expanduser()
        return p if p.is_absolute() else path.parent / p

    out: list[tuple[Path, Path | None]] = []
    for number, line in enumerate(text.splitlines(), 1):
        line = line.strip()
        if line and not line.startswith("#"):
            item, bar, calib = line.partition(CALIB_SEPARATOR)
            if bar and not (item.strip() and calib.strip()):
                raise InputError(path, f"line {number}: {line!r}", f"write INPUT {CALIB_SEPARATOR} CALIBRATION")
            out.append((located(item), located(calib) if bar else None))
    return out


def expand_inputs(inputs) -> list[Path]:
    """INPUTS as given: ``.txt`` files replaced by the paths they list (:func:`expand_input_pairs`)."""
    return [p for p, _ in expand_input_pairs(inputs)]


def expand_input_pairs(inputs) -> list[tuple[Path, Path | None]]:
    """INPUTS as given, each with the calibration its list pairs it with (or None): ``.txt`` files
    replaced by what they list (:func:`read_input_pairs`); every path must exist.

    Raises GeoNetError naming the first missing path (and how many are missing).
    """
    pairs: list[tuple[Path, Path | None]] = []
    for given in map(Path, inputs):
        if given.suffix.lower() == LIST_SUFFIX and given.is_file():
            listed = read_input_pairs(given)
            bad = [p for p, _ in listed if p.suffix.lower() == LIST_SUFFIX and p.is_file()]
            if bad:
                raise InputError(
                    bad[0], f"listed in {given}, but input lists do not nest", "list the sequences themselves"
                )
            pairs += listed
        else:
            pairs.append((given, None))
    paths = [p for p, _ in pairs] + [c for _, c in pairs if c is not None]
    missing = [p for p in paths if not p.exists()]
    if missing:
        more = f" (and {len(missing) - 1} more missing)" if len(missing) > 1 else ""
        raise InputError(
            missing[0], f"not found{more}", "pass sequence folders, videos, KITTI drives or a .txt file listing them"
        )
    if not pairs:
        raise InputError(None, "no inputs", "pass sequence folders, videos, KITTI drives or a .txt list")
    return pairs


def sequence_name(path) -> str:
    """The sequence's name as ``open_frames`` gives it (video stem, KITTI drive or folder name),
    worked out from the path alone (a broken video still gets its name)."""
    p = Path(os.path.abspath(path))
    if p.is_file():
        return p.stem
    layout = find_layout(p)
    return p.name if layout is None else layout.name


def _safe_name(name: str) -> str:
    """A folder name under OUT that cannot be a reserved or hidden file."""
    if not name or name.startswith(".") or name in _RESERVED or "/" in name or "\\" in name:
        return f"seq_{name.lstrip('.')}" if name.strip(".") else "seq"
    return name


def sequence_root(path: Path) -> Path:
    """The folder or file a sequence is named after (a KITTI drive for ``.../image_02/data``, a
    dataset's sequence folder for its frames folder: :mod:`geonet_infer.io.layouts`)."""
    p = Path(os.path.abspath(path))
    layout = find_layout(p)
    return p if layout is None else layout.root


def plan_units(paths, calibs=None) -> list[WorkUnit]:
    """One unit per distinct input (the same real path twice = once), in input order; ``calibs``:
    each input's calibration from its list, or None (:func:`expand_input_pairs`).

    Names are the sequences' names. Inputs that share a name are each called
    ``<name>__<folder it is in>``; if that still collides, the later ones get ``__2``,
    ``__3``, ... in input order. So the names depend only on the inputs and their order.
    """
    seen, distinct, calib_of = set(), [], []
    for p, calib in zip(paths, calibs or [None] * len(paths)):
        real = os.path.realpath(p)
        if real not in seen:
            seen.add(real)
            distinct.append(Path(os.path.abspath(p)))
            calib_of.append("" if calib is None else os.path.abspath(calib))
    base = [_safe_name(sequence_name(p)) for p in distinct]
    names = [
        f"{n}__{sequence_root(p).parent.name or 'root'}" if base.count(n) > 1 else n for p, n in zip(distinct, base)
    ]
    final: list[str] = []
    for n in names:
        candidate, k = n, 1
        while candidate in final or (candidate != n and candidate in names):
            k += 1
            candidate = f"{n}__{k}"
        final.append(candidate)
    return [WorkUnit(i, n, str(p), c) for i, (n, p, c) in enumerate(zip(final, distinct, calib_of))]


def needs_own_calib(path) -> bool:
    """Whether the input has no calibration of its own: no ``<name>.calib.txt`` beside it
    (:func:`~geonet_infer.io.frames.find_side_calib`) and not a KITTI drive with its file."""
    from geonet_infer.io.frames import find_side_calib
    from geonet_infer.io.layouts import find_layout

    root = sequence_root(path)
    if find_side_calib(root) is not None:
        return False
    layout = find_layout(root)
    return layout is None or (layout.calib is None and layout.tum_camera is None)

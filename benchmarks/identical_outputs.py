"""Does this checkout's `geonet-infer predict` write the same bytes as an older revision?

A restructure must not change what users get. This runs the documented `predict` commands
on the KITTI drive in ../shared with the working tree and with REVISION (checked out into a
temporary git worktree, run from there), then compares the two output folders file by file:
the same names, the same bytes. ``summary.json`` is compared as JSON without what is
measured or per-run (timings, frames/s, dates, the output path); records this checkout added are
listed, not compared (every record the revision wrote must be unchanged); every other file must match
byte for byte (depth .npy, colour maps, KITTI flow PNGs, pose files).

    python benchmarks/identical_outputs.py --against 3c9be22
    python benchmarks/identical_outputs.py --against 3c9be22 --cases kitti_depth_metric
    python benchmarks/identical_outputs.py --against c56716d --after-args "--mode latency"   (this checkout's only)
    python benchmarks/identical_outputs.py --against c56716d --same-model   (both on c56716d's bundled model)

``--same-model``: both trees run REVISION's bundled model instead of their own, so that the runtime's
arithmetic is compared after the bundled model itself was replaced (issue 53 shipped a new one).

Exit 0 when every case is identical, 1 otherwise (the differing files are listed).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import shlex
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np

from geonet_infer.models import DEFAULT_MODEL

REPO = Path(__file__).resolve().parents[1]
KITTI = (REPO / "../shared/realdata/kitti_raw_2011_09_26_sfnd").resolve()
CASES = {  # name -> predict arguments after INPUT (all on the KITTI drive, calibration found there)
    "kitti_all": [],
    "kitti_depth_metric": ["--tasks", "depth", "--camera-height", "1.65"],
    "kitti_int8_batch3": ["--precision", "int8", "--batch-size", "3", "--no-vis"],
    "kitti_pose": ["--tasks", "pose"],
}
BUNDLED_MODEL = Path("geonet_infer/models", DEFAULT_MODEL)  # inside a tree
# summary.json keys that differ between any two runs of the same code
PER_RUN_KEYS = {"timings_ms_per_frame", "overlapped_ms_per_frame", "wall_s", "frames_per_s"}


def run_cli(tree: Path, args: list[str]) -> None:
    """``geonet-infer ARGS`` with the package of ``tree`` (a checkout or a revision's worktree)."""
    env = {**os.environ, "PYTHONPATH": str(tree)}
    # cwd = the tree: `python -m` puts the working directory first on sys.path
    done = subprocess.run(
        [sys.executable, "-m", "geonet_infer.cli", *args], cwd=tree, env=env, capture_output=True, text=True
    )
    if done.returncode != 0:
        raise SystemExit(f"{tree}: {' '.join(args)} exited {done.returncode}:\n{done.stderr}")


def run_predict(tree: Path, args: list[str], out: Path) -> None:
    run_cli(tree, ["predict", str(KITTI), "--out", str(out), "--no-progress", *args])


@contextlib.contextmanager
def revision_tree(revision: str, parent: Path) -> Iterator[Path]:
    """``revision`` checked out into a temporary git worktree under ``parent`` (removed after)."""
    tree = parent / "tree"
    subprocess.run(["git", "worktree", "add", "--detach", "-q", str(tree), revision], cwd=REPO, check=True)
    try:
        yield tree
    finally:
        subprocess.run(["git", "worktree", "remove", "--force", str(tree)], cwd=REPO, check=False)


def _strip(obj):
    if isinstance(obj, dict):
        return {k: _strip(v) for k, v in obj.items() if k not in PER_RUN_KEYS}
    if isinstance(obj, list):
        return [_strip(v) for v in obj]
    return obj


def _unrooted(text: bytes, roots: tuple[Path, Path]) -> str:
    out = text.decode()
    for root in roots:
        out = out.replace(str(root), "<tree>")
    return out


def _json_diff(before, after, at: str = "") -> tuple[list[str], list[str]]:
    """(changed, added): the key paths whose values differ or that ``after`` lost, and those only ``after``
    has (records a later version added: what was there before must be unchanged, new records are new)."""
    if not (isinstance(before, dict) and isinstance(after, dict)):
        return ([at or "."] if before != after else []), []
    changed, added = [], []
    for key in sorted(before.keys() | after.keys()):
        path = f"{at}.{key}" if at else key
        if key not in after:
            changed.append(path)
        elif key not in before:
            added.append(path)
        else:
            more_changed, more_added = _json_diff(before[key], after[key], path)
            changed += more_changed
            added += more_added
    return changed, added


def _same_pixels(a: Path, b: Path) -> bool:
    pixels = [cv2.imread(str(p), cv2.IMREAD_UNCHANGED) for p in (a, b)]
    return all(p is not None for p in pixels) and pixels[0].dtype == pixels[1].dtype and np.array_equal(*pixels)


def compare(before: Path, after: Path, roots: tuple[Path, Path]) -> list[str]:
    """The differences between two output folders, one line each (empty: identical).

    ``roots``: the two source trees, whose paths (the bundled model's folder) may appear in summary.json.
    """
    files_before = {p.relative_to(before) for p in before.rglob("*") if p.is_file()}
    files_after = {p.relative_to(after) for p in after.rglob("*") if p.is_file()}
    diffs = [f"only before: {p}" for p in sorted(files_before - files_after)]
    diffs += [f"only after: {p}" for p in sorted(files_after - files_before)]
    for rel in sorted(files_before & files_after):
        a, b = (before / rel).read_bytes(), (after / rel).read_bytes()
        if rel.name == "summary.json":
            sa, sb = _strip(json.loads(_unrooted(a, roots))), _strip(json.loads(_unrooted(b, roots)))
            changed, added = _json_diff(sa, sb)
            if changed:
                diffs.append(f"differs (beyond timings): {rel}: {', '.join(changed)}")
            if added:
                print(f"  records added since, not compared: {rel}: {', '.join(added)}")
        elif rel.name.startswith(".geonet-predict"):
            continue  # ownership marker and lock: paths and pids of this run
        elif rel.suffix == ".png" and a != b:
            # PNG is lossless: the same pixels are the same output, whatever filter or deflate wrote them
            # (issue 43 moved the flow PNG from the Sub to the Up filter).
            if not _same_pixels(before / rel, after / rel):
                diffs.append(f"differs (pixels): {rel}")
        elif a != b:
            diffs.append(f"differs: {rel}")
    return diffs


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--against", required=True, help="git revision to compare with (e.g. the last release)")
    parser.add_argument("--cases", default=",".join(CASES), help=f"comma list of {','.join(CASES)}")
    parser.add_argument("--after-args", default="", help="more predict arguments for this checkout's runs")
    parser.add_argument(
        "--same-model", action="store_true", help="both trees run the revision's bundled model, not their own"
    )
    args = parser.parse_args(argv)
    cases = args.cases.split(",")
    unknown = [c for c in cases if c not in CASES]
    if unknown:
        parser.error(f"unknown case(s) {unknown}; choose from {','.join(CASES)}")
    failed = 0
    with (
        tempfile.TemporaryDirectory(prefix="geonet_identical_") as tmp,
        revision_tree(args.against, Path(tmp)) as old_tree,
    ):
        model = ["--model", str(old_tree / BUNDLED_MODEL)] if args.same_model else []
        for case in cases:
            outs = {}
            for label, tree, more in (("before", old_tree, []), ("after", REPO, shlex.split(args.after_args))):
                more = model + more
                outs[label] = Path(tmp) / f"{case}_{label}"
                run_predict(tree, CASES[case] + more, outs[label])
            diffs = compare(outs["before"], outs["after"], (old_tree, REPO))
            n_files = sum(1 for p in outs["after"].rglob("*") if p.is_file())
            print(f"{case}: {'identical' if not diffs else 'DIFFERENT'} ({n_files} files)")
            for line in diffs[:20]:
                print(f"  {line}")
            failed += bool(diffs)
    print(f"{len(cases) - failed}/{len(cases)} cases identical to {args.against}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())

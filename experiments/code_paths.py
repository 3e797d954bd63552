"""Which source files does each main path of the project pass through?

A newcomer changing how a video is predicted, how the benchmark measures or how a trained
model reaches the runtime has to read the files the code runs through. This counts them:
each path runs for real (small inputs) under a profiler hook, and a file counts when one of
its functions is called after the path's entry point (module and class bodies, i.e. imports,
do not count, nor do the argument parsers of other subcommands).

    python experiments/code_paths.py                        # this checkout, all paths
    python experiments/code_paths.py --root /tmp/old_tree   # another checkout (git worktree add ...)
    python experiments/code_paths.py --paths predict --list

Paths: predict (`geonet-infer predict` on the KITTI drive in ../shared), bench
(`geonet-infer bench --iters 2 --warmup 1`), train_export_load (`python -m training.train` for
2 steps on a tiny synthetic set, `python -m export`, `geonet_infer.load`). docs/architecture.md
lists the files each path prints.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
KITTI = str((REPO / "../shared/realdata/kitti_raw_2011_09_26_sfnd").resolve())
FRAME = f"{KITTI}/image_02/data/0000000000.png"

# Runs `python -m MODULE ARGS` (or CODE with `-c`) and writes the source files of ROOT whose
# functions ran, once the function named by TRACE_FROM ("path/to/file.py:function") was entered.
TRACER = r"""
import os, runpy, sys, threading
root, out, start = os.environ["TRACE_ROOT"], os.environ["TRACE_OUT"], os.environ.get("TRACE_FROM")
seen, started = set(), [start is None]
follow, target, stops = os.environ.get("TRACE_ARGS"), [None], []  # the calls that receive the start's `args`
first, called = [], set()  # each function of the main thread the first time it is called, in order

def hook(frame, event, arg):
    code = frame.f_code
    if event != "call" or not code.co_flags & 1 or not code.co_filename.startswith(root + os.sep):
        return None  # co_flags & 1 (CO_OPTIMIZED): a function body, not a module or class body
    rel = os.path.relpath(code.co_filename, root)
    if rel.startswith(".") or "site-packages" in rel:
        return None
    if not started[0]:
        if f"{rel}:{code.co_name}" != start:
            return None
        started[0] = True
        if follow:
            target[0] = frame.f_locals.get(follow)
    seen.add(rel)
    if threading.current_thread() is threading.main_thread() and (rel, code.co_name) not in called:
        called.add((rel, code.co_name))
        first.append(rel)
    if target[0] is not None and any(v is target[0] for v in frame.f_locals.values()):
        stops.append(f"{rel}:{code.co_name}")

sys.setprofile(hook)
threading.setprofile(hook)
try:
    if sys.argv[1] == "-c":
        sys.argv = ["-c", *sys.argv[3:]]
        exec(compile(os.environ["TRACE_CODE"], "<trace>", "exec"), {"__name__": "__main__"})
    else:
        sys.argv = [sys.argv[1], *sys.argv[2:]]
        runpy.run_module(sys.argv[0], run_name="__main__", alter_sys=True)
except SystemExit as exc:
    if exc.code not in (0, None):
        raise
finally:
    sys.setprofile(None)
    with open(out, "a") as fh:
        fh.writelines(f"{name}\n" for name in sorted(seen))
        fh.writelines(f"STOP {name}\n" for name in stops)
        fh.writelines(f"FIRST {name}\n" for name in first)
"""


def traced(root: Path, out: Path, module_args: list[str], start: str | None = None, code: str | None = None) -> None:
    env = {**os.environ, "PYTHONPATH": str(root), "TRACE_ROOT": str(root), "TRACE_OUT": str(out)}
    env.pop("TRACE_FROM", None)
    if start:
        env["TRACE_FROM"] = start
        env["TRACE_ARGS"] = "args"
    if code:
        env["TRACE_CODE"] = code
    cmd = [sys.executable, "-c", TRACER, *(["-c", "code"] if code else []), *module_args]
    # cwd = the tree: `python -c` and `-m` put the working directory first on sys.path
    done = subprocess.run(cmd, cwd=root, env=env, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(module_args) or code}: exited {done.returncode}\n{done.stderr[-3000:]}")


def run_path(name: str, root: Path, tmp: Path) -> list[str]:
    out = tmp / f"{name}.txt"
    cli = ["geonet_infer.cli"]
    if name == "predict":
        traced(
            root,
            out,
            [*cli, "predict", KITTI, "--out", str(tmp / "predict"), "--no-progress", "--quiet"],
            start="geonet_infer/cli/predict.py:run",
        )
    elif name == "bench":
        traced(
            root,
            out,
            [*cli, "bench", "--iters", "2", "--warmup", "1", "--json", str(tmp / "bench.json")],
            start="geonet_infer/cli/bench.py:run",
        )
    elif name == "train_export_load":
        data, prepared, run_dir, model = tmp / "synth", tmp / "prepared", tmp / "run", tmp / "model"
        env = {**os.environ, "PYTHONPATH": str(root)}
        for step in (
            ["training.synth", "--out", str(data), "--sequences", "2", "--frames", "8", "--seed", "0"],
            ["training.prepare", "--kind", "synth", "--src", str(data), "--out", str(prepared), "--heldout", "1"],
        ):  # the data the path needs: made here, not counted
            subprocess.run([sys.executable, "-m", *step], cwd=root, env=env, check=True, capture_output=True)
        traced(
            root,
            out,
            [
                "training.train",
                "--stage",
                "rigid",
                "--arch",
                "small",
                "--data-dir",
                str(prepared),
                "--out-dir",
                str(run_dir),
                "--max-steps",
                "2",
                "--num-workers",
                "0",
            ],
        )
        traced(
            root,
            out,
            [
                "export",
                "--checkpoint",
                str(run_dir / "last.pt"),
                "--out",
                str(model),
                "--graphs",
                "depthnet,posenet,rigidflow",
            ],
        )
        traced(
            root,
            out,
            [],
            code=f"import geonet_infer\ngeonet_infer.load({str(model)!r}).depth({FRAME!r})",
        )
    else:
        raise ValueError(name)
    lines = out.read_text().splitlines()
    files = sorted({line for line in lines if not line.startswith(("STOP ", "FIRST "))})
    return (
        files,
        [line[5:] for line in lines if line.startswith("STOP ")],
        [line[6:] for line in lines if line.startswith("FIRST ")],
    )


def returns(stops: list[str]) -> int:
    """How often a sequence of calls ("file" or "file:function") comes back to a file it had left (issue 56)."""
    files = [stop.split(":")[0] for stop in stops]
    left, count = set(), 0
    for previous, current in zip(files, files[1:]):
        if current != previous:
            left.add(previous)
            count += current in left
    return count


PATHS = ("predict", "bench", "train_export_load")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--root", type=Path, default=REPO, help="the checkout to measure (default: this one)")
    parser.add_argument("--paths", default=",".join(PATHS), help=f"comma list of {','.join(PATHS)}")
    parser.add_argument("--list", action="store_true", help="print each path's files, not only the counts")
    parser.add_argument("--json", type=Path, help="write {path: [files]} here")
    args = parser.parse_args(argv)
    root = args.root.resolve()
    result = {}
    with tempfile.TemporaryDirectory(prefix="geonet_paths_") as tmp:
        for name in args.paths.split(","):
            result[name], stops, first = run_path(name, root, Path(tmp))
            print(f"{name}: {len(result[name])} files")
            if first:
                print(f"  functions in the order first called (main thread): {len(first)}, "
                      f"{returns(first)} returns to a file already left")  # fmt: skip
            if stops:
                files = {stop.split(":")[0] for stop in stops}
                print(f"  `args` of its entry point: {len(stops)} stops in {len(files)} files, "
                      f"{returns(stops)} returns to a file already left")  # fmt: skip
            if args.list:
                print("".join(f"  {f}\n" for f in result[name]), end="")
                print("".join(f"  -> {stop}\n" for stop in stops), end="")
    if args.json:
        args.json.write_text(json.dumps(result, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""``geonet-infer``: depth, optical flow and camera pose from video on CPU.

One module per subcommand; each has ``add_parser(subparsers)`` and ``run(args) -> int``, and is
imported only when chosen (``geonet-infer info`` does not load the batch or eval code): the
other subcommands are listed from :data:`COMMANDS` alone.
Exit codes, for every subcommand: 0 all good, 1 some items failed (recorded in the
output), 2 bad usage or input (one line on stderr naming the item), 3 the operating system
refused a read or write (permission, disk full, read-only; one line naming the path),
130 interrupted (Ctrl-C or SIGTERM).
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from collections.abc import Callable, Sequence

from geonet_infer.errors import GeoNetError

# subcommand -> its one-line help (module geonet_infer.cli.<name>), in the order --help lists them
COMMANDS = {
    "predict": "depth, flow and poses for a video or a folder of frames",
    "batch": "many sequences (folders, videos, KITTI drives, lists) on many CPUs",
    "demo": "run on the bundled sample and write demo.png",
    "info": "versions, CPU, threads and the model's manifest",
    "bench": "latency of each stage (network only and end to end), table + JSON",
    "eval": "accuracy against ground truth (model or baselines), paper's tables",
    "convert": "the authors' released TensorFlow checkpoints -> a model by name (no torch, no TensorFlow)",
    "models": "the models a name reaches: bundled and converted; `models rm NAME`",
    "report": "one offline HTML page of a predict output (check, path, pairs) or a bench JSON",
}
EXIT_OK, EXIT_PARTIAL, EXIT_USAGE, EXIT_OS_ERROR, EXIT_INTERRUPTED = 0, 1, 2, 3, 130
M_ARENA_MAX = -8  # glibc's mallopt parameter behind the MALLOC_ARENA_MAX environment variable


def chosen_command(argv: Sequence[str]) -> str | None:
    """The subcommand named in ``argv`` (the first word not an option: the top level's options take no value)."""
    word = next((a for a in argv if not a.startswith("-")), None)
    return word if word in COMMANDS else None


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The parser with ``command``'s full arguments (its module imported); the others by name and help only."""
    from geonet_infer import __version__

    parser = argparse.ArgumentParser(
        prog="geonet-infer",
        description="GeoNet (CVPR 2018) monocular depth, optical flow and camera pose on CPU with onnxruntime. "
        "Start with `geonet-infer demo`; run `geonet-infer COMMAND --help` for each command.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="exit codes: 0 all good, 1 some frames failed (see summary.json), 2 bad usage or input, "
        "3 a file could not be read or written (permission, disk full), 130 interrupted",
    )
    parser.add_argument("--version", action="version", version=f"geonet-infer {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, help_line in COMMANDS.items():
        if name == command:
            importlib.import_module(f"geonet_infer.cli.{name}").add_parser(sub)
        else:
            sub.add_parser(name, help=help_line, add_help=False)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser(chosen_command(sys.argv[1:] if argv is None else argv))
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # argparse exits 2 on bad usage and 0 on --help/--version
        return int(exc.code or 0)
    if args.command is None:
        parser.print_help()
        return EXIT_USAGE
    one_malloc_arena()
    return run_reporting_errors(f"geonet-infer {args.command}", lambda: args.run(args))


def one_malloc_arena() -> bool:
    """Every thread of this process allocates from glibc's main arena, as ``MALLOC_ARENA_MAX=1`` would.

    By default glibc gives each thread that allocates an arena of its own (up to 8 per core), and
    each arena keeps the pages its thread freed: predict's reader, cascade and writer threads
    allocate and free frame-sized arrays. Set after the command's imports (their threads keep the
    arenas they already have), before any of predict's threads start. On the 2-core Intel Xeon of docs/performance.md
    ("One malloc arena"), predict's peak RSS 316 -> 275 MiB with all outputs and
    266 -> 232 with --no-vis, no slower (system time 1.0 -> 0.8 s). Called by the CLI only, which owns
    its process (a program using the API keeps its own allocator settings); a user's own
    MALLOC_ARENA_MAX wins. True where it was set (glibc only).
    """
    if os.environ.get("MALLOC_ARENA_MAX") or not _glibc():
        return False
    import ctypes  # here, not at the top: `import geonet_infer.cli` stays as light as it was

    try:
        return bool(ctypes.CDLL(None).mallopt(M_ARENA_MAX, 1))
    except (AttributeError, OSError):  # a libc without mallopt
        return False


def _glibc() -> bool:
    try:
        return os.confstr("CS_GNU_LIBC_VERSION").startswith("glibc")  # type: ignore[union-attr]
    except (AttributeError, ValueError, OSError):  # not a POSIX confstr, or a libc that does not name itself
        return False


def run_reporting_errors(prog: str, run: Callable[[], int]) -> int:
    """``run()``'s exit code, with the errors a user can meet as one line on stderr and the exit codes
    above (also the repository's own tools: ``python -m benchmarks.eval_all``)."""
    try:
        return run()
    except GeoNetError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except BrokenPipeError:  # `geonet-infer info | head`: the reader left, nothing to report
        sys.stderr.close()
        return 0
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except OSError as exc:  # permission, disk full, read-only: one line, not a traceback
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"{prog}: error: {where}{exc.strerror or exc}", file=sys.stderr)
        return EXIT_OS_ERROR

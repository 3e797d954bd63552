"""``geonet-infer``: depth, optical flow and camera pose from video on CPU.

One module per subcommand; each has ``add_parser(subparsers)`` and ``run(args) -> int``.
Exit codes, for every subcommand: 0 all good, 1 some items failed (recorded in the
output), 2 bad usage or input (one line on stderr naming the item), 3 the operating system
refused a read or write (permission, disk full, read-only; one line naming the path),
130 interrupted (Ctrl-C or SIGTERM).
"""

from __future__ import annotations

import argparse
import sys

from geonet_infer import __version__
from geonet_infer.cli import batch, bench, demo, eval, info, predict
from geonet_infer.errors import GeoNetError

SUBCOMMANDS = (predict, batch, demo, info, bench, eval)
EXIT_OK, EXIT_PARTIAL, EXIT_USAGE, EXIT_OS_ERROR, EXIT_INTERRUPTED = 0, 1, 2, 3, 130


def build_parser() -> argparse.ArgumentParser:
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
    for module in SUBCOMMANDS:
        module.add_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # argparse exits 2 on bad usage and 0 on --help/--version
        return int(exc.code or 0)
    if args.command is None:
        parser.print_help()
        return EXIT_USAGE
    try:
        return args.run(args)
    except GeoNetError as exc:
        print(f"geonet-infer {args.command}: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except BrokenPipeError:  # `geonet-infer info | head`: the reader left, nothing to report
        sys.stderr.close()
        return 0
    except KeyboardInterrupt:
        print(f"geonet-infer {args.command}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except OSError as exc:  # permission, disk full, read-only: one line, not a traceback
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"geonet-infer {args.command}: error: {where}{exc.strerror or exc}", file=sys.stderr)
        return EXIT_OS_ERROR

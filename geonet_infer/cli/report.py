"""``geonet-infer report``: one offline HTML page of a predict or batch output folder, or of a bench JSON."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

HELP = """\
One self-contained HTML page (plots with plotly.js embedded, pictures inline: it opens offline,
from a file, anywhere), at most 6 MiB. Needs the [viz] extra (pip install 'geonet-infer[viz]').

OUT, a predict (or batch) output folder: the output check's errors per pair over time, the camera
path from above, the frame / depth / flow of the best and the worst pairs, the stage table, the
intrinsics and their source, and the model's stated limits. Written to OUT/report.html.
BENCH.json, what `geonet-infer bench --json` wrote: each case's latency distribution per engine
and precision. Written beside it (BENCH.html).

examples:
  geonet-infer predict ../shared/realdata/kitti_raw_2011_09_26_sfnd --out out/kitti
  geonet-infer report out/kitti                    # -> out/kitti/report.html
  geonet-infer bench --json bench.json && geonet-infer report bench.json --html bench.html
"""


def add_parser(sub) -> argparse.ArgumentParser:
    parser = sub.add_parser(
        "report", help="one offline HTML page of a predict output or a bench JSON", description=HELP,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )  # fmt: skip
    parser.add_argument(
        "path", type=Path, metavar="OUT|BENCH.json", help="a predict/batch --out folder or a bench --json file"
    )
    parser.add_argument("--html", type=Path, default=None, help="where to write the page (default: see above)")
    parser.set_defaults(run=run)
    return parser


def run(args: argparse.Namespace) -> int:
    from geonet_infer.errors import InputError
    from geonet_infer.output.html import require_plotly, write_page

    require_plotly()
    path: Path = args.path
    if path.is_file() and path.suffix.lower() == ".json":
        from geonet_infer.bench.html import bench_page

        page, target = bench_page(path), args.html or path.with_suffix(".html")
    elif path.is_dir():
        from geonet_infer.output.report import predict_page

        page, target = predict_page(path), args.html or path / "report.html"
    else:
        raise InputError(
            path, "neither a folder nor a .json file", "pass a predict --out folder or a bench --json file"
        )
    if target.exists() and target.is_dir():
        raise InputError(target, "is a folder", "pass --html FILE.html")
    size = write_page(target, page)
    print(f"report: {target} ({size / 2**20:.1f} MiB, {page.plots} plots); open it in a browser", file=sys.stdout)
    return 0

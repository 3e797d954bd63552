"""Distance to the speed targets of issue 9, from two `geonet-infer bench --json` files.

    python benchmarks/targets.py runs/bench/bench_r50.json runs/bench/bench_small_synth.json

Prints the markdown table that docs/performance.md holds (measured / target; < 1 = met).
"""
from __future__ import annotations

import json
import sys


def get(data: dict, task: str, mode: str, precision: str, field: str = "p50_ms", batch: int = 1) -> float:
    rows = [r for r in data["results"] if (r["task"], r["mode"], r["precision"], r["batch"]) == (task, mode, precision, batch)]
    return rows[0][field] if rows else float("nan")


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 2:
        print(__doc__, file=sys.stderr)
        return 2
    r50, small = (json.load(open(p)) for p in argv)
    rows = [("resnet50 int8 depth (graph p50)", get(r50, "depth", "graph", "int8"), 19),
            ("resnet50 int8 flow per pair in a sequence (e2e)", get(r50, "sequence", "e2e", "int8", "per_pair_p50_ms"), 45),
            ("resnet50 int8 pose (graph p50)", get(r50, "pose", "graph", "int8"), 4),
            ("rigid op (graph p50, fp32)", get(r50, "rigid_flow", "graph", "fp32"), 1.5),
            ("small int8 cascade per frame in a sequence (e2e)", get(small, "sequence", "e2e", "int8"), 8)]
    print("| target | measured ms | target ms | distance (measured/target) |\n|---|---|---|---|")
    for name, value, target in rows:
        print(f"| {name} | {value:.1f} | ≤ {target:g} | {value / target:.2f}× |")
    for label, data in (("resnet50", r50), ("small", small)):
        for key, mem in data["environment"].get("memory", {}).items():
            if mem.get("first_in_process", True):
                print(f"| {label} {key} peak RSS / graph files | {mem['peak_rss_mib']:.0f} MiB / "
                      f"{mem['graph_files_mib']:.0f} MiB | ≤ 1.5× | {mem['peak_rss_over_graph_files']:.2f}× |")
    return 0


if __name__ == "__main__":
    sys.exit(main())

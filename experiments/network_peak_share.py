"""How close does each network run to this CPU's int8 GEMM peak? (issue 54, point 5)

Per graph of a model directory and per engine and precision: the graph's convolution MACs
(:func:`target_limits.graph_macs`, from the FP32 graph's shapes), its p50 time from one
``geonet-infer bench --modes graph`` run, the GOP/s that makes (2 ops per MAC) and that rate's
share of the int8 GEMM peak measured in the same run on as many threads (``torch._int_mm``,
:func:`target_limits.gemm_peaks`). The last rows are a sequence's networks per frame (DepthNet
once, PoseNet and ResFlowNet once per pair) on each graph's fastest engine and precision.

    python -m experiments.network_peak_share --threads 2 --json docs/network_peak_share.json
    python -m experiments.network_peak_share --model /tmp/geonet_r50 --threads 2

Needs torch (the ``train`` extra) for the peak; the ``openvino`` extra to time OpenVINO too.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from experiments import target_limits
from experiments.graph_bench import bench_graphs_json
from geonet_infer.models import resolve_model
from geonet_infer.models.manifest import load_manifest

NETWORKS = {"depth": "depthnet", "pose": "posenet", "resflow": "resflownet"}  # bench task -> graph


def bench_graphs(model: str, threads: int, backends: str, iters: int) -> dict:
    """One ``geonet-infer bench --modes graph`` run of the three networks, fp32 and int8: its JSON."""
    return bench_graphs_json(model, ",".join(NETWORKS), "fp32,int8", backends, threads, iters)


def shares(model: str, threads: int, backends: str, iters: int) -> dict:
    model_dir = resolve_model(model)
    manifest = load_manifest(model_dir)
    macs = {
        graph: target_limits.graph_macs(manifest.path(graph, "fp32"), skip_zero_taps=True)
        for graph in NETWORKS.values()
    }
    bench = bench_graphs(model, threads, backends, iters)
    peaks = target_limits.gemm_peaks(threads)
    rows = []
    for row in bench["results"]:
        graph = NETWORKS[row["task"]]
        gops = 2 * macs[graph] / (row["p50_ms"] / 1e3) / 1e9
        rows.append(
            {
                "graph": graph,
                "engine": row["backend"],
                "precision": row["precision"],
                "gmacs": macs[graph] / 1e9,
                "p50_ms": row["p50_ms"],
                "gops": gops,
                "share_of_int8_peak": gops / peaks["int8_gops"],
            }
        )
    best = {graph: min((r for r in rows if r["graph"] == graph), key=lambda r: r["p50_ms"]) for graph in macs}
    frame_ms = sum(best[graph]["p50_ms"] for graph in macs)  # long sequence: each network once per frame
    frame_gops = 2 * sum(macs.values()) / (frame_ms / 1e3) / 1e9
    return {
        "model": str(model_dir),
        "threads": threads,
        "cpu": bench["environment"].get("cpu"),
        "cpu_flags": bench["environment"].get("cpu_flags"),
        "peaks": peaks,
        "rows": rows,
        "per_frame": {
            "best": {graph: f"{r['engine']} {r['precision']}" for graph, r in best.items()},
            "gmacs": sum(macs.values()) / 1e9,
            "ms": frame_ms,
            "ms_at_int8_peak": 2 * sum(macs.values()) / peaks["int8_gops"] / 1e6,
            "gops": frame_gops,
            "share_of_int8_peak": frame_gops / peaks["int8_gops"],
        },
    }


def markdown(result: dict) -> str:
    peaks = result["peaks"]
    lines = [
        f"{result['cpu']} ({' '.join(result['cpu_flags'] or [])}), {result['threads']} threads; "
        f"int8 GEMM peak {peaks['int8_gops']:.0f} GOP/s (`torch._int_mm`), "
        f"fp32 {peaks['fp32_gflops']:.0f} GFLOP/s (`torch.mm`)",
        "",
        "| graph | GMAC | engine, precision | p50 ms | GOP/s | share of the int8 peak |",
        "|---|---|---|---|---|---|",
    ]
    for r in sorted(result["rows"], key=lambda r: (r["graph"], r["p50_ms"])):
        lines.append(
            f"| {r['graph']} | {r['gmacs']:.3f} | {r['engine']} {r['precision']} | {r['p50_ms']:.2f} "
            f"| {r['gops']:.0f} | {r['share_of_int8_peak']:.0%} |"
        )
    f = result["per_frame"]
    best = ", ".join(f"{graph} {how}" for graph, how in f["best"].items())
    lines.append(
        f"| **per frame** (each graph's fastest: {best}) | {f['gmacs']:.3f} | | {f['ms']:.2f} "
        f"(at the peak: {f['ms_at_int8_peak']:.2f}) | {f['gops']:.0f} | **{f['share_of_int8_peak']:.0%}** |"
    )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", default="small_synth", help="bundled model name or model directory")
    parser.add_argument("--threads", type=int, default=2, help="threads per graph call and for the peak GEMM")
    parser.add_argument("--backend", default="onnxruntime,openvino", help="engines to time (bench --backend)")
    parser.add_argument("--iters", type=int, default=30, help="timed calls per graph (bench --iters)")
    parser.add_argument("--json", type=Path, help="write the result here too")
    args = parser.parse_args(argv)
    result = shares(args.model, args.threads, args.backend, args.iters)
    if args.json:
        args.json.write_text(json.dumps(result, indent=1) + "\n")
    print(markdown(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())

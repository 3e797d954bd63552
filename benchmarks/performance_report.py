"""Write docs/performance.md from one measurement run (no figure typed by hand).

    python benchmarks/performance_report.py --bench-small runs/bench/bench_small_synth.json \
        --bench-r50 runs/bench/bench_r50.json --peers runs/bench/peers_small.md runs/bench/peers_resnet50.md \
        --out docs/performance.md

The inputs come from the commands in the "How the numbers were made" section it writes.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

# written by batch_throughput.py, speed_targets.py, peer_models.py, output_size (issue 43), and by hand (issue 45)
KEPT_SECTIONS = (
    "## Batch throughput",
    "## Speed targets",
    "## Versus the models users pick instead",
    "## AVX2-only CPUs",
    "## Output size and writing time",
)
TASK_LABELS = {
    "depth": "depth",
    "pose": "pose",
    "rigid_flow": "rigid_flow",
    "resflow": "resflow",
    "flow": "flow (one pair)",
    "sequence": "sequence, per frame",
}
COMMANDS = """\
```bash
mkdir -p runs/bench
# 1. the runtime on the bundled model (int8 first: its memory figures are the clean ones)
geonet-infer bench --precision int8,fp32 --backend onnxruntime,openvino,auto \\
    --json runs/bench/bench_small_synth.json
# 2. the resnet50 timing export, then the runtime on it
python -m export --arch resnet50 --random-init --out /tmp/geonet_r50 --precision fp32,int8 \\
    --calib-data ../shared/realdata/kitti_raw_2011_09_26_sfnd/image_02/data --calib-frames 8
geonet-infer bench --model /tmp/geonet_r50 --precision int8,fp32 --backend onnxruntime,openvino,auto \\
    --json runs/bench/bench_r50.json
# 3. the peers, one interleaved run per arch (pip install -e '.[openvino]' first)
python benchmarks/peers.py --arch small --random-init --out runs/bench/peers_small
python benchmarks/peers.py --arch resnet50 --random-init --onnx-dir /tmp/geonet_r50 --out runs/bench/peers_resnet50
# 4. memory, one fresh process per configuration
python benchmarks/memory.py --model /tmp/geonet_r50 --model small_synth --json runs/bench/memory.json
# 5. this page
python benchmarks/performance_report.py --bench-small runs/bench/bench_small_synth.json \\
    --bench-r50 runs/bench/bench_r50.json --peers runs/bench/peers_small.md runs/bench/peers_resnet50.md \\
    --memory runs/bench/memory.json --out docs/performance.md
```"""


BACKEND_LABELS = {"onnxruntime": "ORT", "openvino": "OpenVINO", "auto": "auto"}


LEVERS = """\
## Levers tried

The runs behind them are in issue 9's notes.

- *OpenVINO for the same ONNX files* (`--backend openvino`, `auto`): adopted as an option; its
  VNNI int8 kernels are where the large INT8 gains above come from. onnxruntime's INT8 graphs
  barely beat its fp32 ones on these nets.
- *`auto`*: per graph, the faster engine at load. It keeps onnxruntime for the rigid-flow op
  (GridSample is slower in OpenVINO), OpenVINO for the ConvNets.
- *onnxruntime's CPU memory arena*: one arena per session kept each session's largest buffers
  (a cascade has four). Issue 30 measured, in fresh processes (peak added by a predictor after a
  4-frame 1242×375 sequence, small INT8 / resnet50 INT8), and `predict` on the KITTI drive
  interleaved: one arena per session 178 / 326 MiB; no arena 110 / 232 MiB but `predict` 6–10 %
  slower (every run's buffers are fresh pages: system time 0.9 → 1.4 s); one arena shared by every
  session of the process (onnxruntime's environment allocator) 112 / 259 MiB at the speed of
  per-session arenas. Shared since then.
  *Weight prepacking off*: about 3× slower; kept on.
- *A gather-based bilinear warp instead of GridSample in the rigid op*: not faster in
  onnxruntime; not adopted. The rigid op is the largest single cost of the small cascade and
  the furthest from its target.
- *Post-processing*: the residual flow at the input size is now flow − rigid flow (resizing is
  linear), one bilinear resize less per frame."""


def isa_of(env: dict) -> str:
    """The ISA line of a bench run (``geonet-infer info``'s), from its record or its cpu_flags (older runs)."""
    from geonet_infer.engines.cpu import ISA_FLAGS, int8_kernel, isa_line

    if env.get("isa"):
        return env["isa"]["line"]
    flags = set(env.get("cpu_flags", []))
    isa: dict[str, bool | None] = {f: f in flags for f in ISA_FLAGS}
    return isa_line({"isa": isa, "int8_kernel": int8_kernel(isa)})


def row(data: dict, task: str, mode: str, precision: str, batch: int = 1, backend: str = "onnxruntime") -> dict | None:
    for r in data["results"]:
        if (r["task"], r["mode"], r["precision"], r["batch"], r["backend"]) == (task, mode, precision, batch, backend):
            return r
    return None


def backends(data: dict) -> list[str]:
    seen = {r["backend"] for r in data["results"]}
    return [b for b in BACKEND_LABELS if b in seen]


def fmt(value, digits: int = 1) -> str:
    return "—" if value is None else f"{value:.{digits}f}"


def bench_table(data: dict) -> list[str]:
    """p50 (p90) ms per engine and precision, and the best engine's speed-up over ORT fp32."""
    cols = [(b, p) for b in backends(data) for p in ("fp32", "int8")]
    head = " | ".join(f"{BACKEND_LABELS[b]} {p}" for b, p in cols)
    lines = [f"| task | mode | {head} | fastest vs ORT fp32 |", "|---|---|" + "---|" * (len(cols) + 1)]
    for task, label in TASK_LABELS.items():
        for mode in ("graph", "e2e"):
            cells = {c: row(data, task, mode, c[1], backend=c[0]) for c in cols}
            if not any(cells.values()):
                continue
            text = [f"{r['p50_ms']:.1f} ({r['p90_ms']:.1f})" if r else "—" for r in cells.values()]
            base = cells.get(("onnxruntime", "fp32"))
            best = min((r["p50_ms"], c) for c, r in cells.items() if r)
            speedup = f"{base['p50_ms'] / best[0]:.2f}× ({BACKEND_LABELS[best[1][0]]} {best[1][1]})" if base else "—"
            lines.append(f"| {label} | {mode} | {' | '.join(text)} | {speedup} |")
    return lines


def memory_rows(label: str, data: dict) -> list[str]:
    out = []
    for key, m in data["environment"].get("memory", {}).items():
        note = "" if m.get("first_in_process", True) else " (second predictor of the process: not clean)"
        out.append(
            f"| {label} | {key}{note} | {m['graph_files_mib']:.1f} | {m['rss_after_load_mib']:.0f} | "
            f"{m['peak_rss_mib']:.0f} | {m['peak_rss_over_graph_files']:.2f} |"
        )
    return out


def memory_table(rows: list[dict]) -> list[str]:
    """benchmarks/memory.py: one fresh process per configuration."""
    out = [
        "| model | precision | engine | graph files MiB | RSS after load − before, MiB | peak − before, MiB "
        "(load + a 4-frame sequence) | (peak − before) / graph files |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        out.append(
            f"| {Path(r['model']).name} | {r['precision']} | {BACKEND_LABELS[r['backend']]} | "
            f"{r['graph_files_mib']:.1f} | {r['rss_after_load_mib'] - r['rss_before_load_mib']:.0f} | "
            f"{r['predictor_mib']:.0f} | {r['predictor_over_graph_files']:.2f}× |"
        )
    return out


def report(small: dict, r50: dict, peers: list[str], memory: list[dict] | None = None) -> str:
    env = small["environment"]
    so = env.get("session_options", {})
    L = [
        "# Performance on CPU",
        "",
        "Generated by `benchmarks/performance_report.py` from one run of the commands at the end of "
        "this page; no figure is typed by hand. Absolute times vary between runs and machines: "
        "compare ratios measured in the same run.",
        "",
        "What the paper reports (one TitanXP GPU, per example): depth 15 ms, optical flow 45 ms, camera pose 4 ms.",
        "",
        "## Machine",
        "",
        "| | |",
        "|---|---|",
        f"| CPU | {env['cpu']}; flags {' '.join(env.get('cpu_flags', []))} |",
        f"| ISA (INT8 arithmetic) | {isa_of(env)}; every table of this page, unless its section names another CPU |",
        f"| usable CPUs / threads per graph | {env['usable_cpus']} / {env.get('threads')} |",
        f"| versions | Python {env['python']}, onnxruntime {env['onnxruntime']}, "
        f"OpenVINO {env.get('openvino') or r50['environment'].get('openvino')}, numpy {env['numpy']}, "
        f"OpenCV {env['opencv']} |",
        f"| session options | intra_op {so.get('intra_op_num_threads')}, inter_op {so.get('inter_op_num_threads')}, "
        f"{so.get('execution_mode')}, {so.get('graph_optimization_level')}, spinning "
        f"{so.get('session.intra_op.allow_spinning')} |",
        f"| load average (bundled run) start → end | {env.get('load_average_start')} → {env.get('load_average_end')} |",
        f"| git commit | `{env.get('git_commit', '')[:12]}` |",
        "",
    ]
    if env.get("busy_warning") or r50["environment"].get("busy_warning"):
        L += [
            "**The machine was not idle during these runs** (see the load averages): other jobs shared "
            "the 2 cores, so absolute times are pessimistic and noisy; ratios within one run hold better.",
            "",
        ]
    L += (
        [
            "## Method",
            "",
            "- `geonet-infer bench` (`geonet_infer/engines/timing.py`): warm-up, then all cases of one precision "
            "and batch block-interleaved (rotating order, quiet-wait and ≥ 50 ms re-warm before each "
            "block), `perf_counter_ns`, GC off; p50/p90 of the wall time of one synchronous call.",
            "- Engines (`--backend`): *ORT* = onnxruntime, *OpenVINO* = the same ONNX files on OpenVINO's "
            "CPU plugin (f32 inference precision forced), *auto* = the faster of the two per graph, "
            "picked at load by timing both (the choices are in the JSON, `environment.engines`).",
            "- Cells: p50 (p90) in ms. *graph* = the engines only, on inputs prepared at 128×416; "
            "*e2e* = from uint8 "
            "frames at 1242×375 through `Predictor` (resize, normalise, intrinsics, output resizing). "
            "*sequence* rows are per frame of `iter_sequence` (depth computed once per frame).",
            "- The resnet50 export and the peer runs use random weights (latency only). INT8 accuracy "
            "of the trained bundled model: [models.md](models.md).",
            "- `benchmarks/peers.py`: the same weights through torch eager, torch.compile, ORT fp32/int8 "
            "and OpenVINO f32 (inference precision forced to f32) / int8, one interleaved run per arch.",
            "",
            "## `geonet-infer bench`: the runtime",
            "",
            "### Bundled model (`small_synth`, 128×416), batch 1, ms",
            "",
        ]
        + bench_table(small)
        + ["", "### resnet50 timing export (128×416, random weights), batch 1, ms", ""]
        + bench_table(r50)
    )
    for label, data in (("small_synth", small), ("resnet50 export", r50)):
        for backend in backends(data):
            ints = [row(data, t, "e2e", "int8", backend=backend) for t in ("depth", "pose")]
            seq = row(data, "sequence", "e2e", "int8", backend=backend)
            if all(ints) and seq:
                L += [
                    "",
                    f"Paper-style line, {label}, {BACKEND_LABELS[backend]} (batch 1, e2e p50, int8): depth "
                    f"{ints[0]['p50_ms']:.1f} ms, flow per pair in a sequence "
                    f"{seq.get('per_pair_p50_ms', float('nan')):.1f} ms, pose {ints[1]['p50_ms']:.1f} ms "
                    "(paper, TitanXP GPU: 15 / 45 / 4 ms).",
                ]
    L += (
        [
            "",
            "### Memory",
            "",
            "| model | engine/precision | graph files MiB | RSS after load MiB | peak RSS MiB | peak / files |",
            "|---|---|---|---|---|---|",
        ]
        + memory_rows("small_synth", small)
        + memory_rows("resnet50 export", r50)
    )
    L += [
        "",
        "The process itself (Python, numpy, OpenCV, onnxruntime) takes about "
        f"{env.get('rss_at_start_mib', 0):.0f} MiB before any model is loaded, which dominates for the small model.",
        "",
    ]
    if memory:
        L += [
            "### Memory, one fresh process per configuration (`benchmarks/memory.py`)",
            "",
            "What loading a predictor and running it adds to a process, measured alone (the figures "
            "above are of one process that loads every configuration in turn). *auto* holds both "
            "engines while it times them at load, hence its higher peak.",
            "",
            *memory_table(memory),
            "",
        ]
    L += [
        "## `benchmarks/peers.py`: the same weights in every engine",
        "",
    ]
    for text in peers:
        L += [
            line.replace("# GeoNet peers:", "### Peers:", 1)
            if line.startswith("# ")
            else ("#" + line if line.startswith("## ") else line)
            for line in text.strip().splitlines()
        ] + [""]
    L += ["", LEVERS]
    L += ["", "## How the numbers were made", "", COMMANDS, ""]
    return "\n".join(L)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--bench-small", type=Path, required=True)
    p.add_argument("--bench-r50", type=Path, required=True)
    p.add_argument("--peers", type=Path, nargs="+", required=True, help="peers_<arch>.md files")
    p.add_argument("--memory", type=Path, default=None, help="benchmarks/memory.py --json output")
    p.add_argument("--out", type=Path, required=True)
    args = p.parse_args(argv)
    for path in [args.bench_small, args.bench_r50, *args.peers, *([args.memory] if args.memory else [])]:
        if not path.is_file():
            print(f"performance_report: error: {path}: not found (run the commands in its docstring)", file=sys.stderr)
            return 2
    text = report(
        json.loads(args.bench_small.read_text()),
        json.loads(args.bench_r50.read_text()),
        [p.read_text() for p in args.peers],
        json.loads(args.memory.read_text()) if args.memory else None,
    )
    # Sections written by other benchmarks (batch_throughput.py) are kept as they are.
    old = args.out.read_text() if args.out.is_file() else ""
    for heading in KEPT_SECTIONS:
        if heading in old:
            text = text.rstrip() + "\n\n" + old[old.index(heading) :].rstrip() + "\n"
            break
    args.out.write_text(text)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

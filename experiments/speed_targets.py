"""Issue 30's speed targets, this checkout against an older revision, from one interleaved run.

Each round runs, for both trees in rotating order, each as a fresh process:
``geonet-infer bench`` (sequence and rigid-flow op, fp32 and int8, every engine installed),
the memory child of ``benchmarks/memory.py`` (small model, int8, onnxruntime, a 4-frame
sequence) and ``geonet-infer predict`` on the 78-frame KITTI drive with all default outputs
and with ``--no-vis`` (``benchmarks/predict_fps.py``). This checkout is also benched with
``--rigid-op numpy``. Every figure is the median over rounds; each target's distance is
value / target (<= 1 met).

    python experiments/speed_targets.py --against 3f60b25 --rounds 2 --json runs/bench/targets.json \\
        --page docs/performance.md --resnet50 /tmp/geonet_r50

``--page`` rewrites the page's "## Speed targets" section only (the rest of the page is
``benchmarks/performance_report.py``'s, which keeps this section). Target 4's accuracy half is read
from each tree's bundled manifest (the INT8 accuracy delta export measured on the held-out synthetic
sequences). 7 (the paper's resnet50 networks) is measured when ``--resnet50 DIR`` names a resnet50
export (``python -m export --arch resnet50 ...``): ``geonet-infer bench`` on it, INT8, depth and
sequence, every engine, for both trees. Then, for this checkout only, what bounds each target left
unmet (:mod:`target_limits`: the parts of the work each target covers timed alone, the networks'
convolution MACs against this machine's int8 GEMM peak, onnxruntime's int8 profile, and the flow
accuracy with each network kept in fp32), as a table under the targets.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

# its siblings (experiments/) and the re-run tools it times with (benchmarks/) import by name, as a script or -m
sys.path[:0] = [str(Path(__file__).resolve().parent), str(Path(__file__).resolve().parents[1] / "benchmarks")]
import target_limits  # noqa: E402
from identical_outputs import REPO, revision_tree  # noqa: E402
from memory import CHILD as MEMORY_CHILD  # noqa: E402
from predict_fps import OUTPUTS, one_run  # noqa: E402
from speed_milestones import SPEED_TARGETS, speed_target_values, target_distance  # noqa: E402
from target_limits import median_ms  # noqa: E402

from geonet_infer.models import resolve_model  # noqa: E402

SECTION = "## Speed targets"


SMALL_BENCH = ["--tasks", "rigid_flow,sequence", "--precision", "fp32,int8"]
RESNET50_BENCH = ["--tasks", "depth,sequence", "--precision", "int8", "--iters", "10"]


def run_bench(tree: Path, json_out: Path, options: list[str]) -> dict:
    env = {**os.environ, "PYTHONPATH": str(tree)}
    cmd = [sys.executable, "-m", "geonet_infer.cli", "bench", *options]
    cmd += ["--backend", ",".join(backends()), "--json", str(json_out), "--quiet"]
    done = subprocess.run(cmd, cwd=tree, env=env, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"{tree}: bench exited {done.returncode}:\n{done.stderr}")
    return json.loads(json_out.read_text())


def run_memory(tree: Path) -> dict:
    env = {**os.environ, "PYTHONPATH": str(tree)}
    cmd = [sys.executable, "-c", MEMORY_CHILD, "small_synth", "int8", "onnxruntime"]
    done = subprocess.run(cmd, cwd=tree, env=env, capture_output=True, text=True, check=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def backends() -> list[str]:
    from geonet_infer.engines import ENGINES

    return [name for name, cls in ENGINES.items() if cls.available()]


def int8_flow_delta_pct(tree: Path) -> float | None:
    """The bundled model's INT8 flow EPE-noc delta in % of FP32, as export recorded it in the manifest."""
    manifest = json.loads((tree / "geonet_infer" / "models" / "small_synth" / "manifest.json").read_text())
    epe = ((manifest.get("quantization") or {}).get("accuracy_delta") or {}).get("flow_epe_noc")
    return 100 * epe["delta"] / epe["fp32"] if epe else None


def figures(
    bench: dict,
    rigid_numpy: dict | None,
    memory: dict,
    predicts: dict[str, dict],
    int8_flow_delta: float | None,
    resnet50: dict | None = None,
) -> dict:
    """One tree's value for each target (ms, ratio, frames/s or MiB); 1-4 as ``geonet-infer bench --json``
    reports them (:func:`speed_milestones.speed_target_values`), the rigid op in its fastest form;
    and predict's CPU ms per frame (``predicts``: :func:`predict_fps.one_run` per output setting)."""
    measured = speed_target_values(bench["results"], "small")
    r50 = speed_target_values(resnet50["results"], "resnet50") if resnet50 else {}
    if rigid_numpy is not None:
        numpy_op = speed_target_values(rigid_numpy["results"], "small").get("3_rigid_op_ms")
        forms = [v for v in (measured.get("3_rigid_op_ms"), numpy_op) if v is not None]
        measured["3_rigid_op_ms"] = min(forms) if forms else None
    rows = {
        (r["task"], r["mode"], r["precision"], r["backend"]): r["p50_ms"] for r in bench["results"] if r["batch"] == 1
    }
    networks = {key: ms for key, ms in rows.items() if key[:2] == ("sequence", "graph")}
    return {
        **{key: measured.get(key) for key in BENCH_KEYS},
        "4b_int8_flow_epe_delta_pct": int8_flow_delta,
        "5a_predict_fps": predicts["all outputs"]["frames_per_s"],
        "5b_predict_no_vis_fps": predicts["--no-vis"]["frames_per_s"],
        "6_memory_small_int8_mib": memory["predictor_mib"],
        **{key: r50.get(key) for key in R50_KEYS},
        "predict_cpu_ms_per_frame": {outputs: run["cpu_ms_per_frame"] for outputs, run in predicts.items()},
        # what bounds the targets: the sequence's graphs alone, and the memory's parts
        "networks_best_ms": min(networks.values(), default=None),
        "networks_onnxruntime_ms": min((v for k, v in networks.items() if k[3] == "onnxruntime"), default=None),
        "rigid_graph_onnxruntime_ms": rows.get(("rigid_flow", "graph", "fp32", "onnxruntime")),
        "memory_load_mib": memory["rss_after_load_mib"] - memory["rss_before_load_mib"],
        "memory_inputs_mib": memory.get("inputs_mib"),
        "memory_results_mib": memory.get("results_mib"),
    }


LIMIT_KEYS = (
    "networks_best_ms",
    "networks_onnxruntime_ms",
    "rigid_graph_onnxruntime_ms",
    "memory_load_mib",
    "memory_inputs_mib",
    "memory_results_mib",
)


BENCH_KEYS = ("1a_best_engine_ms", "1b_onnxruntime_ms", "2_pre_post_ms", "3_rigid_op_ms", "4_int8_speedup_onnxruntime")
R50_KEYS = ("7a_resnet50_int8_depth_ms", "7b_resnet50_int8_flow_pair_ms")
TARGETS = {  # key: (what, target, "max" = at most / "min" = at least); 1-4 from speed_milestones.py
    **{key: SPEED_TARGETS[key] for key in BENCH_KEYS},
    "4b_int8_flow_epe_delta_pct": ("INT8 flow EPE-noc vs FP32, synthetic held-out, from the manifest (+%)", 5, "max"),
    "5a_predict_fps": ("predict, 78-frame KITTI drive, all outputs (frames/s)", 25, "min"),
    "5b_predict_no_vis_fps": ("predict with --no-vis (frames/s)", 40, "min"),
    "6_memory_small_int8_mib": ("small INT8 predictor after a 4-frame sequence, added (MiB)", 80, "max"),
    **{key: SPEED_TARGETS[key] for key in R50_KEYS},
}


def bounds(predict_out: Path, frame: Path) -> dict[str, float]:
    """CPU ms of the per-frame work no network change removes, measured on one KITTI frame and its outputs."""
    import cv2
    import numpy as np

    from geonet_infer.io.flow import encode_flow_kitti, read_flow_kitti
    from geonet_infer.io.png import encode_png
    from geonet_infer.output.viz import depth_to_color, flow_to_color

    name = sorted((predict_out / "flow").glob("*.png"))[0].stem
    flow, _ = read_flow_kitti(predict_out / "flow" / f"{name}.png")
    depth = np.load(predict_out / "depth" / f"{name}.npy")
    flow_rgb16 = encode_flow_kitti(flow)
    flow_bgr16 = np.ascontiguousarray(flow_rgb16[..., ::-1])
    depth_rgb, flow_rgb = depth_to_color(depth), flow_to_color(flow)
    frame_bytes = np.frombuffer(frame.read_bytes(), np.uint8)
    rgb = cv2.imdecode(frame_bytes, cv2.IMREAD_COLOR)
    return {
        "flow_png_opencv_ms": median_ms(lambda: cv2.imencode(".png", flow_bgr16)),
        "flow_png_opencv_stored_ms": median_ms(
            lambda: cv2.imencode(".png", flow_bgr16, [cv2.IMWRITE_PNG_COMPRESSION, 0])
        ),
        "flow_png_ours_ms": median_ms(lambda: encode_png(flow_rgb16)),
        "colour_pngs_opencv_ms": median_ms(lambda: (cv2.imencode(".png", depth_rgb), cv2.imencode(".png", flow_rgb))),
        "colour_pngs_ours_ms": median_ms(lambda: (encode_png(depth_rgb), encode_png(flow_rgb))),
        "colour_maps_ms": median_ms(lambda: (depth_to_color(depth), flow_to_color(flow))),
        "depth_npy_ms": median_ms(lambda: np.save(predict_out / "bounds_depth.npy", depth)),
        "input_png_decode_ms": median_ms(lambda: cv2.imdecode(frame_bytes, cv2.IMREAD_COLOR)),
        "resize_inter_area_ms": median_ms(lambda: cv2.resize(rgb, (416, 128), interpolation=cv2.INTER_AREA)),
    }


def limits(frame: Path, resnet50: Path | None) -> dict:
    """This checkout's measured limits (:mod:`target_limits`): GEMM peaks, the networks' MACs, the parts of
    pre/post-processing and of the rigid op, onnxruntime's int8 profile and the int8 flow sensitivity."""
    small = resolve_model(target_limits.SMALL)
    out = {
        "gemm_peaks": target_limits.gemm_peaks(os.cpu_count() or 1),
        "small_gmacs_per_frame": target_limits.sequence_macs_per_frame(small) / 1e9,
        "pre_post_ms": target_limits.pre_post_ms(frame),
        "rigid_op_parts_ms": target_limits.rigid_op_parts_ms(),
        "onnxruntime_int8": target_limits.onnxruntime_int8_profile(small),
        "int8_flow_sensitivity": target_limits.int8_flow_sensitivity(REPO),
    }
    if resnet50 is not None:
        out["resnet50_depth_gmacs"] = target_limits.graph_macs(resnet50 / "depthnet.onnx") / 1e9
        out["resnet50_gmacs_per_frame"] = target_limits.sequence_macs_per_frame(resnet50) / 1e9
    return out


BOUND_LABELS = {
    "flow_png_opencv_ms": "KITTI 16-bit flow PNG, OpenCV's encoder (zlib level 1; what `before` wrote)",
    "flow_png_opencv_stored_ms": "the same PNG stored without compression (OpenCV's PNG path itself)",
    "flow_png_ours_ms": "the same PNG, geonet_infer.io.png (Sub filter, ISA-L deflate)",
    "colour_pngs_opencv_ms": "depth colour map + flow colour wheel PNGs, OpenCV's encoder",
    "colour_pngs_ours_ms": "the same two PNGs, geonet_infer.io.png",
    "colour_maps_ms": "depth colour map + flow colour wheel (numpy)",
    "depth_npy_ms": "depth .npy (float32, to disk)",
    "input_png_decode_ms": "the input frame, a KITTI PNG, decoded by OpenCV",
    "resize_inter_area_ms": "1242x375 uint8 frame to 416x128, cv2.INTER_AREA (the trained resize)",
}
# What one frame of `predict` with every default output costs outside the networks, in this tree.
OUTSIDE_NETWORKS = ("flow_png_ours_ms", "colour_pngs_ours_ms", "colour_maps_ms", "depth_npy_ms", "input_png_decode_ms")


def distance(key: str, value: float | None) -> str:
    if value is None:
        return "—"
    _, goal, sense = TARGETS[key]
    ratio = target_distance(value, goal, sense)
    return f"{ratio:.2f}" + (" (met)" if ratio <= 1 else "")


def section(result: dict) -> str:
    before, after = result["before"], result["after"]
    lines = [
        SECTION,
        "",
        f"Generated by `experiments/speed_targets.py` (issue 30): before = `{result['against']}`, after = "
        f"`{result['commit']}`, median of {result['rounds']} interleaved rounds, {result['cpus']} CPUs, engines "
        f"{', '.join(result['engines'])}; target 7 on "
        + (
            f"the resnet50 export `{result['resnet50']}`"
            if result.get("resnet50")
            else "no resnet50 export (not measured)"
        )
        + ". Distance = value / target for an upper bound, target / value for a lower one: 1 or less is met.",
        "",
        "| target | goal | before | after | after / before | distance after |",
        "|---|---|---|---|---|---|",
    ]
    for key, (what, target, sense) in TARGETS.items():
        b, a = before.get(key), after.get(key)
        ratio = f"{a / b:.2f}" if a is not None and b else "—"
        goal = f"{'≤' if sense == 'max' else '≥'} {target:g}"
        fmt = (
            (lambda v: "—" if v is None else f"{v:.1f}")
            if "speedup" not in key
            else (lambda v: "—" if v is None else f"{v:.2f}")
        )
        lines.append(f"| {what} | {goal} | {fmt(b)} | {fmt(a)} | {ratio} | {distance(key, a)} |")
    lines += [
        "",
        "What bounds the unmet ones, measured in the same run on one KITTI frame (single-thread CPU ms):",
        "",
        "| per-frame work | ms |",
        "|---|---|",
    ]
    lines += [f"| {BOUND_LABELS[k]} | {v:.1f} |" for k, v in result["bounds_ms"].items()]
    peaks = result["limits"]["gemm_peaks"]
    lines += [
        "",
        "What bounds each unmet target, measured in the same run (this checkout; GEMM peaks of this machine: "
        f"int8 {peaks['int8_gops']:.0f} GOP/s with `torch._int_mm`, fp32 {peaks['fp32_gflops']:.0f} GFLOP/s with "
        f"`torch.mm`, n = 2048, {result['cpus']} threads; convolution MACs from the fp32 graphs' shapes):",
        "",
        "| target | what bounds it |",
        "|---|---|",
        *(f"| {target} | {text} |" for target, text in limit_rows(result)),
    ]
    lines += ["", NOT_ADOPTED]
    outside = sum(result["bounds_ms"][k] for k in OUTSIDE_NETWORKS)
    cpu = result["after_cpu_ms_per_frame"]
    lines += [
        "",
        f"Outside the networks, one frame with every default output costs about {outside:.0f} ms of CPU here "
        f"(decoding the input, colour maps, encoding and writing). Whole `predict` processes, after (user + system "
        f"CPU, model load included, median): {cpu['all outputs']:.0f} CPU-ms per frame with all outputs, "
        f"{cpu['--no-vis']:.0f} with `--no-vis`; {result['cpus']} cores hold at most "
        f"{1e3 * result['cpus'] / cpu['all outputs']:.1f} and {1e3 * result['cpus'] / cpu['--no-vis']:.1f} frames/s "
        f"at that cost, against the targets' 25 and 40 ({result['cpus']} × 1000 / 25 = {result['cpus'] * 40} "
        "core-ms per frame).",
        "",
    ]
    return "\n".join(lines)


# Levers tried for these targets and left out, each measured in its own interleaved run (not this one).
NOT_ADOPTED = """\
Tried and left out (separate interleaved runs, in issue 30's notes):
- decoding the input frames on a thread ahead of the networks: `predict` 18.3 -> 17.4 frames/s,
  107-108 CPU-ms per frame either way (the two cores are already busy);
- onnxruntime's arena growing by the size asked instead of doubling: target 6 111 -> 122 MiB;
- one frame per DepthNet batch in `predict_sequence` instead of four: target 6 111 -> 93 MiB, but the
  FP32 sequence 32.0 -> 37.6 ms per frame."""


def limit_rows(result: dict) -> list[tuple[str, str]]:
    """(target, what bounds it: measured) for every target the run left unmet."""
    after, lim = result["after"], result["limits"]
    peaks = lim["gemm_peaks"]
    int8_peak, fp32_peak = peaks["int8_gops"], peaks["fp32_gflops"]
    unmet = {
        key
        for key, (_, goal, sense) in TARGETS.items()
        if after.get(key) is not None and target_distance(after[key], goal, sense) > 1
    }
    rows = []

    def at_peak(gmacs: float, ms: float | None, key: str) -> str:
        floor = 2 * gmacs / int8_peak * 1e3
        text = f"{2 * gmacs:.2f} GOP of convolutions: {floor:.1f} ms at the int8 GEMM peak"
        if floor > TARGETS[key][1]:
            text += f", more than the {TARGETS[key][1]:g} ms goal (out of reach on this machine)"
        if ms is not None:
            achieved = 2 * gmacs / ms * 1e3
            text += f"; measured {ms:.1f} ms = {achieved:.0f} GOP/s, {achieved / int8_peak:.0%} of the peak"
        return text

    small = lim["small_gmacs_per_frame"]
    if "1a_best_engine_ms" in unmet:
        rows.append(
            (
                "1a",
                f"the networks alone, best engine: {after['networks_best_ms']:.1f} ms per frame; "
                + at_peak(small, after["networks_best_ms"], "1a_best_engine_ms"),
            )
        )
    if "1b_onnxruntime_ms" in unmet:
        ms = after["networks_onnxruntime_ms"]
        rows.append(
            (
                "1b",
                f"the networks alone on onnxruntime: {ms:.1f} ms per frame "
                f"({2 * small / ms * 1e3:.0f} GOP/s; fp32 GEMM peak {fp32_peak:.0f} GFLOP/s)",
            )
        )
    if "2_pre_post_ms" in unmet:
        parts = lim["pre_post_ms"]
        rows.append(
            (
                "2",
                f"input to the network (resize 1242x375 -> 416x128, normalise) {parts['to_network_ms']:.1f} ms, "
                f"depth back to 1242x375 {parts['depth_to_input_ms']:.1f} ms, flow back "
                f"{parts['flow_to_input_ms']:.1f} ms (one thread each)",
            )
        )
    if "3_rigid_op_ms" in unmet:
        parts = lim["rigid_op_parts_ms"]
        rows.append(
            (
                "3",
                f"numpy + OpenCV form at 128x416, one thread: rigid flow {parts['rigid_flow_ms']:.1f} ms, "
                f"bilinear warp {parts['warp_ms']:.1f}, SSIM + L1 error map {parts['error_map_ms']:.1f}, "
                f"whole op {parts['whole_op_ms']:.1f}; the graph on onnxruntime "
                f"{after['rigid_graph_onnxruntime_ms']:.1f} ms",
            )
        )
    if "4_int8_speedup_onnxruntime" in unmet:
        ort = lim["onnxruntime_int8"]
        graphs = ", ".join(f"{g} {v['fp32']:.1f} -> {v['int8']:.1f}" for g, v in ort["graphs_ms"].items())
        total = ort["int8_op_total_ms"]
        top = ", ".join(f"{op} {ms / total:.0%}" for op, ms in list(ort["int8_op_ms"].items())[:4])
        rows.append(
            (
                "4",
                f"onnxruntime, one thread, fp32 -> int8 ms per graph: {graphs}; onnxruntime's "
                f"profile of the int8 graphs: {top} of their kernel time",
            )
        )
    sens = lim.get("int8_flow_sensitivity")
    if "4b_int8_flow_epe_delta_pct" in unmet and sens:
        epe = sens["fp32_kept"]
        fp32 = epe["depthnet+posenet+resflownet"]
        kept = ", ".join(
            f"{'nothing' if k == 'none' else k} fp32 {100 * (v - fp32) / fp32:+.1f} %"
            for k, v in epe.items()
            if k != "depthnet+posenet+resflownet"
        )
        rows.append(
            (
                "4b",
                f"flow EPE-noc vs all-fp32 on the held-out synthetic pairs ({sens['pairs']}), int8 "
                f"cascade with some networks kept in fp32: {kept}",
            )
        )
    cpu = result["after_cpu_ms_per_frame"]
    if unmet & {"5a_predict_fps", "5b_predict_no_vis_fps"}:
        rows.append(
            (
                "5",
                f"CPU per frame of whole `predict` processes: {cpu['all outputs']:.0f} ms all outputs, "
                f"{cpu['--no-vis']:.0f} with --no-vis, against the {result['cpus'] * 40} and "
                f"{result['cpus'] * 25} core-ms the targets leave; the networks alone take "
                f"{after['networks_onnxruntime_ms']:.0f} ms of wall on {result['cpus']} threads",
            )
        )
    if "6_memory_small_int8_mib" in unmet:
        load, inputs, results = (after[k] for k in ("memory_load_mib", "memory_inputs_mib", "memory_results_mib"))
        rest = after["6_memory_small_int8_mib"] - load - inputs - results
        rows.append(
            (
                "6",
                f"loading the sessions {load:.0f} MiB, the 4 input frames {inputs:.0f}, the 4 results "
                f"(depth and flow at 1242x375) {results:.0f}, the rest of the peak {rest:.0f} (onnxruntime's "
                "buffers and the pre/post-processing's temporaries while a frame runs)",
            )
        )
    if "7a_resnet50_int8_depth_ms" in unmet and "resnet50_depth_gmacs" in lim:
        rows.append(
            (
                "7a",
                "resnet50 DepthNet, "
                + at_peak(lim["resnet50_depth_gmacs"], after["7a_resnet50_int8_depth_ms"], "7a_resnet50_int8_depth_ms"),
            )
        )
    if "7b_resnet50_int8_flow_pair_ms" in unmet and "resnet50_gmacs_per_frame" in lim:
        rows.append(
            (
                "7b",
                "resnet50 cascade per frame, "
                + at_peak(lim["resnet50_gmacs_per_frame"], None, "7b_resnet50_int8_flow_pair_ms")
                + f"; measured {after['7b_resnet50_int8_flow_pair_ms']:.1f} ms e2e",
            )
        )
    return rows


def replace_section(page: Path, text: str) -> None:
    old = page.read_text() if page.exists() else ""
    start = old.find(SECTION + "\n")
    if start < 0:
        page.write_text(old.rstrip("\n") + "\n\n" + text)
        return
    end = old.find("\n## ", start + len(SECTION))
    page.write_text(old[:start] + text + ("" if end < 0 else old[end + 1 :]))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--against", required=True, help="git revision for 'before'")
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--json", type=Path, help="every run and the summary")
    parser.add_argument("--page", type=Path, help="rewrite this page's speed-targets section")
    parser.add_argument("--resnet50", type=Path, help="a resnet50 export: also measure target 7 on it")
    args = parser.parse_args(argv)
    runs: dict[str, list] = {"before": [], "after": []}
    with tempfile.TemporaryDirectory(prefix="geonet_targets_") as tmp, revision_tree(args.against, Path(tmp)) as old:
        trees = [("before", old), ("after", REPO)]
        for r in range(args.rounds):
            for label, tree in trees[r % 2 :] + trees[: r % 2]:
                print(f"round {r + 1}: {label}", file=sys.stderr)
                bench = run_bench(tree, Path(tmp) / f"bench_{label}_{r}.json", SMALL_BENCH)
                numpy_op = (
                    run_bench(tree, Path(tmp) / f"bench_numpy_{r}.json", [*SMALL_BENCH, "--rigid-op", "numpy"])
                    if label == "after"
                    else None
                )
                predicts = {
                    outputs: one_run(tree, flags, Path(tmp) / f"out_{label}_{r}_{i}")
                    for i, (outputs, flags) in enumerate(OUTPUTS.items())
                }
                r50 = (
                    run_bench(
                        tree,
                        Path(tmp) / f"bench_r50_{label}_{r}.json",
                        [*RESNET50_BENCH, "--model", str(args.resnet50.resolve())],
                    )
                    if args.resnet50
                    else None
                )
                runs[label].append(figures(bench, numpy_op, run_memory(tree), predicts, int8_flow_delta_pct(tree), r50))
        kitti = Path(tmp) / f"out_after_{args.rounds - 1}_0"
        frame = sorted((REPO / "../shared/realdata/kitti_raw_2011_09_26_sfnd/image_02/data").glob("*.png"))[0]
        measured_bounds = bounds(kitti, frame)
        print("limits: parts, GEMM peaks, onnxruntime int8 profile, int8 sensitivity", file=sys.stderr)
        measured_limits = limits(frame, args.resnet50)
    summary = {
        label: {
            key: statistics.median(v[key] for v in values if v[key] is not None)
            if any(v[key] is not None for v in values)
            else None
            for key in (*TARGETS, *LIMIT_KEYS)
        }
        for label, values in runs.items()
    }
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True)
    result = {
        "against": args.against,
        "commit": commit.stdout.strip() + (" + changes" if _dirty() else ""),
        "rounds": args.rounds,
        "cpus": os.cpu_count(),
        "engines": backends(),
        "resnet50": args.resnet50.name if args.resnet50 else None,
        **summary,
        "bounds_ms": measured_bounds,
        "limits": measured_limits,
        **{
            f"{label}_cpu_ms_per_frame": {
                k: statistics.median(v["predict_cpu_ms_per_frame"][k] for v in values) for k in OUTPUTS
            }
            for label, values in runs.items()
        },
        "runs": runs,
    }
    text = section(result)
    print(text)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=2) + "\n")
    if args.page:
        replace_section(args.page, text)
    return 0


def _dirty() -> bool:
    status = subprocess.run(
        ["git", "status", "--porcelain", "--untracked-files=no"], cwd=REPO, capture_output=True, text=True
    )
    return bool(status.stdout.strip())


if __name__ == "__main__":
    sys.exit(main())

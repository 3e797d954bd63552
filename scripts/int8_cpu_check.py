"""INT8 vs FP32 of a model's graphs on the CPU this runs on, as the runtime runs them and as a plain
onnxruntime session does (issue 45; docs/performance.md, "AVX2-only CPUs").

The plain session lacks the runtime's ``session.x64quantprecision``: on a CPU without VNNI its
uint8 x int8 sums saturate in int16 pairs. An AVX2-only CPU can be run on any x86 machine with
QEMU's user-mode emulator (``apt-get install qemu-user``; slow, a few graphs only)::

    python scripts/int8_cpu_check.py --model small_synth --out /tmp/native.npz
    qemu-x86_64 -cpu Haswell .venv/bin/python scripts/int8_cpu_check.py --model small_synth \\
        --out /tmp/haswell.npz --compare /tmp/native.npz

Feeds: frames of ``--frames`` (default: the bundled sample) resized to the graphs' size; ResFlowNet
gets its 12-channel inputs from the FP32 cascade. Prints, per graph output, the correlation and the
mean |INT8 - FP32| / FP32 range, for the runtime's sessions ("runtime") and plain ones ("plain");
``--compare`` adds the largest difference from another run's outputs (another CPU).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from geonet_infer.convert import quantize as qz  # noqa: E402
from geonet_infer.core.cascade import InputSpec  # noqa: E402
from geonet_infer.core.predictor import Predictor  # noqa: E402
from geonet_infer.engines import onnxruntime as ort_engine  # noqa: E402
from geonet_infer.engines.cpu import isa_line  # noqa: E402
from geonet_infer.io import read_calib_K  # noqa: E402
from geonet_infer.models import resolve_model  # noqa: E402
from geonet_infer.models.manifest import load_manifest  # noqa: E402
from geonet_infer.samples import SAMPLE_CALIB, SAMPLE_FRAMES  # noqa: E402

INPUTS = {"depthnet": "image", "posenet": "snippet", "resflownet": "flow_input"}


def feeds(model_dir: Path, frames_dir: Path, n: int) -> dict[str, list[dict]]:
    m = load_manifest(model_dir)
    frames, original = qz.load_frames(frames_dir, m.height, m.width, n, min_frames=m.seq_length)
    spec = InputSpec.from_manifest(m)
    out = {"depthnet": qz.depth_feeds(frames, spec), "posenet": qz.pose_feeds(frames, spec)}
    if "resflownet" in m.graph_names("fp32"):
        if frames_dir == SAMPLE_FRAMES:
            sx, sy = m.width / original[1], m.height / original[0]
            K = read_calib_K(SAMPLE_CALIB, "K") * np.array([[sx], [sy], [1.0]])
        else:
            K, _ = qz.calibration_intrinsics(frames_dir, original, m.height, m.width)
        out["resflownet"] = qz.resflow_feeds(Predictor(model_dir, "fp32", threads=1), frames, K.astype(np.float32))
    return out


def run_graph(path: Path, feed_list: list[dict], remedy: bool) -> dict[str, np.ndarray]:
    options = ort_engine.make_session_options(threads=1)
    if not remedy:  # a fresh SessionOptions without the runtime's INT8 setting
        import onnxruntime as ort

        options = ort.SessionOptions()
        options.intra_op_num_threads = 1
        options.log_severity_level = 3
    session = ort_engine.make_session(path, options)
    names = [o.name for o in session.get_outputs()]
    runs = [session.run(None, f) for f in feed_list]
    return {n: np.concatenate([r[i] for r in runs]) for i, n in enumerate(names)}


def task_error(output: str, fp32: np.ndarray, int8: np.ndarray) -> str:
    """The task metric of INT8 against FP32 as if FP32 were the ground truth: AbsRel of depth
    (disparity inverted), or flow EPE relative to the mean FP32 flow length (issue 45's goals:
    at most 2 % and 5 %)."""
    if output in ("disparity", "depth"):
        d32, d8 = (1 / fp32, 1 / int8) if output == "disparity" else (fp32, int8)
        return f", AbsRel {float(np.mean(np.abs(d8 - d32) / d32)):.2%}"
    if output == "flow" or (output.endswith("flow") and fp32.ndim == 4 and fp32.shape[1] == 2):
        epe = float(np.linalg.norm(int8 - fp32, axis=1).mean())
        return f", EPE {epe:.3g} px = {epe / float(np.linalg.norm(fp32, axis=1).mean()):.2%} of mean |flow|"
    return ""


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default=None, help="bundled model name or model directory with fp32 and int8")
    parser.add_argument("--frames", type=Path, default=SAMPLE_FRAMES, help="consecutive frames (default: sample)")
    parser.add_argument("--n", type=int, default=6, help="frames read (default 6)")
    parser.add_argument("--out", type=Path, required=True, help="npz of every output (for --compare)")
    parser.add_argument("--compare", type=Path, help="npz of another run: largest difference from it")
    args = parser.parse_args(argv)
    model_dir = resolve_model(args.model)
    m = load_manifest(model_dir)
    print(f"isa: {isa_line()}")
    all_feeds = feeds(model_dir, args.frames, args.n)
    saved = {}
    for graph, feed_list in all_feeds.items():
        if graph not in m.graph_names("int8"):
            continue
        ref = run_graph(m.path(graph, "fp32"), feed_list, remedy=True)
        for label, remedy in (("runtime", True), ("plain", False)):
            got = run_graph(m.path(graph, "int8"), feed_list, remedy)
            for out, value in got.items():
                r, q = ref[out].ravel(), value.ravel()
                corr = float(np.corrcoef(r, q)[0, 1])
                err = float(np.abs(r - q).mean() / (r.max() - r.min()))
                saved[f"{graph}/{out}/{label}"] = value
                print(
                    f"{graph:10s} {out:15s} {label:7s} INT8 vs FP32: corr {corr:.4f}, mean err {err:.4f} of range"
                    + task_error(out, ref[out], value)
                )
    np.savez_compressed(args.out, **saved)
    if args.compare:
        other = np.load(args.compare)
        for key, value in saved.items():
            if key in other:
                diff = float(np.abs(value - other[key]).max())
                print(f"{key:40s} max |this - {args.compare.name}| {diff:.3g}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""GeoNet's depth network against the depth models users pick instead, in ONE interleaved run (issue 44).

    python -m experiments.peer_models --json docs/peer_models_run1.json
    python -m experiments.peer_models --json docs/peer_models_run2.json \\
        --compare docs/peer_models_run1.json --page docs/performance.md   # a second run: same ranking?
    python -m experiments.peer_models --render docs/peer_models_run2.json \\
        --compare docs/peer_models_run1.json --page docs/performance.md   # the page again, no timing
    python -m experiments.peer_models --quick              # development: 1 round, no memory children

The peers (:mod:`experiments.peer_nets`, random weights: speed only) are monodepth2 (ResNet18),
Lite-Mono, MiDaS v2.1 small and Depth-Anything-V2 Small. Each is exported to ONNX (opset 18) at
its native input size and at ours (128x416; Depth-Anything's ViT needs sides divisible by 14, so
126x420 there: the nearest such size, 0.6 % fewer pixels), and quantised to INT8 by the project's
own quantiser (``geonet_infer/convert/quantize.py``: QDQ, per-channel int8 weights, uint8 activations, MinMax)
on real KITTI frames of odometry sequence 06 (never the raw drive the project evaluates on), or
the bundled synthetic sample without them. GeoNet is the bundled ``small_synth`` DepthNet
(fp32 and its shipped int8 graph).

Every graph runs through the runtime's engine factory (``geonet_infer.engines.make_engine``:
onnxruntime with the shipped session options, OpenVINO CPU with f32 inference precision), FP32
and INT8, and is timed two ways with the bench's harness (``geonet_infer.engines.timing``: warm-up, then
block-interleaved rounds in rotating order over ALL cases of the run, quiet-wait and re-warm
before each block, GC off):

* *graph*: the engine alone on a prepared input;
* *e2e*: per frame from a PNG file on disk: read (OpenCV), resize to the graph size
  (``INTER_AREA``), normalise (each model's own mean/std), the graph, the output resized back to
  the frame size (``INTER_LINEAR``). Identical pre/post code for every model.

Memory: one fresh process per (model, size, precision, engine) loads the graph, runs one e2e
frame and reports peak RSS minus RSS before loading (as ``benchmarks/memory.py`` does for the
runtime). MACs: from the ONNX graphs' shapes, Conv/ConvTranspose and MatMul/Gemm (attention
included). Parameters: of the PyTorch modules, checked against each paper's figure (within 2 %).

``--page`` rewrites the page's "## Versus the models users pick instead" section only.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from geonet_infer.bench.environment import cpu_flags
from geonet_infer.core.spec import InputSpec
from geonet_infer.engines import ENGINES, make_engine, usable_cpus
from geonet_infer.engines.cpu import cpu_info, isa_line
from geonet_infer.engines.timing import Case, current_rss_mib, load_average, peak_rss_mib, time_interleaved
from geonet_infer.errors import GeoNetError
from geonet_infer.io.atomic import atomic_write
from geonet_infer.io.images import list_images, read_image, write_image
from geonet_infer.models import resolve_model
from geonet_infer.models.manifest import load_manifest

REPO = Path(__file__).resolve().parents[1]
SECTION = "## Versus the models users pick instead"
OURS = (128, 416)  # (H, W) of GeoNet's graphs
FRAME_DIR = REPO / ".." / "shared" / "realdata" / "kitti_odometry_06" / "sequences" / "06" / "image_2"
SAMPLE_DIR = REPO / "geonet_infer" / "samples" / "synth_seq" / "image"
IMAGENET = ((0.485, 0.456, 0.406), (0.229, 0.224, 0.225))
UNIT = ((0.0, 0.0, 0.0), (1.0, 1.0, 1.0))  # input = pixel / 255 (the network normalises itself)
PRECISIONS = ("fp32", "int8")
BACKENDS = ("onnxruntime", "openvino")
LABEL = {"onnxruntime": "ORT", "openvino": "OpenVINO"}


@dataclass(frozen=True)
class Peer:
    """One model of the comparison and what its paper / official repository says about it."""

    key: str
    title: str
    builder: str  # class name in experiments.peer_nets
    native: tuple[int, int]  # (H, W) it was trained / is run at
    ours: tuple[int, int]  # (H, W) nearest 128x416 its architecture accepts
    norm: tuple[tuple[float, ...], tuple[float, ...]]  # (mean, std) on pixel / 255
    params_ref: float  # parameters the paper / official repo states
    params_src: str
    absrel: str  # KITTI AbsRel as reported ("—": none reported)
    absrel_src: str
    output: str  # what the output is and its shape, per its code

    def out_shape(self, h: int, w: int) -> tuple[int, ...]:
        return (1, 1, h, w) if self.builder in ("Monodepth2", "LiteMono") else (1, h, w)


PEERS = {
    p.key: p
    for p in (
        Peer(
            "monodepth2",
            "monodepth2 (ResNet18)",
            "Monodepth2",
            (192, 640),
            OURS,
            UNIT,
            14.3e6,
            "Lite-Mono paper (Zhang et al., CVPR 2023), Table 1, Monodepth2 R18 row (the monodepth2 paper "
            "gives no count; ResNet18 without its classifier 11.18 M + decoder 3.15 M)",
            "0.115",
            "monodepth2 paper, Table 1 / README (mono_640x192, monocular, ImageNet-pretrained)",
            "disparity (sigmoid) 1 x 1 x H x W",
        ),
        Peer(
            "litemono",
            "Lite-Mono",
            "LiteMono",
            (192, 640),
            OURS,
            UNIT,
            3.1e6,
            "Lite-Mono README / paper Table 1 (lite-mono, 3.1M)",
            "0.107",
            "Lite-Mono README / paper Table 1 (lite-mono 640x192, monocular, ImageNet-pretrained)",
            "disparity (sigmoid) 1 x 1 x H x W",
        ),
        Peer(
            "midas_small",
            "MiDaS v2.1 small",
            "MidasSmall",
            (256, 256),
            OURS,
            IMAGENET,
            21e6,
            "isl-org/MiDaS README, model table, 'Par. M' of v2.1 Small 256: 21",
            "—",
            "none: its README reports zero-shot KITTI as δ>1.25 error (29.27 %), not AbsRel",
            "relative inverse depth (ReLU) 1 x H x W",
        ),
        Peer(
            "dav2_small",
            "Depth-Anything-V2 Small",
            "DepthAnythingV2Small",
            (518, 518),
            (126, 420),
            IMAGENET,
            24.8e6,
            "Depth-Anything-V2 README, model table (Depth-Anything-V2-Small, 24.8M)",
            "0.078 (zero-shot, scale and shift fitted)",
            "Depth-Anything-V2 paper, Table 2, ViT-S, KITTI zero-shot relative depth (an affine-invariant "
            "protocol: scale and shift fitted per image, not the Eigen median-scaling one; the figure as quoted "
            "in github.com/heyoeyo/muggled_dpt issue 8, the paper's text was not at hand)",
            "relative inverse depth (ReLU) 1 x H x W",
        ),
    )
}
GEONET_ABSREL = (
    "0.155",
    "GeoNet paper Table 1, ResNet DepthNet trained on KITTI (../shared/reference/paper_numbers.md)",
)


# ----------------------------------------------------------------------------- inputs
def prepare(rgb: np.ndarray, size: tuple[int, int], mean, std) -> np.ndarray:
    """uint8 RGB (H, W, 3) -> float32 (1, 3, h, w): resized as the runtime does (``INTER_AREA`` down,
    ``INTER_LINEAR`` up), then (pixel / 255 - mean) / std per channel."""
    h, w = size
    if rgb.shape[:2] != (h, w):
        down = rgb.shape[0] >= h and rgb.shape[1] >= w
        rgb = cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA if down else cv2.INTER_LINEAR)
    x = np.ascontiguousarray(rgb.transpose(2, 0, 1)).astype(np.float32)
    scale = (1.0 / (255.0 * np.asarray(std, np.float32)))[:, None, None]
    x *= scale
    x -= (np.asarray(mean, np.float32) / np.asarray(std, np.float32))[:, None, None]
    return x[None]


def geonet_norm(model_dir: Path) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """GeoNet's pixel / 255 * scale + offset as (mean, std), for :func:`prepare`."""
    spec = InputSpec.from_manifest(load_manifest(model_dir))
    return (-spec.norm_offset / spec.norm_scale,) * 3, (1.0 / spec.norm_scale,) * 3


def e2e_call(engine, frame: Path, size: tuple[int, int], norm) -> Callable[[], np.ndarray]:
    """One frame end to end: read the PNG, :func:`prepare`, the graph, the map back at the frame's size."""
    name = engine.input_names[0]
    out_name = engine.output_names[0]

    def run() -> np.ndarray:
        rgb = read_image(frame)
        out = engine.run({name: prepare(rgb, size, *norm)})[out_name]
        return cv2.resize(out.reshape(out.shape[-2:]), (rgb.shape[1], rgb.shape[0]), interpolation=cv2.INTER_LINEAR)

    return run


def bench_frame(tmp: Path) -> tuple[Path, str]:
    """The e2e input: a real KITTI colour frame (odometry 06) if present, else the bundled sample at 1242x375."""
    frames = list_images(FRAME_DIR) if FRAME_DIR.is_dir() else []
    if frames:
        return frames[0], f"../shared/realdata/kitti_odometry_06/sequences/06/image_2/{frames[0].name}"
    rgb = cv2.resize(read_image(list_images(SAMPLE_DIR)[0]), (1242, 375), interpolation=cv2.INTER_LINEAR)
    path = tmp / "frame.png"
    write_image(path, rgb)
    return path, "bundled synthetic sample frame resized to 1242x375"


# ----------------------------------------------------------------------------- counting
def params_of(peer: Peer) -> int:
    """Parameters of the PyTorch module (every tensor the released checkpoint carries)."""
    from experiments import peer_nets

    return sum(p.numel() for p in getattr(peer_nets, peer.builder)().parameters())


def graph_macs_all(path: Path) -> int:
    """Multiply-accumulates of one run of an ONNX graph: Conv/ConvTranspose (``target_limits.graph_macs``)
    plus MatMul and Gemm (linear layers and attention), from ONNX shape inference, batch 1.

    The graph is constant-folded first (onnxruntime's basic level: folding and fusions that keep the
    MACs): the TorchScript exporter computes ``F.pad`` amounts with a chain of ops that shape
    inference cannot follow, which would leave every later shape unknown."""
    import onnx
    import onnxruntime as ort

    from experiments.target_limits import graph_macs

    with tempfile.TemporaryDirectory(prefix="macs_") as tmp:
        folded = Path(tmp) / "folded.onnx"
        options = ort.SessionOptions()
        options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_BASIC
        options.optimized_model_filepath = str(folded)
        ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
        model = onnx.shape_inference.infer_shapes(onnx.load(str(folded)))
        macs = graph_macs(folded)
    shapes = {}
    for value in [*model.graph.value_info, *model.graph.input, *model.graph.output]:
        dims = value.type.tensor_type.shape.dim
        shapes[value.name] = [d.dim_value if d.HasField("dim_value") else 1 for d in dims]
    shapes.update({init.name: list(init.dims) for init in model.graph.initializer})
    for node in model.graph.node:
        if node.op_type in ("MatMul", "Gemm"):
            a = shapes[node.input[0]]
            k = a[-2] if node.op_type == "Gemm" and any(x.name == "transA" and x.i for x in node.attribute) else a[-1]
            macs += int(np.prod(shapes[node.output[0]])) * int(k)
    return macs


# ----------------------------------------------------------------------------- export
def _source_hash() -> str:
    text = (REPO / "benchmarks" / "peer_nets.py").read_bytes() + (REPO / "export" / "quantize.py").read_bytes()
    return hashlib.sha256(text).hexdigest()[:16]


def build_module(peer: Peer, seed: int = 0):
    """The peer's PyTorch module with random weights fixed by ``seed``, in eval mode."""
    import torch

    from experiments import peer_nets

    torch.manual_seed(seed)  # the matrices: PyTorch's initialisation
    return peer_nets.randomize(getattr(peer_nets, peer.builder)(), seed).eval()


def export_peer(peer: Peer, size: tuple[int, int], out: Path, calib: list[np.ndarray], seed: int = 0) -> dict:
    """``out``/fp32.onnx and ``out``/int8.onnx of ``peer`` at ``size`` (random weights, ``seed``)."""
    import torch

    from geonet_infer.convert.quantize import quantize_graph

    module = build_module(peer, seed)
    out.mkdir(parents=True, exist_ok=True)
    example = torch.from_numpy(prepare(calib[0], size, *peer.norm))
    started = time.perf_counter()
    with torch.no_grad():
        torch.onnx.export(
            module,
            (example,),
            str(out / "fp32.onnx"),
            dynamo=False,  # static 1 x 3 x H x W; the TorchScript exporter is quicker here
            opset_version=18,
            input_names=["image"],
            output_names=["depth"],
        )
    feeds = [{"image": prepare(f, size, *peer.norm)} for f in calib]
    notes = quantize_graph(out / "fp32.onnx", out / "int8.onnx", feeds, quant_settings())
    return {"export_s": round(time.perf_counter() - started, 1), "quant_notes": notes}


def quant_settings():
    """The quantiser's defaults, LayerNormalization left fp32: Depth-Anything-V2 applies one norm to four
    taps, and onnxruntime with the runtime's x64 INT8 precision option cannot load a graph whose one
    int8 weight feeds several nodes (it fails with "Attempt to replace the existing tensor")."""
    from geonet_infer.convert.quantize import QuantSettings, quantisable_op_types

    return QuantSettings(op_types=tuple(t for t in quantisable_op_types() if t != "LayerNormalization"))


def calibration_frames(folder: Path | None, count: int) -> tuple[list[np.ndarray], str]:
    """Full-size uint8 RGB calibration frames (never the KITTI raw drive the project evaluates on)."""
    if folder is None:
        folder = FRAME_DIR if FRAME_DIR.is_dir() and list_images(FRAME_DIR) else SAMPLE_DIR
    if "kitti_raw_2011_09_26_sfnd" in str(folder):
        raise SystemExit(f"error: {folder}: the KITTI raw drive is the project's evaluation data; calibrate elsewhere")
    files = list_images(folder)[:count]
    if not files:
        raise SystemExit(f"error: {folder}: no images for the INT8 calibration; pass --calib-data DIR")
    return [read_image(f) for f in files], f"{shown(folder)} ({len(files)} frames)"


def shown(path: Path) -> str:
    """``path`` as the docs write it: ``../shared/...`` beside the repository, else as given."""
    try:
        return "../" + Path(os.path.abspath(path)).relative_to(os.path.abspath(REPO.parent)).as_posix()
    except ValueError:
        return str(path)


# ----------------------------------------------------------------------------- the run
@dataclass
class Model:
    key: str
    title: str
    size: tuple[int, int]
    which: str  # "native" or "ours"
    files: dict[str, Path]  # precision -> graph
    norm: tuple


def collect_models(args, log) -> tuple[list[Model], dict]:
    """GeoNet's bundled graphs and every peer at both sizes, exported (or reused) under ``args.onnx_dir``."""
    geonet_dir = resolve_model(args.geonet)
    manifest = load_manifest(geonet_dir)
    models = [
        Model(
            "geonet",
            f"GeoNet DepthNet ({args.geonet})",
            (manifest.height, manifest.width),
            "ours",
            {p: manifest.path("depthnet", p) for p in PRECISIONS if p in manifest.graphs},
            geonet_norm(geonet_dir),
        )
    ]
    info = {"geonet": {"dir": str(geonet_dir), "arch": manifest.arch}}
    calib, calib_src = calibration_frames(args.calib_data, args.calib_frames)
    info["calibration"] = calib_src
    stamp = {"source": _source_hash(), "calibration": calib_src, "seed": 0, "quant": quant_settings().describe()}
    for peer in PEERS.values():
        if peer.key not in args.peers:
            continue
        for which, size in (("native", peer.native), ("ours", peer.ours)):
            out = args.onnx_dir / f"{peer.key}_{size[0]}x{size[1]}"
            record = out / "export.json"
            fresh = not (record.is_file() and json.loads(record.read_text()).get("stamp") == stamp)
            if fresh:
                log(f"export {peer.key} {size[0]}x{size[1]} (fp32 + int8)")
                done = export_peer(peer, size, out, calib)
                record.write_text(json.dumps({"stamp": stamp, **done}, indent=1) + "\n")
            models.append(
                Model(
                    peer.key,
                    peer.title,
                    size,
                    which,
                    {p: out / f"{p}.onnx" for p in PRECISIONS},
                    peer.norm,
                )
            )
    return models, info


def high_water_mib() -> float | None:
    """Peak RSS of this process image (``VmHWM``), MiB. Unlike ``getrusage``'s maximum, which a child
    keeps from the (large) benchmark process that forked it, it starts afresh at exec; else ``peak_rss_mib``."""
    try:
        with open("/proc/self/status") as f:
            line = next(line for line in f if line.startswith("VmHWM:"))
        return int(line.split()[1]) / 1024
    except (OSError, StopIteration, ValueError):
        return peak_rss_mib()


def memory_child(path: str, backend: str, threads: int, frame: str, h: int, w: int, norm: str) -> dict:
    """In a fresh process: RSS before loading, after, and the peak after one e2e frame (MiB)."""
    before = current_rss_mib()
    engine = make_engine(path, backend, threads)
    loaded = current_rss_mib()
    e2e_call(engine, Path(frame), (h, w), json.loads(norm))()
    peak = high_water_mib()
    return {"rss_before_mib": before, "rss_loaded_mib": loaded, "peak_rss_mib": peak, "added_peak_mib": peak - before}


def measure_memory(models: list[Model], backends: list[str], threads: int, frame: Path, log) -> list[dict]:
    rows = []
    for m in models:
        for precision, path in m.files.items():
            for backend in backends:
                argv = [str(path), backend, str(threads), str(frame), str(m.size[0]), str(m.size[1])]
                argv.append(json.dumps(m.norm))
                done = subprocess.run(
                    [sys.executable, "-m", "experiments.peer_models", "--memory-child", *argv],
                    capture_output=True,
                    text=True,
                    cwd=REPO,
                    env={**os.environ, "PYTHONPATH": str(REPO)},
                )
                if done.returncode != 0:
                    log(f"memory {m.key} {precision} {backend}: {(done.stderr.strip().splitlines() or ['?'])[-1]}")
                    continue
                row = json.loads(done.stdout.strip().splitlines()[-1])
                rows.append({"model": m.key, "size": list(m.size), "precision": precision, "backend": backend, **row})
    return rows


def rankings(results: list[dict]) -> dict[str, list[str]]:
    """Models from fastest to slowest (p50), per (size kind, precision, engine, mode), and per (size
    kind, mode) with each model at its best engine and precision ("best"). GeoNet's 128x416 is both
    its native size and ours."""
    return {k: rankings_of(v) for k, v in tied_rankings(results).items()}


def tied_rankings(results: list[dict]) -> dict[str, list[list[str]]]:
    """:func:`rankings` with ties: each ranking is a list of groups, fastest first. Two models that are
    next to each other by p50 are in one group when their interquartile ranges of timed calls overlap
    (the run cannot tell them apart); groups chain. A row without quartiles (an older JSON) is its own group."""
    best: dict[str, dict[str, dict]] = {}
    for r in results:
        for kind in ("ours", "native") if r["model"] == "geonet" else (r["which"],):
            for key in (f"{kind}/{r['precision']}/{r['backend']}/{r['mode']}", f"{kind}/best/{r['mode']}"):
                rows = best.setdefault(key, {})
                if r["model"] not in rows or r["p50_ms"] < rows[r["model"]]["p50_ms"]:
                    rows[r["model"]] = r
    out: dict[str, list[list[str]]] = {}
    for key, rows in sorted(best.items()):
        groups: list[list[str]] = []
        previous = None
        for model in sorted(rows, key=lambda m: rows[m]["p50_ms"]):
            row = rows[model]
            overlap = previous is not None and "q3_ms" in previous and "q1_ms" in row
            if overlap and previous["q3_ms"] >= row["q1_ms"]:
                groups[-1].append(model)
            else:
                groups.append([model])
            previous = row
        out[key] = groups
    return out


def quartiles(samples_ns: list[int]) -> dict[str, float]:
    q1, q3 = np.percentile(np.asarray(samples_ns) / 1e6, [25, 75])
    return {"q1_ms": float(q1), "q3_ms": float(q3)}


def rankings_of(groups: list[list[str]]) -> list[str]:
    return [m for group in groups for m in group]


def contradictions(a: list[list[str]], b: list[list[str]]) -> list[tuple[str, str]]:
    """Pairs of models that one tied ranking puts strictly in one order and the other strictly in the
    other (a tie in either run is no contradiction)."""

    def rank(groups: list[list[str]]) -> dict[str, int]:
        return {m: i for i, group in enumerate(groups) for m in group}

    ra, rb = rank(a), rank(b)
    common = sorted(set(ra) & set(rb))
    return [(x, y) for i, x in enumerate(common) for y in common[i + 1 :] if (ra[x] - ra[y]) * (rb[x] - rb[y]) < 0]


def run(args) -> dict:
    log = lambda msg: print(f"peer_models: {msg}", file=sys.stderr, flush=True)  # noqa: E731
    started = time.perf_counter()
    threads = args.threads or usable_cpus()
    backends = [b for b in args.backends if ENGINES[b].available()]
    load_start = load_average()
    models, info = collect_models(args, log)
    with tempfile.TemporaryDirectory(prefix="peer_models_") as tmp:
        frame, frame_src = bench_frame(Path(tmp))
        rgb = read_image(frame)
        cases, meta, failures = [], [], []
        for m in models:
            x = prepare(rgb, m.size, *m.norm)
            for precision, path in m.files.items():
                for backend in backends:
                    try:
                        engine = make_engine(path, backend, threads)
                    except GeoNetError as exc:  # reported in the JSON and the page; the run goes on
                        failures.append(
                            {
                                "model": m.key,
                                "size": list(m.size),
                                "precision": precision,
                                "backend": backend,
                                "error": str(exc)[:400],
                            }
                        )
                        log(f"{m.key} {m.size} {precision} {backend}: {exc}")
                        continue
                    name = engine.input_names[0]
                    label = f"{m.key} {m.size[0]}x{m.size[1]} {precision} {backend}"
                    cases.append(Case(f"{label} graph", (lambda e=engine, f={name: x}: e.run(f)), 1))
                    meta.append((m, precision, backend, "graph"))
                    cases.append(Case(f"{label} e2e", e2e_call(engine, frame, m.size, m.norm), 1))
                    meta.append((m, precision, backend, "e2e"))
        log(
            f"timing {len(cases)} cases interleaved: {args.warmup} warm-up, {args.rounds} rounds x {args.block} "
            f"calls, {threads} threads"
        )
        time_interleaved(cases, warmup=args.warmup, iters=args.rounds * args.block, block=args.block)
        results = []
        for (m, precision, backend, mode), case in zip(meta, cases):
            s = case.stats()
            results.append(
                {
                    "model": m.key,
                    "which": m.which,
                    "size": list(m.size),
                    "precision": precision,
                    "backend": backend,
                    "mode": mode,
                    **s.as_dict(),
                    # quartiles of the timed calls: the ranking's ties (tied_rankings)
                    **quartiles(case.samples_ns),
                    "fps_per_core": 1000.0 / s.p50_ms / threads,
                }
            )
        del cases
        load_timed = load_average()
        memory = [] if args.no_memory else measure_memory(models, backends, threads, frame, log)
    nets = {}
    for m in models:
        entry = nets.setdefault(m.key, {"title": m.title, "sizes": {}})
        entry["sizes"][f"{m.size[0]}x{m.size[1]}"] = {
            "which": m.which,
            "gmacs": graph_macs_all(m.files["fp32"]) / 1e9,
            "onnx_mib": {p: round(f.stat().st_size / 2**20, 2) for p, f in m.files.items()},
        }
        peer = PEERS.get(m.key)
        if peer is not None and "params" not in entry:
            n = params_of(peer)
            entry.update(
                params=n,
                params_ref=peer.params_ref,
                params_src=peer.params_src,
                params_within_2pct=abs(n / peer.params_ref - 1) <= 0.02,
                absrel=peer.absrel,
                absrel_src=peer.absrel_src,
                output=peer.output,
                native=list(peer.native),
            )
        elif m.key == "geonet" and "params" not in entry:
            entry.update(params=geonet_params(info["geonet"]["arch"]), absrel=GEONET_ABSREL[0])
            entry.update(absrel_src=GEONET_ABSREL[1], native=list(m.size))
    env = {
        "cpu": cpu_info()["model"],
        "isa": isa_line(),
        "cpu_flags": cpu_flags(),
        "usable_cpus": usable_cpus(),
        "threads": threads,
        "backends": {b: ENGINES[b].version() for b in backends},
        "python": platform.python_version(),
        "load_average_start": load_start,
        "load_average_after_timing": load_timed,
        "load_average_end": load_average(),
        "thread_env": {k: os.environ.get(k) for k in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OMP_WAIT_POLICY")},
        "frame": frame_src,
        "frame_size": list(rgb.shape[:2]),
        "method": {"warmup": args.warmup, "rounds": args.rounds, "block": args.block, "cases": len(results)},
        "wall_s": round(time.perf_counter() - started, 1),
        "git": _git_head(),
        **info,
    }
    return {
        "environment": env,
        "nets": nets,
        "results": results,
        "memory": memory,
        "failures": failures,
        "rankings": rankings(results),
    }


def geonet_params(arch: str) -> int | None:
    """Parameters of training's DepthNet of this arch (None without the training extra)."""
    try:
        from training.networks import DepthNet
    except ImportError:
        return None
    return sum(p.numel() for p in DepthNet(arch).parameters())


def _git_head() -> str | None:
    done = subprocess.run(["git", "rev-parse", "--short=12", "HEAD"], cwd=REPO, capture_output=True, text=True)
    return done.stdout.strip() or None


# ----------------------------------------------------------------------------- report
def _cell(rows: dict, key) -> str:
    g, e = rows.get((*key, "graph")), rows.get((*key, "e2e"))
    return f"{g['p50_ms']:.1f} / {e['p50_ms']:.1f}" if g and e else "—"


def markdown(data: dict, compared: dict | None = None) -> str:
    env, nets, res = data["environment"], data["nets"], data["results"]
    rows = {(r["model"], tuple(r["size"]), r["precision"], r["backend"], r["mode"]): r for r in res}
    backends = [b for b in BACKENDS if b in env["backends"]]
    combos = [(p, b) for p in PRECISIONS for b in backends]
    order = ["geonet", *[k for k in PEERS if k in nets]]
    load = (
        f"1-min load average {env['load_average_start'][0]} at the start, {env['load_average_after_timing'][0]} "
        f"after the timing, on {env['usable_cpus']} CPUs shared with other jobs"
        if env["load_average_start"]
        else "load average unknown"
    )
    lines = [
        SECTION,
        "",
        "Generated by `python -m experiments.peer_models` (issue 44; the command is at the end of this section). "
        "GeoNet's bundled DepthNet beside the depth networks users pick instead, rebuilt in PyTorch from "
        "their papers and code with **random weights** (`experiments/peer_nets.py`: speed only), exported "
        "to ONNX and quantised to INT8 by `geonet_infer/convert/quantize.py`, all timed in **one interleaved run** "
        "through the runtime's engines.",
        "",
        f"- CPU: {env['cpu']}; ISA {env['isa']}; {env['usable_cpus']} usable CPUs, {env['threads']} threads "
        f"per engine; {', '.join(f'{LABEL[b]} {v}' for b, v in env['backends'].items())}; commit `{env['git']}`.",
        f"- {env['method']['cases']} cases, {env['method']['warmup']} warm-up calls, then {env['method']['rounds']} "
        f"rounds x {env['method']['block']} timed calls each, rotating order "
        f"(`geonet_infer.engines.timing`); p50 shown; "
        f"wall {env['wall_s']} s; {load}.",
        f"- *graph* = the engine alone; *e2e* = per frame from a {env['frame_size'][1]}x{env['frame_size'][0]} PNG "
        f"on disk ({env['frame']}): read, resize, normalise, graph, output resized back. "
        f"*frames/s per core* = 1000 / e2e ms / {env['threads']} threads, best engine and precision.",
        f"- INT8 calibration: {env['calibration']}.",
        "- With few samples on a loaded machine a cell can show e2e below graph (the two are separate, "
        "interleaved samples): read differences of less than about 30 % between models as noise.",
        "",
    ]
    for kind, title in (("ours", "At our input size (128x416)"), ("native", "At each model's native input size")):
        lines += [
            f"### {title}, ms per frame, graph / e2e",
            "",
            "| model | input | GMACs | "
            + " | ".join(f"{LABEL[b]} {p.upper()}" for p, b in combos)
            + " | best e2e | frames/s per core |",
            "|---|---|---|" + "---|" * len(combos) + "---|---|",
        ]
        for key in order:
            for size_key, s in nets[key]["sizes"].items():
                if key != "geonet" and s["which"] != kind:
                    continue
                size = tuple(int(v) for v in size_key.split("x"))
                cells = [_cell(rows, (key, size, p, b)) for p, b in combos]
                e2e = [rows[(key, size, p, b, "e2e")] for p, b in combos if (key, size, p, b, "e2e") in rows]
                best = min(e2e, key=lambda r: r["p50_ms"]) if e2e else None
                best_txt = (
                    f"{best['p50_ms']:.1f} ms ({LABEL[best['backend']]} {best['precision'].upper()})" if best else "—"
                )
                fps = f"{best['fps_per_core']:.1f}" if best else "—"
                lines.append(
                    f"| {nets[key]['title']} | {size_key} | {s['gmacs']:.2f} | "
                    + " | ".join(cells)
                    + f" | {best_txt} | {fps} |"
                )
        lines.append("")
    lines += [
        "### The models: parameters, accuracy as reported, memory",
        "",
        "Parameters are those of our PyTorch rebuild, beside the figure its authors state (within 2 % for "
        "every peer: `tests/benchmarks/test_peer_models.py`). KITTI AbsRel is **reported, not measured here** (Eigen "
        "split, 80 m cap, median scaling, as each paper states it); random weights cannot measure it. "
        "Memory: peak RSS a fresh process adds by loading the graph and running one e2e frame, MiB, at 128x416 "
        "(DA-V2: 126x420) / at the native size.",
        "",
        "| model | params (M), ours / paper | KITTI AbsRel (reported, not measured here) | "
        + " | ".join(f"memory {LABEL[b]} {p.upper()}" for p, b in combos)
        + " |",
        "|---|---|---|" + "---|" * len(combos),
    ]
    mem = {(r["model"], tuple(r["size"]), r["precision"], r["backend"]): r["added_peak_mib"] for r in data["memory"]}
    for key in order:
        n = nets[key]
        ref = f"{n['params_ref'] / 1e6:.1f}" if n.get("params_ref") else "—"
        params = f"{n['params'] / 1e6:.2f} / {ref}" if n.get("params") else f"— / {ref}"
        sizes = sorted(n["sizes"], key=lambda s: n["sizes"][s]["which"] != "ours")
        cells = []
        for p, b in combos:
            vals = [mem.get((key, tuple(int(v) for v in s.split("x")), p, b)) for s in sizes]
            cells.append(" / ".join("—" if v is None else f"{v:.0f}" for v in vals))
        lines.append(f"| {n['title']} | {params} | {n['absrel']} | " + " | ".join(cells) + " |")
    lines += ["", "Sources:", ""]
    for key in order:
        n = nets[key]
        src = f"params: {n['params_src']}; " if n.get("params_src") else ""
        lines.append(f"- {n['title']}: {src}AbsRel: {n['absrel_src']}.")
    lines += [
        "- GeoNet's AbsRel is the paper's ResNet50 DepthNet trained on KITTI, not the bundled small model timed "
        "here (trained on synthetic data; its measured real-KITTI numbers: [real_eval.md](real_eval.md)).",
        '- Depth-Anything-V2 runs at 126x420 in the "ours" table: its ViT needs sides divisible by 14.',
        "- Lite-Mono at 128x416 keeps the dilations of its 640x192 setting (its code defines none for other sizes).",
        "",
        "### Ranking (e2e p50, fastest first)",
        "",
        "`a < b`: a is faster, and the interquartile ranges of their timed calls do not overlap; `a ≈ b`: they "
        "overlap, so this run cannot order them.",
        "",
        "| size / precision / engine | this run |" + (" previous run | same order |" if compared else ""),
        "|---|---|" + ("---|---|" if compared else ""),
    ]
    tied = tied_rankings(data["results"])
    old_tied = tied_rankings(compared["results"]) if compared else {}
    shown_order = lambda groups: " < ".join(" ≈ ".join(g) for g in groups)  # noqa: E731
    clashes = {k: contradictions(v, old_tied[k]) for k, v in tied.items() if old_tied.get(k)}
    keys = sorted(tied, key=lambda k: ("/best/" not in k, k))  # each model at its best first
    for key in keys:
        if not key.endswith("/e2e"):
            continue
        line = f"| {key[: -len('/e2e')]} | {shown_order(tied[key])} |"
        if compared:
            prev, clash = old_tied.get(key), clashes.get(key)
            verdict = "—" if not prev else "no: " + ", ".join(f"{a}/{b}" for a, b in clash) if clash else "yes"
            line += f" {shown_order(prev) if prev else '—'} | {verdict} |"
        lines.append(line)
    if compared:
        strict = [k for k in clashes if rankings_of(tied[k]) == rankings_of(old_tied[k])]
        clashing = [k for k, clash in clashes.items() if clash]
        best = [k for k in tied if "/best/" in k and old_tied.get(k)]
        lines += [
            "",
            f"Re-run check against the previous run (`--compare`; git `{compared['environment'].get('git')}`, "
            f"1-min load average {compared['environment']['load_average_start'][0]} at its start): of "
            f"{len(tied)} rankings (graph and e2e), {len(tied) - len(clashing)} have no pair of models in the "
            f"opposite order where both runs tell them apart ({len(best) - len(set(best) & set(clashing))} of the "
            f"{len(best)} at each model's best); {len(strict)} have the same strict order of p50s, ties ignored.",
        ]
    if data["failures"]:
        lines += ["", "Not timed (the engine could not load the graph):", ""]
        lines += [
            f"- {f['model']} {f['size'][0]}x{f['size'][1]} {f['precision']} {f['backend']}: {f['error']}"
            for f in data["failures"]
        ]
    lines += [
        "",
        "Reproduce (`pip install -e '.[train,openvino]'`; 7-8 minutes per run on 2 cores, plus the exports "
        "the first time, cached in `runs/peer_models/onnx`):",
        "",
        "```bash",
        "python -m experiments.peer_models --json docs/peer_models_run1.json",
        "python -m experiments.peer_models --json docs/peer_models_run2.json \\",
        "    --compare docs/peer_models_run1.json --page docs/performance.md",
        "# the page again from the two JSONs, without timing:",
        "python -m experiments.peer_models --render docs/peer_models_run2.json \\",
        "    --compare docs/peer_models_run1.json --page docs/performance.md",
        "```",
        "",
    ]
    return "\n".join(lines)


def replace_section(page: Path, text: str) -> None:
    """Rewrite ``SECTION`` of ``page`` (up to the next "## " heading), or append it; atomically."""
    old = page.read_text() if page.exists() else ""
    start = old.find(SECTION + "\n")
    if start < 0:
        new = old.rstrip("\n") + "\n\n" + text
    else:
        end = old.find("\n## ", start + len(SECTION))
        new = old[:start] + text + ("" if end < 0 else old[end + 1 :])
    with atomic_write(page) as tmp:
        tmp.write_text(new)


# ----------------------------------------------------------------------------- command line
def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m experiments.peer_models",
        description=__doc__.split("\n\n")[0],
        epilog="\n\n".join(__doc__.split("\n\n")[1:]),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--json", type=Path, help="write every number of the run here")
    p.add_argument("--markdown", type=Path, help="write the section's markdown here")
    p.add_argument("--page", type=Path, help=f"rewrite this page's '{SECTION[3:]}' section")
    p.add_argument("--render", type=Path, help="no timing: render a previous run's --json (with --page, --compare)")
    p.add_argument("--compare", type=Path, help="a previous run's --json: report whether the rankings are the same")
    p.add_argument("--geonet", default="small_synth", help="GeoNet model: bundled name or model directory")
    p.add_argument("--peers", default=",".join(PEERS), help=f"comma list of {', '.join(PEERS)}")
    p.add_argument("--backends", default=",".join(BACKENDS), help="comma list of onnxruntime, openvino")
    p.add_argument("--onnx-dir", type=Path, default=REPO / "runs" / "peer_models" / "onnx", help="export cache")
    p.add_argument("--calib-data", type=Path, help="INT8 calibration frames (default: KITTI odometry 06 colour)")
    p.add_argument("--calib-frames", type=int, default=8, help="at most this many calibration frames (default 8)")
    p.add_argument("--threads", type=int, help="threads per engine (default: usable CPUs, as bench)")
    # Small defaults: Depth-Anything-V2 at 518x518 takes seconds per call on 2 cores, and every case
    # is also re-warmed (one call at least) before each block.
    p.add_argument("--warmup", type=int, default=1, help="untimed calls per case first (default 1)")
    p.add_argument("--rounds", type=int, default=9, help="interleaved rounds (default 9)")
    p.add_argument("--block", type=int, default=1, help="timed calls per case per round (default 1)")
    p.add_argument("--no-memory", action="store_true", help="skip the per-configuration memory processes")
    p.add_argument("--quick", action="store_true", help="development: 1 warm-up, 1 round x 1 call, no memory")
    p.add_argument("--memory-child", nargs=7, help=argparse.SUPPRESS)
    return p


def _read_run(path: Path, flag: str) -> dict:
    """A previous run's --json; ValueError naming the flag and the file if it cannot be read."""
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise ValueError(f"{flag} {path}: {exc}") from None


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.memory_child:
        path, backend, threads, frame, h, w, norm = args.memory_child
        print(json.dumps(memory_child(path, backend, int(threads), frame, int(h), int(w), norm)))
        return 0
    args.peers = [k.strip() for k in args.peers.split(",") if k.strip()]
    args.backends = [b.strip() for b in args.backends.split(",") if b.strip()]
    for what, given, allowed in (("peer", args.peers, PEERS), ("backend", args.backends, BACKENDS)):
        bad = [g for g in given if g not in allowed]
        if bad:
            print(f"error: unknown {what} {', '.join(bad)}; choose from {', '.join(allowed)}", file=sys.stderr)
            return 2
    if args.quick:
        args.warmup, args.rounds, args.block, args.no_memory = 1, 1, 1, True
    try:
        compared = _read_run(args.compare, "--compare") if args.compare else None
        rendered = _read_run(args.render, "--render") if args.render else None
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    data = rendered if rendered is not None else run(args)
    text = markdown(data, compared)
    if args.json and not args.render:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(data, indent=1, default=str) + "\n")
    if args.markdown:
        args.markdown.write_text(text)
    if args.page:
        replace_section(args.page, text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())

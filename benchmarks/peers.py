"""The same GeoNet weights through every CPU engine, in ONE interleaved run (dev tool).

    .venv/bin/python benchmarks/peers.py --arch small --random-init              # ~4-6 min
    .venv/bin/python benchmarks/peers.py --arch resnet50 --random-init \\
        --onnx-dir /tmp/geonet_r50                                                # reuse an export
    .venv/bin/python benchmarks/peers.py --checkpoint runs/flow/last.pt
    .venv/bin/python benchmarks/peers.py --quick                                 # development

Engines ("backends"), per graph (DepthNet, PoseNet, ResFlowNet, the rigid-flow op):

* ``eager``    torch eager, the export wrappers around training's modules (BN not folded);
* ``compile``  ``torch.compile`` (inductor, ``freezing=True``, ``dynamic=False``,
  ``compile_threads=1``); a failure is caught and reported, the run goes on;
* ``ort_fp32`` / ``ort_int8``  onnxruntime through the runtime's one session factory
  (``geonet_infer.engines.onnxruntime``: the shipped options, spinning off unless ``--ort-spinning``);
* ``ov_f32`` / ``ov_int8``  OpenVINO CPU on the same ONNX files (static shapes per batch,
  ``PERFORMANCE_HINT=LATENCY``, ``INFERENCE_PRECISION_HINT=f32``: its bf16 default is slower
  on CPUs without AMX and breaks the rigid op). ``pip install -e '.[openvino]'``.

The weights come from ``--checkpoint`` or ``--random-init`` (training's model code, seeded),
exported with ``python -m export`` (fp32 + int8) unless ``--onnx-dir`` names an export of the
same weights; eager vs ORT fp32 parity is checked either way (exit 1 if they differ).

Method (``../shared/reference/cpu_latency_anchors.md``): per (graph, batch) every engine is
loaded and warmed up, then ``--rounds`` rounds; in each round every engine, in a rotating
order, waits until the process is quiet, re-warms for >= 50 ms and makes ``--block`` timed
back-to-back calls (``geonet_infer.engines.timing``). Inputs are realistic: the bundled sample frames
at the graphs' size, with depth, pose and the ResFlowNet input from the fp32 cascade.
Roofline: best of a few 4096^3 GEMMs, fp32 (numpy and torch sgemm) and int8
(``torch._int_mm``, s8 x s8 -> s32); achieved GFLOP/s counts conv MACs x 2 only.

Writes ``--out PREFIX`` .json and .md (default ``runs/bench/peers_<arch>``) and prints the
markdown tables.
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import json
import os
import platform
import shutil
import sys
import tempfile
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from benchmarks.peers_report import BACKENDS, NETS, markdown  # noqa: E402
from geonet_infer.bench.cases import bench_frames, cascade_feeds  # noqa: E402
from geonet_infer.bench.environment import cpu_flags, cpu_model  # noqa: E402
from geonet_infer.core.predictor import Predictor  # noqa: E402
from geonet_infer.engines import usable_cpus  # noqa: E402
from geonet_infer.engines.onnxruntime import make_session, make_session_options  # noqa: E402
from geonet_infer.engines.timing import Case, current_rss_mib, load_average, peak_rss_mib, time_interleaved, wait_quiet  # noqa: E402
from geonet_infer.models.manifest import load_manifest  # noqa: E402

INT8_BACKENDS = ("ort_int8", "ov_int8")
TEMP_DIRS: list[Path] = []  # temporary exports, removed at exit
DEFAULT_CALIB = REPO / ".." / "shared" / "realdata" / "kitti_raw_2011_09_26_sfnd" / "image_02" / "data"


# ----------------------------------------------------------------------------- arguments
def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="benchmarks/peers.py", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    src = p.add_argument_group("weights")
    src.add_argument("--arch", choices=("small", "resnet50", "vgg"), help="with --random-init (default: small)")
    src.add_argument("--random-init", action="store_true", help="seeded random weights (timing only)")
    src.add_argument("--seed", type=int, default=0, help="seed of --random-init (export's default is 0)")
    src.add_argument("--checkpoint", type=Path, help="a training checkpoint (stage flow for ResFlowNet)")
    src.add_argument(
        "--onnx-dir", type=Path, help="an existing `python -m export` directory of the SAME weights (skips the export)"
    )
    src.add_argument("--keep-export", type=Path, help="export into this directory and keep it")
    src.add_argument(
        "--calib-data",
        type=Path,
        default=DEFAULT_CALIB,
        help="frames for the int8 calibration of the export (default: the shared KITTI raw drive, "
        "else the bundled sample)",
    )
    src.add_argument("--calib-frames", type=int, default=8, help="int8 calibration frames (default: 8)")
    run = p.add_argument_group("run")
    run.add_argument("--nets", default=",".join(NETS), help=f"comma list of {', '.join(NETS)}")
    run.add_argument("--backends", default=",".join(BACKENDS), help=f"comma list of {', '.join(BACKENDS)}")
    run.add_argument("--batch", default="1", help="comma list of batch sizes (default: 1)")
    run.add_argument("--threads", type=int, default=None, help="threads per engine (default: usable CPUs)")
    run.add_argument("--warmup", type=int, default=5, help="untimed calls per engine first (default: 5)")
    run.add_argument("--rounds", type=int, default=10, help="interleaving rounds (default: 10)")
    run.add_argument("--block", type=int, default=4, help="timed calls per engine per round (default: 4)")
    run.add_argument("--rewarm-ms", type=float, default=50.0, help="re-warm before each block (default: 50)")
    run.add_argument("--ort-spinning", action="store_true", help="ORT intra-op spinning on (runtime default: off)")
    run.add_argument("--gemm-size", type=int, default=4096, help="roofline GEMM size n (n^3; default 4096)")
    run.add_argument(
        "--quick",
        action="store_true",
        help="development: small arch, 1 warm-up, 2 rounds x 2 calls, GEMM 1024, 8 calibration frames",
    )
    p.add_argument("--out", type=Path, default=None, help="output prefix (default: runs/bench/peers_<arch>)")
    return p


def _csv(text: str, allowed: tuple, what: str) -> list[str]:
    items = [t.strip() for t in text.split(",") if t.strip()]
    bad = [t for t in items if t not in allowed]
    if bad or not items:
        raise SystemExit(f"error: unknown {what} {bad or text!r}; choose from {', '.join(allowed)}")
    return [t for t in allowed if t in items]


# ----------------------------------------------------------------------------- weights and export
def _export_args(args, out: Path) -> list[str]:
    calib = (
        args.calib_data if Path(args.calib_data).is_dir() else REPO / "geonet_infer" / "samples" / "synth_seq" / "image"
    )
    argv = [
        "--out",
        str(out),
        "--precision",
        "fp32,int8",
        "--calib-data",
        str(calib),
        "--calib-frames",
        str(args.calib_frames),
        "--quiet",
        "--force",
    ]
    if args.checkpoint:
        return ["--checkpoint", str(args.checkpoint), *argv]
    return ["--arch", args.arch, "--random-init", "--seed", str(args.seed), *argv]


def load_weights_and_graphs(args, log) -> tuple[object, Path, dict]:
    """(training GeoNet in eval mode, model dir with fp32 + int8 graphs, provenance notes)."""
    from export.__main__ import build_parser as export_parser
    from export.build import ExportConfig, export_model, load_source

    temp = None
    if args.onnx_dir is None and args.keep_export is None:
        temp = Path(tempfile.mkdtemp(prefix="geonet_peers_"))
        TEMP_DIRS.append(temp)
    out = args.onnx_dir or args.keep_export or temp / "model"
    eargv = _export_args(args, out)
    eargs = ExportConfig(**vars(export_parser().parse_args(eargv)))
    notes = {"export_argv": eargv}
    if args.onnx_dir is None:
        log(f"exporting {args.arch or args.checkpoint} (fp32 + int8) -> {out}")
        t0 = time.perf_counter()
        export_model(eargs)
        notes["export_s"] = round(time.perf_counter() - t0, 1)
    manifest = load_manifest(out)
    graphs = list(manifest.graphs["fp32"])
    source = load_source(eargs, graphs)
    if source.height != manifest.height or source.width != manifest.width:
        raise SystemExit(
            f"error: {out} is {manifest.height}x{manifest.width}, the weights' export size is "
            f"{source.height}x{source.width}"
        )
    notes.update(
        onnx_dir=str(out),
        arch=source.arch,
        random_init=source.random_init,
        seed=args.seed,
        checkpoint=str(args.checkpoint) if args.checkpoint else None,
        height=manifest.height,
        width=manifest.width,
        seq_length=manifest.seq_length,
        precisions=list(manifest.graphs),
    )
    return source.model, out, notes


# ----------------------------------------------------------------------------- inputs
def realistic_feeds(model_dir: Path, batch: int, threads: int) -> dict[str, dict[str, np.ndarray]]:
    """Per graph, its feeds at ``batch``: sample frames, and depth/pose/flow input from the fp32 cascade."""
    predictor = Predictor(model_dir, "fp32", threads=threads)
    spec = predictor.spec
    L = spec.seq_length
    frames, camera = bench_frames(None, spec.size, L + batch)
    x = np.stack([spec.to_network(f) for f in frames])
    feeds = cascade_feeds(predictor, x, camera, spec.size, batch)
    del predictor
    return feeds


# ----------------------------------------------------------------------------- engines
@dataclass
class Engine:
    backend: str
    fn: Callable[[], object]
    outputs: Callable[[], list[np.ndarray]]  # one call, outputs as numpy in the graph's output order
    setup_s: float = 0.0
    first_call_ms: float = 0.0
    info: dict = field(default_factory=dict)


def _torch_inputs(feeds: dict, names: list[str]) -> tuple[torch.Tensor, ...]:
    return tuple(torch.from_numpy(np.ascontiguousarray(feeds[n])) for n in names)


def make_engine(backend: str, net: str, model, model_dir: Path, manifest, feeds: dict, threads: int, args) -> Engine:
    from export.wrappers import build_wrapper, io_spec

    spec = io_spec(net, manifest.height, manifest.width, manifest.seq_length)
    in_names = [n for n, _ in spec.inputs]
    started = time.perf_counter()
    if backend in ("eager", "compile"):
        wrapper = build_wrapper(net, model)
        tensors = _torch_inputs(feeds, in_names)
        info = {}
        if backend == "compile":
            import torch._inductor.config as inductor_config

            inductor_config.freezing = True
            inductor_config.compile_threads = 1
            module = torch.compile(wrapper, backend="inductor", dynamic=False)
            ctx = torch.no_grad
            info["options"] = "inductor, freezing=True, dynamic=False, compile_threads=1"
        else:
            module = wrapper
            ctx = torch.inference_mode

        def fn():
            with ctx():
                return module(*tensors)

        def outputs():
            return [o.detach().numpy().copy() for o in fn()]
    elif backend in ("ort_fp32", "ort_int8"):
        precision = backend.split("_")[1]
        if precision not in manifest.graphs or net not in manifest.graphs[precision]:
            raise RuntimeError(f"no {precision} {net} graph in {model_dir}")
        path = manifest.path(net, precision)
        if precision == "int8" and manifest.graph(net, "int8").precision != "int8":
            raise RuntimeError(f"{net} stays fp32 in the int8 set")
        session = make_session(path, make_session_options(threads=threads, spinning=args.ort_spinning))
        ort_feeds = {n: np.ascontiguousarray(feeds[n], dtype=np.float32) for n in in_names}
        info = {"file": str(path.relative_to(model_dir)), "spinning": args.ort_spinning}

        def fn():
            return session.run(None, ort_feeds)

        outputs = fn
    elif backend in ("ov_f32", "ov_int8"):
        import openvino as ov

        precision = "fp32" if backend == "ov_f32" else "int8"
        if precision not in manifest.graphs or net not in manifest.graphs[precision]:
            raise RuntimeError(f"no {precision} {net} graph in {model_dir}")
        if precision == "int8" and manifest.graph(net, "int8").precision != "int8":
            raise RuntimeError(f"{net} stays fp32 in the int8 set")
        path = manifest.path(net, precision)
        core = ov.Core()
        ov_model = core.read_model(str(path))
        ov_model.reshape({n: list(feeds[n].shape) for n in in_names})
        config = {
            "PERFORMANCE_HINT": "LATENCY",
            "INFERENCE_PRECISION_HINT": "f32",
            "INFERENCE_NUM_THREADS": str(threads),
        }
        compiled = core.compile_model(ov_model, "CPU", config)
        request = compiled.create_infer_request()
        ov_feeds = {n: np.ascontiguousarray(feeds[n], dtype=np.float32) for n in in_names}
        info = {
            "file": str(path.relative_to(model_dir)),
            "config": config,
            "properties": {
                k: str(compiled.get_property(k))
                for k in ("INFERENCE_PRECISION_HINT", "INFERENCE_NUM_THREADS", "NUM_STREAMS", "PERFORMANCE_HINT")
            },
        }
        ov_outputs = list(compiled.outputs)

        def fn():
            return request.infer(ov_feeds)

        def outputs():
            result = fn()
            return [np.array(result[o]) for o in ov_outputs]
    else:
        raise ValueError(backend)
    setup_s = time.perf_counter() - started
    t0 = time.perf_counter()
    fn()  # first call: torch.compile compiles here
    first = (time.perf_counter() - t0) * 1e3
    return Engine(backend, fn, outputs, setup_s=setup_s, first_call_ms=first, info=info)


def conv_macs(module: torch.nn.Module, inputs: tuple[torch.Tensor, ...]) -> int:
    """Conv multiply-accumulates of one forward pass (per the batch of ``inputs``)."""
    total = [0]

    def hook(m, _inp, out):
        kh, kw = m.kernel_size
        total[0] += out.numel() * (m.in_channels // m.groups) * kh * kw

    handles = [m.register_forward_hook(hook) for m in module.modules() if isinstance(m, torch.nn.Conv2d)]
    try:
        with torch.inference_mode():
            module(*inputs)
    finally:
        for h in handles:
            h.remove()
    return total[0]


# ----------------------------------------------------------------------------- roofline
def gemm_roofline(n: int, reps: int, log) -> dict:
    """Best and median GFLOP/s (GOP/s for int8) of n^3 GEMMs: numpy sgemm, torch sgemm, torch._int_mm."""
    rng = np.random.default_rng(0)
    a = rng.random((n, n), dtype=np.float32)
    b = rng.random((n, n), dtype=np.float32)
    flop = 2.0 * n**3
    out = {"n": n, "reps": reps}

    def bench(name, fn):
        fn()
        times = []
        for _ in range(reps):
            wait_quiet()
            t0 = time.perf_counter()
            fn()
            times.append(time.perf_counter() - t0)
        out[f"{name}_best"] = flop / min(times) / 1e9
        out[f"{name}_median"] = flop / float(np.median(times)) / 1e9
        log(f"roofline {name}: best {out[f'{name}_best']:.1f}")

    bench("numpy_sgemm_fp32_gflops", lambda: a @ b)
    ta, tb = torch.from_numpy(a), torch.from_numpy(b)
    bench("torch_sgemm_fp32_gflops", lambda: torch.mm(ta, tb))
    try:
        ia = torch.randint(-128, 127, (n, n), dtype=torch.int8)
        ib = torch.randint(-128, 127, (n, n), dtype=torch.int8)
        bench("torch_int_mm_s8s8s32_gops", lambda: torch._int_mm(ia, ib))
    except Exception as exc:  # noqa: BLE001
        out["torch_int_mm_error"] = f"{type(exc).__name__}: {exc}"
    try:
        blas = np.show_config(mode="dicts")["Build Dependencies"]["blas"]["name"]
    except Exception:  # noqa: BLE001
        blas = None
    out["numpy_blas"] = blas
    return out


# ----------------------------------------------------------------------------- run
def max_abs_diff(ref: list[np.ndarray], got: list[np.ndarray]) -> list[float]:
    return [
        float(np.max(np.abs(r.astype(np.float64) - g.astype(np.float64)))) if r.shape == g.shape else float("nan")
        for r, g in zip(ref, got)
    ]


def environment(threads: int) -> dict:
    env = {
        "cpu": cpu_model(),
        "cpu_flags": cpu_flags(),
        "usable_cpus": usable_cpus(),
        "threads": threads,
        "python": platform.python_version(),
        "platform": platform.platform(),
        "numpy": np.__version__,
        "torch": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "torch_interop_threads": torch.get_num_interop_threads(),
        "torch_cpu_capability": getattr(torch.backends.cpu, "get_cpu_capability", lambda: None)(),
        "load_average_start": load_average(),
        "thread_env": {
            k: os.environ.get(k)
            for k in (
                "OMP_NUM_THREADS",
                "MKL_NUM_THREADS",
                "OMP_WAIT_POLICY",
                "KMP_BLOCKTIME",
                "OPENBLAS_NUM_THREADS",
                "ORT_INTRA_OP_NUM_THREADS",
            )
        },
    }
    import onnxruntime as ort

    env["onnxruntime"] = ort.__version__
    try:
        import openvino as ov

        env["openvino"] = ov.__version__
    except ImportError:
        env["openvino"] = None
    try:
        import onnx

        env["onnx"] = onnx.__version__
    except ImportError:
        pass
    return env


def run(args) -> dict:
    log = lambda msg: print(f"peers: {msg}", file=sys.stderr, flush=True)  # noqa: E731
    started = time.perf_counter()
    if args.quick:
        args.arch = args.arch or "small"
        args.warmup, args.rounds, args.block, args.gemm_size = 1, 2, 2, 1024
        args.calib_frames = min(args.calib_frames, 8)
    if bool(args.checkpoint) == bool(args.random_init):
        if args.checkpoint is None and not args.random_init:
            args.random_init = True  # default: random weights
        else:
            raise SystemExit("error: pass exactly one of --checkpoint or --random-init")
    if args.random_init:
        args.arch = args.arch or "small"
    nets = _csv(args.nets, NETS, "net")
    backends = _csv(args.backends, BACKENDS, "backend")
    batches = [int(b) for b in args.batch.split(",") if b.strip()]
    threads = args.threads or usable_cpus()
    torch.set_num_threads(threads)
    env = environment(threads)
    if env["load_average_start"] and env["load_average_start"][0] > 0.5 * env["usable_cpus"]:
        env["busy_warning"] = f"1-min load average {env['load_average_start'][0]} on {env['usable_cpus']} CPUs"
        log(f"warning: machine busy ({env['busy_warning']}): numbers not representative")
    model, model_dir, notes = load_weights_and_graphs(args, log)
    manifest = load_manifest(model_dir)
    nets = [n for n in nets if n in manifest.graphs["fp32"]]
    env["model"] = notes
    roof = gemm_roofline(args.gemm_size, 3 if args.quick else 5, log)
    fp32_roof = roof.get("torch_sgemm_fp32_gflops_best")
    int8_roof = roof.get("torch_int_mm_s8s8s32_gops_best")
    results, failures, net_info = [], [], {}
    all_feeds = {b: realistic_feeds(model_dir, b, threads) for b in batches}
    for net in nets:
        from export.wrappers import build_wrapper, io_spec

        spec = io_spec(net, manifest.height, manifest.width, manifest.seq_length)
        in_names = [n for n, _ in spec.inputs]
        wrapper = build_wrapper(net, model)
        files = {p: (model_dir / manifest.graphs[p][net].file) for p in manifest.graphs if net in manifest.graphs[p]}
        net_info[net] = {
            "params_m": sum(p.numel() for p in wrapper.parameters()) / 1e6,
            "onnx_mib": {p: round(f.stat().st_size / 2**20, 2) for p, f in files.items()},
        }
        for batch in batches:
            feeds = all_feeds[batch][net]
            macs = conv_macs(wrapper, _torch_inputs(feeds, in_names)) if net != "rigidflow" else 0
            net_info[net].setdefault("conv_gmacs", {})[batch] = macs / 1e9
            engines = []
            for backend in backends:
                if backend in INT8_BACKENDS and net == "rigidflow":
                    continue  # the geometric op has no int8 version
                log(f"{net} b{batch}: loading {backend}")
                try:
                    engines.append(make_engine(backend, net, model, model_dir, manifest, feeds, threads, args))
                except Exception as exc:  # noqa: BLE001 -- report and go on (e.g. torch.compile)
                    msg = f"{type(exc).__name__}: {str(exc).splitlines()[0][:300] if str(exc) else ''}"
                    failures.append(
                        {
                            "net": net,
                            "batch": batch,
                            "backend": backend,
                            "error": msg,
                            "traceback": traceback.format_exc(limit=3),
                        }
                    )
                    log(f"{net} b{batch}: {backend} FAILED: {msg}")
            if not engines:
                continue
            ref = next((e for e in engines if e.backend == "eager"), engines[0]).outputs()
            diffs = {e.backend: max_abs_diff(ref, e.outputs()) for e in engines}
            ref_scale = [float(np.max(np.abs(r))) for r in ref]
            if "eager" in diffs and "ort_fp32" in diffs:
                worst = max(d / max(s, 1e-6) for d, s in zip(diffs["ort_fp32"], ref_scale))
                if worst > 1e-3:
                    raise SystemExit(
                        f"error: ORT fp32 {net} differs from torch eager by {worst:.2e} of the output "
                        f"range: {model_dir} was not exported from these weights"
                    )
            cases = [Case(e.backend, e.fn, batch) for e in engines]
            log(
                f"{net} b{batch}: timing {', '.join(e.backend for e in engines)} "
                f"({args.rounds} rounds x {args.block} calls)"
            )
            time_interleaved(
                cases, warmup=args.warmup, iters=args.rounds * args.block, block=args.block, rewarm_ms=args.rewarm_ms
            )
            base = None
            rows = []
            for e, c in zip(engines, cases):
                s = c.stats()
                gflops = 2 * macs / (s.p50_ms / 1e3) / 1e9 if macs else None
                roofline = int8_roof if e.backend in INT8_BACKENDS else fp32_roof
                row = {
                    "net": net,
                    "backend": e.backend,
                    "batch": batch,
                    **s.as_dict(),
                    "per_item_p50_ms": s.p50_ms / batch,
                    "gflops_at_p50": gflops,
                    "roofline_gflops": roofline,
                    "roofline_fraction": gflops / roofline if gflops and roofline else None,
                    "max_abs_diff_vs_eager": diffs[e.backend],
                    "ref_max_abs": ref_scale,
                    "setup_s": round(e.setup_s, 3),
                    "first_call_ms": round(e.first_call_ms, 2),
                    "info": e.info,
                }
                rows.append(row)
                if e.backend == "ort_fp32":
                    base = s.p50_ms
            for row in rows:
                row["speedup_vs_ort_fp32"] = base / row["p50_ms"] if base else None
            results += rows
            del engines, cases
            gc.collect()
        del wrapper
    env["load_average_end"] = load_average()
    env["peak_rss_mib"] = peak_rss_mib()
    env["rss_end_mib"] = current_rss_mib()
    env["wall_s"] = round(time.perf_counter() - started, 1)
    env["method"] = {
        "warmup": args.warmup,
        "rounds": args.rounds,
        "block": args.block,
        "rewarm_ms": args.rewarm_ms,
        "quiet_wait": True,
        "gc_disabled": True,
        "latency": "wall time of one synchronous call incl. output materialisation",
    }
    return {
        "environment": env,
        "roofline": roof,
        "nets": net_info,
        "results": results,
        "failures": failures,
        "backends": backends,
    }


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        data = run(args)
    finally:
        for d in TEMP_DIRS:
            shutil.rmtree(d, ignore_errors=True)
    out = args.out or REPO / "runs" / "bench" / f"peers_{data['environment']['model']['arch']}"
    out.parent.mkdir(parents=True, exist_ok=True)
    md = markdown(data)
    Path(f"{out}.json").write_text(json.dumps(data, indent=2, default=str) + "\n")
    Path(f"{out}.md").write_text(md)
    print(md)
    print(f"-> {out}.json, {out}.md", file=sys.stderr)
    return 0


if __name__ == "__main__":
    with contextlib.suppress(BrokenPipeError):
        sys.exit(main())

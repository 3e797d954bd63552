"""Options and helpers shared by the subcommands."""

from __future__ import annotations

import argparse
import contextlib
import signal
import threading
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from geonet_infer.classical import DIS_PRESET, FLOW_METHODS, POSE_METHODS
from geonet_infer.core.cascade import RIGID_OPS
from geonet_infer.core.predictor import MODES, Predictor, load
from geonet_infer.engines import AUTO, BACKENDS, ENGINES, check_threads
from geonet_infer.errors import InputError
from geonet_infer.io.calib import Camera, read_camera
from geonet_infer.io.camera import ASSUMED_RULE
from geonet_infer.io.frames import FrameSource, open_frames, open_stdin, open_stream
from geonet_infer.limits import DEFAULT_BATCH_SIZE, MAX_BATCH_SIZE
from geonet_infer.models import DEFAULT_MODEL
from geonet_infer.models.manifest import PRECISION_CHOICES


def positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {value}")
    return value


def add_batch_size_arg(parser: argparse.ArgumentParser) -> None:
    """--batch-size, as predict and batch take it (the default and the bound: :mod:`geonet_infer.limits`)."""
    parser.add_argument(
        "--batch-size",
        type=positive_int,
        default=DEFAULT_BATCH_SIZE,
        help=f"frames per DepthNet/PoseNet/ResFlowNet batch, at most {MAX_BATCH_SIZE}; larger batches hold "
        f"more memory and measured no faster (default: {DEFAULT_BATCH_SIZE})",
    )


def backend_help() -> str:
    """--backend's help, one clause per registered engine (:data:`geonet_infer.engines.ENGINES`)."""
    engines = "; ".join(cls.summary for cls in ENGINES.values())
    both, faster = ("both", "faster") if len(ENGINES) == 2 else ("each", "fastest")
    return (
        f"inference engine: {engines}; {AUTO} (times {both} per graph at load, keeps the {faster}) "
        f"(default: {BACKENDS[0]})"
    )


def add_model_args(
    parser: argparse.ArgumentParser,
    threads: bool = True,
    rigid_op: bool = True,
    precision: bool = True,
    mode: str | None = None,
) -> None:
    """--model, --precision (unless ``precision=False``: the caller runs every precision), --backend and
    (unless ``threads=False``: batch has per-worker threads) --threads, (unless ``rigid_op=False``)
    --rigid-op, and with ``mode`` (its default) --mode."""
    group = parser.add_argument_group("model")
    group.add_argument(
        "--model",
        default=None,
        help=f"bundled model name or a model directory from `python -m export` "
        f"(default: the bundled {DEFAULT_MODEL!r})",
    )
    if precision:
        group.add_argument(
            "--precision",
            default="fp32",
            choices=PRECISION_CHOICES,
            help="fp32; int8 (quantised ConvNets, faster on CPUs with VNNI); or auto: per graph, the fastest "
            "precision that is exact on this CPU, timed at load with the engines --backend allows (default: fp32)",
        )
    group.add_argument(
        "--backend",
        default=BACKENDS[0],
        choices=BACKENDS,
        help=backend_help(),
    )
    if rigid_op:
        group.add_argument(
            "--rigid-op",
            choices=RIGID_OPS,
            default=RIGID_OPS[0],
            help="how the weightless rigid-flow op runs: 'graph' (rigidflow.onnx on --backend, the "
            "reference) or 'numpy' (numpy + OpenCV, about 1.5x as fast; flows within 2e-4 px of the "
            "graph's) (default: graph)",
        )
    if mode:
        group.add_argument(
            "--mode",
            default=mode,
            choices=MODES,
            help="how the CPUs are spent: 'latency' (one graph call at a time on every thread) or 'throughput' "
            "(as many batches of the sequence computed at once as there are threads, one thread each; the "
            f"same graph calls, the same outputs to float rounding) (default: {mode})",
        )
    if threads:
        group.add_argument(
            "--threads",
            type=positive_int,
            default=None,
            help="inference threads per graph (default: the CPUs this process may use)",
        )


def load_predictor(args: argparse.Namespace) -> Predictor:
    """The predictor the model options ask for; more --threads than usable CPUs is refused."""
    if getattr(args, "threads", None) is not None:
        check_threads(args.threads, "--threads")
    return load(
        args.model,
        precision=args.precision,
        threads=args.threads,
        backend=args.backend,
        rigid_op=getattr(args, "rigid_op", RIGID_OPS[0]),
        mode=getattr(args, "mode", "latency"),
    )


def add_method_args(parser: argparse.ArgumentParser) -> None:
    """--flow-method and --pose-method: the networks, or the classical methods the eval measures."""
    group = parser.add_argument_group("methods (what makes the flow and the poses)")
    group.add_argument(
        "--flow-method",
        choices=FLOW_METHODS,
        default=FLOW_METHODS[0],
        help=f"'network' (GeoNet's full flow) or 'dis' (OpenCV DIS optical flow, preset {DIS_PRESET}, at the "
        "input resolution: the eval's DIS row, far better than the bundled model on real KITTI flow, see "
        "docs/real_eval.md; needs no network and no intrinsics); same files either way (default: network)",
    )
    group.add_argument(
        "--pose-method",
        choices=POSE_METHODS,
        default=POSE_METHODS[0],
        help="'network' (PoseNet) or 'orbvo' (the eval's two-view ORB visual odometry per frame pair; each "
        "step's length from the predicted depth of its matched points, so metres with --camera-height; "
        "needs intrinsics and the depth network) (default: network)",
    )


def add_camera_args(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("camera (needed for flow)").add_mutually_exclusive_group()
    group.add_argument(
        "--calib",
        type=Path,
        default=None,
        help="calibration file: KITTI calib_cam_to_cam.txt (P_rect_02), KITTI odometry calib.txt "
        "(P2), a 3x3 text matrix, `K: ...` files, key/value files with K and dist, or an "
        "EuRoC sensor.yaml; lens distortion, where given, is removed before inference "
        "(default: the KITTI drive's own calibration, if INPUT is one)",
    )
    group.add_argument(
        "--intrinsics",
        default=None,
        metavar="FX,FY,CX,CY|estimate",
        help="pinhole intrinsics in pixels at the input frames' resolution; or 'estimate': the focal length "
        "from the footage itself (it needs the camera to rotate; where the footage cannot determine it, one "
        "line says why and the assumed intrinsics are used). Without --calib or --intrinsics: the input's "
        "own calibration (KITTI raw and odometry, EuRoC, TUM RGB-D layouts, or NAME.calib.txt beside it), "
        f"else assumed: {ASSUMED_RULE}",
    )


def parse_intrinsics(text: str) -> Camera:
    """``--intrinsics FX,FY,CX,CY`` (every subcommand that takes it) as a checked pinhole Camera."""
    try:
        fx, fy, cx, cy = (float(v) for v in text.split(","))
    except ValueError:
        raise InputError(
            None,
            f"--intrinsics {text!r} is not four numbers nor 'estimate'",
            "write it as FX,FY,CX,CY, e.g. 721.5,721.5,609.6,172.9, or --intrinsics estimate",
        ) from None
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
    return Camera(K, None, None, f"--intrinsics {text}", "flag").validate("--intrinsics")


ESTIMATE = "estimate"


def camera_from_args(args: argparse.Namespace, source=None, log=None) -> Camera | None:
    """The Camera from --calib, --intrinsics FX,FY,CX,CY or estimate (needs ``source``), or the input's own
    calibration (``source.own_camera()``); None: the caller assumes them (:data:`ASSUMED_RULE`)."""
    if args.intrinsics == ESTIMATE:
        if source is None:
            return None  # batch: each input estimates its own
        if source.kind in ("camera", "stream", "stdin"):
            raise InputError(source.location, "a live source cannot be read twice to estimate its focal length")
        from geonet_infer.core.self_calibration import camera_from_footage

        camera, refusal = camera_from_footage(frame.rgb for frame in source if frame.rgb is not None)
        if refusal and log is not None:
            log(f"{source.location}: {refusal}")
        return camera
    if args.intrinsics is not None:
        return parse_intrinsics(args.intrinsics)
    if args.calib is not None:
        return read_camera(args.calib).validate(args.calib)
    return None if source is None else source.own_camera()


def stage_table(per_frame_ms: dict[str, float], frames: int, overlapped: dict[str, float] | None = None) -> str:
    """A plain-text table of the mean ms per frame of each stage that ran: summary.json's
    ``timings_ms_per_frame`` (they add up to its total, the wall time per frame), then its
    ``overlapped_ms_per_frame`` apart (:mod:`geonet_infer.output.latency`)."""
    from geonet_infer.output.latency import meaning

    rows = [(s, ms) for s, ms in per_frame_ms.items() if s != "total" and ms and round(ms, 2)]
    rows.append(("total", per_frame_ms.get("total", sum(ms for _, ms in rows))))
    more = [(s, ms) for s, ms in (overlapped or {}).items() if ms]
    width = max([len(s) for s, _ in rows + more] + [5])

    def line(stage: str, ms: float) -> str:
        said = meaning(stage)
        return f"  {stage:<{width}}  {ms:8.2f}{f'  ({said})' if said else ''}"

    lines = [f"per-frame latency (mean over {frames} frames)", f"  {'stage':<{width}}  {'ms':>8}"]
    return "\n".join(lines + [line(s, ms) for s, ms in rows + more])


@contextlib.contextmanager
def sigterm_as_interrupt() -> Iterator[None]:
    """SIGTERM (a scheduler or ``kill`` stopping the job) handled like Ctrl-C inside the block.

    The KeyboardInterrupt unwinds through the writers (temp files removed), ``predict_to_dir``
    writes its summary with ``"interrupted": true`` and ``main()`` exits 130 with one line.
    Later SIGTERMs (a group-wide one, then the job's own; a scheduler sending it again) are ignored:
    they would cut that clean-up short, or end the process with another status; so after one the
    handler is not put back (the run is ending).
    Signal handlers can only be set from the main thread; elsewhere this does nothing.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    received: list[int] = []

    def interrupt(signum, frame):
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        received.append(signum)
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, interrupt)
    try:
        yield
    finally:
        if not received:
            signal.signal(signal.SIGTERM, previous)


def open_source(args: argparse.Namespace) -> FrameSource:
    """predict's frames: INPUT, '-' with --stdin-frames, or --source (here, beside the camera and model from
    ``args``, so that ``args`` goes down from cli/predict.py and does not come back)."""
    if args.source is not None:
        if args.input is not None:
            raise InputError(args.input, "INPUT and --source both given", "pass one of them")
        return open_stream(args.source)
    if args.input is None and args.stdin_frames is None:
        raise InputError(
            None, "no input", "pass INPUT (a video, a folder of frames), '-' with --stdin-frames, or --source"
        )
    if args.input is None or str(args.input) == "-":  # --stdin-frames alone also reads stdin
        if args.stdin_frames is None:
            raise InputError("-", "raw frames on stdin need their size", "pass --stdin-frames WxH, e.g. 1280x720")
        width, height = args.stdin_frames
        return open_stdin(width, height, fps=args.fps)
    if args.stdin_frames is not None:
        raise InputError(args.input, "--stdin-frames is for INPUT '-'", "drop --stdin-frames, or pipe the frames in")
    return open_frames(args.input)

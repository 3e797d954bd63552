"""Checkpoints written by ``training.train``: save, load safely, rebuild the model.

A checkpoint holds only tensors and plain Python values (RNG states included), so it
loads with ``torch.load(weights_only=True)``: a file from elsewhere cannot run code when
opened. Tensors are stored on the CPU, so a GPU run resumes and exports on a CPU machine.
"""

from __future__ import annotations

import argparse
import pickle
import random
import re
import shlex
import sys
from pathlib import Path

import numpy as np
import torch

from geonet_infer import conventions
from geonet_infer.errors import GeoNetError, InputError
from geonet_infer.io import atomic_write
from training.config import TrainConfig
from training.model import GeoNet

# v2: RNG states stored as tensors (v1 pickled numpy's state, which weights_only refuses).
CHECKPOINT_FORMAT = "geonet-checkpoint-v2"
OLD_FORMAT = "geonet-checkpoint-v1"
REQUIRED_KEYS = ("format", "stage", "arch", "step", "config", "model", "optimizer", "rng", "metrics")
# Weights only (no optimizer or RNG state): what is published beside a bundled model, to fine-tune from.
WEIGHTS_FORMAT = "geonet-weights-v1"
WRITTEN_BY = "pass a .pt file written by training.train"


# ------------------------------------------------------------------------ RNG states
def rng_state() -> dict:
    """torch (CPU and CUDA), numpy and Python RNG states as tensors and plain values."""
    np_kind, np_keys, np_pos, np_has_gauss, np_gauss = np.random.get_state()
    py_version, py_words, py_gauss = random.getstate()
    state = {
        "torch": torch.get_rng_state(),
        "numpy": {
            "kind": np_kind,
            "keys": torch.from_numpy(np_keys.astype(np.int64)),
            "pos": int(np_pos),
            "has_gauss": int(np_has_gauss),
            "gauss": float(np_gauss),
        },
        "python": {"version": py_version, "words": torch.tensor(py_words, dtype=torch.int64), "gauss": py_gauss},
    }
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict) -> None:
    """Inverse of :func:`rng_state` (CUDA states only where this machine has CUDA)."""
    torch.set_rng_state(state["torch"])
    n = state["numpy"]
    np.random.set_state((n["kind"], n["keys"].numpy().astype(np.uint32), n["pos"], n["has_gauss"], n["gauss"]))
    p = state["python"]
    random.setstate((p["version"], tuple(int(w) for w in p["words"].tolist()), p["gauss"]))
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def _to_cpu(value):
    if isinstance(value, torch.Tensor):
        return value.detach().cpu()
    if isinstance(value, dict):
        return {k: _to_cpu(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return type(value)(_to_cpu(v) for v in value)
    return value


# ------------------------------------------------------------------------ save / load
def save_checkpoint(
    path: Path,
    model: GeoNet,
    optimizer,
    step: int,
    cfg: TrainConfig,
    metrics: dict,
    scaler: torch.amp.GradScaler | None = None,
) -> None:
    """Write atomically: a crash mid-save never leaves a truncated checkpoint."""
    state = {
        "format": CHECKPOINT_FORMAT,
        "stage": cfg.stage,
        "arch": cfg.arch,
        "step": step,
        "config": cfg.to_dict(),
        "conventions": conventions.as_dict(),
        "model": _to_cpu(model.state_dict()),
        "optimizer": _to_cpu(optimizer.state_dict()),
        "grad_scaler": scaler.state_dict() if scaler is not None else {},
        "rng": rng_state(),
        "metrics": metrics,
        # module form, not argv[0]: argv[0] is this machine's absolute path to train.py
        "command": "python -m training.train " + shlex.join(sys.argv[1:]),
    }
    with atomic_write(path) as tmp:
        torch.save(state, tmp)


def _refusal(path: Path, exc: Exception) -> GeoNetError:
    """The weights-only unpickler refused the file: name what it wanted to import."""
    try:
        names = torch.serialization.get_unsafe_globals_in_checkpoint(path)
    except Exception:  # the refusal itself is what matters; the names are a courtesy
        names = []
    what = f" ({', '.join(names[:4])})" if names else f" ({str(exc).splitlines()[0][:120]})"
    hint = WRITTEN_BY
    if names and all(n.startswith("numpy") for n in names):  # what a v1 checkpoint's RNG state needs
        hint = (
            "a checkpoint of an older training.train (v1) holds numpy RNG state; if you trust the file, "
            f"convert it once: python -m training.checkpoint --upgrade {path}"
        )
    return InputError(
        path,
        f"refused: the file holds Python objects beyond tensors and plain values{what}, "
        "which could run code when loaded",
        hint,
    )


def _safe_load(path: Path, what: str):
    """``torch.load(weights_only=True)`` onto the CPU; every failure names the file."""
    if not path.is_file():
        raise InputError(path, f"{what} not found", WRITTEN_BY)
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        raise _refusal(path, exc) from None
    except Exception as exc:  # torch raises many types for a corrupt file
        first = str(exc).splitlines()[0] if str(exc) else ""
        raise InputError(path, f"cannot read {what} ({exc.__class__.__name__}: {first})") from exc


def load_checkpoint(path: str | Path, expect_stage: str | None = None, expect_arch: str | None = None) -> dict:
    """Load (weights only, onto the CPU) and validate; errors name the file and the fix."""
    path = Path(path)
    ckpt = _safe_load(path, "checkpoint")
    if not isinstance(ckpt, dict):
        raise InputError(path, f"not a GeoNet checkpoint: it holds a {type(ckpt).__name__}, not a dict", WRITTEN_BY)
    if ckpt.get("format") != CHECKPOINT_FORMAT:
        found = f"format {ckpt['format']!r}" if "format" in ckpt else f"keys {sorted(map(str, ckpt))[:6]}"
        raise InputError(path, f"not a {CHECKPOINT_FORMAT} checkpoint ({found})", WRITTEN_BY)
    missing = [k for k in REQUIRED_KEYS if k not in ckpt]
    if missing:
        raise InputError(path, f"checkpoint lacks {', '.join(missing)}", WRITTEN_BY)
    if expect_stage and ckpt["stage"] != expect_stage:
        raise InputError(
            path,
            f"checkpoint is from stage '{ckpt['stage']}', expected '{expect_stage}'",
            "stage flow needs --init-checkpoint from a stage rigid run",
        )
    if expect_arch and ckpt["arch"] != expect_arch:
        raise InputError(
            path, f"checkpoint arch is '{ckpt['arch']}', expected '{expect_arch}'", f"pass --arch {ckpt['arch']}"
        )
    return ckpt


# ------------------------------------------------------------------------ weights only
def save_weights(ckpt: dict, path: str | Path, source: dict | None = None) -> None:
    """A checkpoint's weights and config, without optimizer or RNG state (about a third of the size).

    Conv kernels are stored as float16, which halves the file again; fine-tuning starts within
    ~1e-3 relative of the original weights. Everything else (BN statistics, biases) stays float32.
    """
    model = {k: v.half() if v.is_floating_point() and v.dim() == 4 else v for k, v in _to_cpu(ckpt["model"]).items()}
    state = {
        "format": WEIGHTS_FORMAT,
        "stage": ckpt["stage"],
        "arch": ckpt["arch"],
        "config": ckpt["config"],
        "conventions": ckpt.get("conventions", conventions.as_dict()),
        "model": model,
        "source": source or {"step": ckpt["step"], "command": _portable_command(ckpt.get("command"))},
    }
    with atomic_write(Path(path)) as tmp:
        torch.save(state, tmp)


def combine_weights(depth_pose: str | Path, flow: str | Path, out: str | Path) -> None:
    """Weights of a stage-flow model: DepthNet/PoseNet from ``depth_pose``, ResFlowNet from ``flow``.

    How an adapted model keeps the published ResFlowNet: fine-tune DepthNet/PoseNet (stage
    rigid), combine, then fine-tune the ResFlowNet on top (stage flow).
    """
    dp = load_weights(depth_pose)
    fl = load_weights(flow, expect_arch=dp["arch"])
    flow_state = {k: v for k, v in fl["model"].items() if k.startswith("flow_net.")}
    if not flow_state:
        raise InputError(flow, "has no ResFlowNet weights", "pass a stage-flow checkpoint or weights file")
    model = {k: v for k, v in dp["model"].items() if not k.startswith("flow_net.")} | flow_state
    config = {**dp["config"], "stage": "flow"}
    # the step and command are depth_pose's: the training a model combined this way adds
    source = {"depth_pose": str(depth_pose), "flow": str(flow), **trained_by(dp)}
    save_weights({**dp, "stage": "flow", "config": config, "model": model}, out, source)


def trained_by(state: dict) -> dict:
    """The step and training command of a checkpoint, or those a weights file kept from one."""
    source = state.get("source", {})
    return {
        "step": state.get("step", source.get("step")),
        "command": _portable_command(state.get("command", source.get("command"))),
    }


def interpolate_weights(base: str | Path, tuned: str | Path, alpha: float, out: str | Path) -> None:
    """Weights ``(1 - alpha) * base + alpha * tuned``, tensor by tensor (WiSE-FT, Wortsman et al. 2022).

    ``tuned`` is a fine-tuned descendant of ``base`` (so the two sit in one basin and their
    average is a working net). The output has ``tuned``'s stage, config and tensors; those that
    ``base`` lacks (a ResFlowNet on top of a stage-rigid base) and integer counters are taken
    from ``tuned`` unchanged. BatchNorm statistics are interpolated like the weights.
    Measured use: docs/training.md, "Toward real video".
    """
    if not 0.0 <= alpha <= 1.0:
        raise InputError(None, f"alpha {alpha} is outside [0, 1]", "0 gives base, 1 gives tuned")
    tu = load_weights(tuned)
    ba = load_weights(base, expect_arch=tu["arch"])
    model = {}
    for key, w_tuned in tu["model"].items():
        w_base = ba["model"].get(key)
        if w_base is None or not w_tuned.is_floating_point():
            model[key] = w_tuned
        elif w_base.shape != w_tuned.shape:
            raise InputError(base, f"{key} is {tuple(w_base.shape)}, {tuned} has {tuple(w_tuned.shape)}", "")
        else:
            model[key] = torch.lerp(w_base, w_tuned, alpha)
    source = {"base": str(base), "tuned": str(tuned), "alpha": alpha}
    save_weights({**tu, "model": model}, out, source)


def _portable_command(command: str | None) -> str | None:
    """v1 checkpoints recorded argv[0], this machine's absolute path to train.py: keep the module form."""
    return re.sub(r"^\S*training/train\.py", "python -m training.train", command) if command else command


def load_weights(path: str | Path, expect_arch: str | None = None) -> dict:
    """Weights to start training from: a weights-only file or a full checkpoint (float32 on return)."""
    path = Path(path)
    state = _safe_load(path, "weights file")
    if isinstance(state, dict) and state.get("format") == CHECKPOINT_FORMAT:
        state = load_checkpoint(path, expect_arch=expect_arch)
    elif not isinstance(state, dict) or state.get("format") != WEIGHTS_FORMAT:
        raise InputError(path, f"neither a {CHECKPOINT_FORMAT} checkpoint nor a {WEIGHTS_FORMAT} file", WRITTEN_BY)
    if expect_arch and state["arch"] != expect_arch:
        raise InputError(
            path, f"weights arch is '{state['arch']}', expected '{expect_arch}'", f"pass --arch {state['arch']}"
        )
    model = {k: v.float() if v.is_floating_point() else v for k, v in state["model"].items()}
    return {**state, "model": model}


# ------------------------------------------------------------------------ model
def build_model(cfg: TrainConfig) -> GeoNet:
    return GeoNet(
        cfg.arch,
        cfg.num_source,
        with_flow=cfg.stage == "flow",
        bn_momentum=cfg.bn_momentum,
        weights=cfg.weights,
        mask_out_of_view=cfg.mask_out_of_view,
        automask=cfg.automask,
        scale_normalize=cfg.scale_normalize,
        rigid_corruption=cfg.rigid_corruption,
        hard_gate=cfg.hard_gate,
        direct_flow=cfg.direct_flow,
        gate_width=cfg.gate_width,
    )


def model_from_checkpoint(ckpt: dict) -> GeoNet:
    """Rebuild the GeoNet a checkpoint came from, weights loaded, in eval mode."""
    model = build_model(TrainConfig.from_dict(ckpt["config"]))
    model.load_state_dict(ckpt["model"])
    return model.eval()


# ------------------------------------------------------------------------ upgrade
def upgrade(path: str | Path) -> None:
    """Rewrite a v1 checkpoint as v2 in place. Unpickles it fully: only for files you trust."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "checkpoint not found", WRITTEN_BY)
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as exc:
        raise InputError(path, f"cannot read checkpoint ({exc.__class__.__name__})") from exc
    if not isinstance(ckpt, dict) or ckpt.get("format") != OLD_FORMAT:
        found = ckpt.get("format") if isinstance(ckpt, dict) else type(ckpt).__name__
        raise InputError(path, f"not a {OLD_FORMAT} checkpoint ({found!r})", "nothing to upgrade")
    np_state, py_state = ckpt["rng"]["numpy"], ckpt["rng"]["python"]
    saved = (np.random.get_state(), random.getstate())
    np.random.set_state(np_state)
    random.setstate(py_state)
    ckpt["rng"] = {**rng_state(), "torch": ckpt["rng"]["torch"]}  # numpy/python from the file, as tensors
    np.random.set_state(saved[0])
    random.setstate(saved[1])
    ckpt["format"] = CHECKPOINT_FORMAT
    ckpt.setdefault("grad_scaler", {})
    with atomic_write(path) as tmp:
        torch.save(ckpt, tmp)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m training.checkpoint",
        description="Convert checkpoints of an older training.train to the format that loads with "
        "torch.load(weights_only=True) (--upgrade: unpickles them, trusted files only), write a "
        "checkpoint's weights alone to fine-tune from (--weights-only), put two models' nets together "
        "(--combine) or interpolate a fine-tuned model toward the one it started from (--interpolate).",
    )
    mode = p.add_mutually_exclusive_group(required=True)
    mode.add_argument("--upgrade", nargs="+", metavar="FILE", help="v1 checkpoints, rewritten in place")
    mode.add_argument("--weights-only", nargs=2, metavar=("CHECKPOINT", "OUT"), help="write CHECKPOINT's weights")
    mode.add_argument(
        "--combine",
        nargs=3,
        metavar=("DEPTH_POSE", "FLOW", "OUT"),
        help="weights with DepthNet/PoseNet of DEPTH_POSE and ResFlowNet of FLOW (checkpoints or weights files)",
    )
    mode.add_argument(
        "--interpolate",
        nargs=4,
        metavar=("BASE", "TUNED", "ALPHA", "OUT"),
        help="weights (1 - ALPHA) * BASE + ALPHA * TUNED, where TUNED was fine-tuned from BASE (WiSE-FT)",
    )
    args = p.parse_args(argv)
    if args.weights_only or args.combine or args.interpolate:
        dst = (args.weights_only or args.combine or args.interpolate)[-1]
        try:
            if args.weights_only:
                save_weights(load_checkpoint(args.weights_only[0]), dst)
            elif args.interpolate:
                base, tuned, alpha, _ = args.interpolate
                try:
                    alpha = float(alpha)
                except ValueError:
                    raise InputError(None, f"ALPHA {alpha!r} is not a number", "e.g. 0.85") from None
                interpolate_weights(base, tuned, alpha, dst)
            else:
                combine_weights(*args.combine)
        except GeoNetError as err:
            print(f"error: {err}", file=sys.stderr)
            return 2
        print(f"wrote {dst} ({Path(dst).stat().st_size / 2**20:.1f} MiB)")
        return 0
    failed = 0
    for path in args.upgrade:
        try:
            upgrade(path)
            print(f"upgraded {path}")
        except GeoNetError as err:
            print(f"error: {err}", file=sys.stderr)
            failed += 1
    if failed == len(args.upgrade):
        return 2
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())

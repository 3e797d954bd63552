"""Stage-wise GeoNet training: ``python -m training.train --stage rigid|flow ...``.

Checkpoints (``last.pt``, ``best.pt`` by validation loss) hold the model, the
optimizer, the step, every RNG state and the full config, so ``--resume``
continues bit-for-bit. Per-term losses go to the console (tqdm) and to
``<out_dir>/log.jsonl``.
"""
from __future__ import annotations

import json
import os
import random
import shlex
import sys
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from geonet_infer import conventions
from geonet_infer.errors import GeoNetInputError
from training.config import TrainConfig, config_from_args
from training.data import SequenceDataset
from training.model import GeoNet

CHECKPOINT_FORMAT = "geonet-checkpoint-v1"


# ------------------------------------------------------------------ checkpoints
def save_checkpoint(path: Path, model: GeoNet, optimizer, step: int, cfg: TrainConfig,
                    metrics: dict) -> None:
    """Write atomically: a crash mid-save never leaves a truncated checkpoint."""
    state = {
        "format": CHECKPOINT_FORMAT,
        "stage": cfg.stage,
        "arch": cfg.arch,
        "step": step,
        "config": cfg.to_dict(),
        "conventions": conventions.as_dict(),
        "model": model.state_dict(),
        "optimizer": optimizer.state_dict(),
        "rng": {"torch": torch.get_rng_state(), "numpy": np.random.get_state(),
                "python": random.getstate()},
        "metrics": metrics,
        # module form, not argv[0]: argv[0] is this machine's absolute path to train.py
        "command": "python -m training.train " + shlex.join(sys.argv[1:]),
    }
    tmp = path.with_suffix(".tmp")
    torch.save(state, tmp)
    os.replace(tmp, path)


def load_checkpoint(path: str | Path, expect_stage: str | None = None,
                    expect_arch: str | None = None) -> dict:
    """Load and validate a checkpoint; errors name the file and the fix."""
    path = Path(path)
    if not path.is_file():
        raise GeoNetInputError(path, "checkpoint not found", "pass a .pt file written by training.train")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as exc:  # torch raises many types for a corrupt file
        raise GeoNetInputError(path, f"cannot read checkpoint ({exc.__class__.__name__}: {exc})") from exc
    if not isinstance(ckpt, dict) or ckpt.get("format") != CHECKPOINT_FORMAT:
        raise GeoNetInputError(path, "not a GeoNet checkpoint written by training.train")
    if expect_stage and ckpt["stage"] != expect_stage:
        raise GeoNetInputError(path, f"checkpoint is from stage '{ckpt['stage']}', expected '{expect_stage}'",
                               "stage flow needs --init-checkpoint from a stage rigid run")
    if expect_arch and ckpt["arch"] != expect_arch:
        raise GeoNetInputError(path, f"checkpoint arch is '{ckpt['arch']}', expected '{expect_arch}'",
                               f"pass --arch {ckpt['arch']}")
    return ckpt


# ----------------------------------------------------------------------- setup
def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def build_model(cfg: TrainConfig) -> GeoNet:
    return GeoNet(cfg.arch, cfg.num_source, with_flow=cfg.stage == "flow",
                  bn_momentum=cfg.bn_momentum, weights=cfg.weights,
                  mask_out_of_view=cfg.mask_out_of_view, automask=cfg.automask)


def model_from_checkpoint(ckpt: dict) -> GeoNet:
    """Rebuild the GeoNet a checkpoint came from, weights loaded, in eval mode."""
    model = build_model(TrainConfig.from_dict(ckpt["config"]))
    model.load_state_dict(ckpt["model"])
    return model.eval()


def trainable_modules(model: GeoNet, stage: str) -> list[torch.nn.Module]:
    return [model.depth_net, model.pose_net] if stage == "rigid" else [model.flow_net]


def set_modes(model: GeoNet, stage: str, training: bool) -> None:
    """Only the stage's own nets use batch statistics; frozen nets use moving averages."""
    model.eval()
    for module in trainable_modules(model, stage):
        module.train(training)


def epoch_batches(dataset: SequenceDataset, cfg: TrainConfig, epoch: int):
    """Batches of one epoch in a seeded order, so a resumed run sees the same data."""
    dataset.set_epoch(epoch)
    generator = torch.Generator().manual_seed(cfg.seed * 1000 + epoch)
    loader = torch.utils.data.DataLoader(
        dataset, batch_size=cfg.batch_size, shuffle=True, generator=generator,
        num_workers=cfg.num_workers, drop_last=True, persistent_workers=False)
    return iter(loader)


def stage_loss(model: GeoNet, stage: str, batch: dict):
    fn = model.rigid_loss if stage == "rigid" else model.flow_loss
    return fn(batch["target"], batch["sources"], batch["intrinsics"])


@torch.no_grad()
def validate(model: GeoNet, cfg: TrainConfig, val_set: SequenceDataset | None) -> dict:
    if val_set is None or len(val_set) == 0:
        return {}
    set_modes(model, cfg.stage, training=False)
    loader = torch.utils.data.DataLoader(val_set, batch_size=cfg.batch_size, shuffle=False,
                                         num_workers=0)
    sums: dict[str, float] = {}
    count = 0
    for i, batch in enumerate(loader):
        if i >= cfg.val_batches:
            break
        for name, value in stage_loss(model, cfg.stage, batch).terms.items():
            sums[name] = sums.get(name, 0.0) + value
        count += 1
    set_modes(model, cfg.stage, training=True)
    return {f"val_{k}": v / count for k, v in sums.items()}


# ------------------------------------------------------------------------ train
def train(cfg: TrainConfig, progress: bool = True) -> dict:
    """Run one stage; returns {'step', 'log', 'last', 'best', 'metrics'}."""
    out_dir = Path(cfg.out_dir)
    if cfg.stage == "flow" and not (cfg.init_checkpoint or cfg.resume):
        raise GeoNetInputError(None, "stage flow needs --init-checkpoint",
                               "pass the last.pt of a stage rigid run")
    seed_everything(cfg.seed)
    train_set = SequenceDataset(cfg.data_dir, "train", cfg.seq_length, cfg.height, cfg.width,
                                augment=cfg.augment, share_color_gain=cfg.share_color_gain,
                                seed=cfg.seed)
    if len(train_set) < cfg.batch_size:
        raise GeoNetInputError(Path(cfg.data_dir) / "train.txt",
                               f"{len(train_set)} samples, fewer than one batch of {cfg.batch_size}",
                               "prepare more data or lower --batch-size")
    val_path = Path(cfg.data_dir) / "val.txt"
    val_set = None
    if val_path.is_file() and val_path.read_text().strip():
        val_set = SequenceDataset(cfg.data_dir, "val", cfg.seq_length, cfg.height, cfg.width,
                                  augment=False, seed=cfg.seed)

    model = build_model(cfg)
    if cfg.stage == "flow" and cfg.init_checkpoint and not cfg.resume:
        rigid = load_checkpoint(cfg.init_checkpoint, expect_stage="rigid", expect_arch=cfg.arch)
        rigid_state = {k: v for k, v in rigid["model"].items() if not k.startswith("flow_net.")}
        model.load_state_dict(rigid_state, strict=False)
    if cfg.channels_last:
        model = model.to(memory_format=torch.channels_last)
    params = [p for m in trainable_modules(model, cfg.stage) for p in m.parameters() if p.requires_grad]
    frozen = [m for m in (model.depth_net, model.pose_net) if cfg.stage == "flow"]
    for module in frozen:
        module.requires_grad_(False)
    optimizer = torch.optim.Adam(params, lr=cfg.lr, betas=(cfg.beta1, cfg.beta2))

    step, best = 0, float("inf")
    if cfg.resume:
        ckpt = load_checkpoint(cfg.resume, expect_stage=cfg.stage, expect_arch=cfg.arch)
        model.load_state_dict(ckpt["model"])
        optimizer.load_state_dict(ckpt["optimizer"])
        step = ckpt["step"]
        best = ckpt["metrics"].get("best_val_total", best)
        torch.set_rng_state(ckpt["rng"]["torch"])
        np.random.set_state(ckpt["rng"]["numpy"])
        random.setstate(ckpt["rng"]["python"])

    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "config.json").write_text(json.dumps(cfg.to_dict(), indent=2))
    log_path = out_dir / "log.jsonl"
    steps_per_epoch = len(train_set) // cfg.batch_size
    epoch = step // steps_per_epoch
    batches = epoch_batches(train_set, cfg, epoch)
    for _ in range(step % steps_per_epoch):  # skip what the resumed run already saw
        next(batches)
    set_modes(model, cfg.stage, training=True)
    metrics: dict = {"best_val_total": best}
    bar = tqdm(total=cfg.max_steps, initial=step, desc=f"train {cfg.stage}", disable=not progress,
               dynamic_ncols=True)
    started = time.perf_counter()
    with open(log_path, "a") as log:
        while step < cfg.max_steps:
            try:
                batch = next(batches)
            except StopIteration:
                epoch += 1
                batches = epoch_batches(train_set, cfg, epoch)
                continue
            loss = stage_loss(model, cfg.stage, batch)
            optimizer.zero_grad(set_to_none=True)
            loss.total.backward()
            optimizer.step()
            step += 1
            bar.update(1)
            row = {"step": step, "epoch": epoch, **loss.terms}
            out_of_time = (cfg.max_minutes is not None
                           and time.perf_counter() - started > 60 * cfg.max_minutes)
            last_step = step == cfg.max_steps or out_of_time
            if step % cfg.val_every == 0 or last_step:
                row.update(validate(model, cfg, val_set))
                if row.get("val_total", float("inf")) < best:
                    best = row["val_total"]
                    metrics.update({k: v for k, v in row.items() if k.startswith("val_")})
                    metrics["best_val_total"] = best
                    metrics["best_step"] = step
                    save_checkpoint(out_dir / "best.pt", model, optimizer, step, cfg, metrics)
            if step % cfg.log_every == 0 or "val_total" in row:
                row["elapsed_s"] = round(time.perf_counter() - started, 2)
                log.write(json.dumps(row) + "\n")
                log.flush()
                bar.set_postfix({k: f"{v:.4f}" for k, v in loss.terms.items()})
            if step % cfg.save_every == 0 or last_step:
                save_checkpoint(out_dir / "last.pt", model, optimizer, step, cfg, metrics)
            if out_of_time:
                print(f"stopping at step {step}: --max-minutes {cfg.max_minutes} reached")
                break
    bar.close()
    return {"step": step, "log": log_path, "last": out_dir / "last.pt",
            "best": out_dir / "best.pt", "metrics": metrics}


def main(argv=None) -> int:
    cfg = config_from_args(argv)
    try:
        result = train(cfg)
    except GeoNetInputError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(f"done: step {result['step']}, checkpoint {result['last']}, log {result['log']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

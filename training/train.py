"""Stage-wise GeoNet training: ``python -m training.train --stage rigid|flow ...``.

Checkpoints (``last.pt``, ``best.pt`` by validation loss; format in
:mod:`training.checkpoint`) hold the model, the optimizer, the step, every RNG state and
the full config, so ``--resume`` continues bit-for-bit. Per-term losses go to the
console (tqdm) and to ``<out_dir>/log.jsonl``.

``--device``/``--amp``/``--compile`` choose where and how the nets run. Several processes
(GPUs or machines): ``torchrun --nproc_per_node N -m training.train ...`` trains
data-parallel (DDP, :mod:`training.distributed`); the effective batch is
``--batch-size`` x N, the logged losses are averaged over the ranks, and rank 0 alone
writes the log and the checkpoints.
"""

from __future__ import annotations

import json
import random
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import TextIO

import numpy as np
import torch
from torch.nn.parallel import DistributedDataParallel
from torch.utils.data import ConcatDataset
from torch.utils.data.distributed import DistributedSampler
from tqdm import tqdm

from geonet_infer.errors import GeoNetError, InputError
from training import distributed
from training.checkpoint import build_model, load_checkpoint, load_weights, save_checkpoint, set_rng_state
from training.config import TrainConfig, config_from_args
from training.data import SequenceDataset, make_loader
from training.model import GeoNet, StageLoss

AMP_DTYPES = {"bf16": torch.bfloat16, "fp16": torch.float16}
MAX_LOADER_STALLS = 3  # data-worker restarts after a loader timeout before the run gives up


# ----------------------------------------------------------------------- setup
def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def trainable_modules(model: GeoNet, cfg: TrainConfig) -> list[torch.nn.Module]:
    """The nets the stage trains (``--freeze-depth``: stage rigid without DepthNet; ``--gate-only``: PoseNet's
    motion gate)."""
    if cfg.stage == "flow":
        return [model.flow_net]
    if cfg.gate_only:
        return [model.pose_net.gate]
    return [model.pose_net] if cfg.freeze_depth else [model.depth_net, model.pose_net]


def set_modes(model: GeoNet, cfg: TrainConfig, training: bool) -> None:
    """Only the stage's own nets use batch statistics; frozen nets use moving averages."""
    model.eval()
    for module in trainable_modules(model, cfg):
        module.train(training)


def loss_name(cfg: TrainConfig) -> str:
    """Which loss a run trains: its stage's, or "gate" (stage rigid with ``--gate-only``)."""
    return "gate" if cfg.gate_only else cfg.stage


def stage_loss(model: GeoNet, stage: str, target, sources, K, truth: dict | None = None) -> StageLoss:
    """``stage``: :func:`loss_name`. ``truth``: the batch's ground truth for supervision by name (depth_gt
    and pose_gt in stage rigid and gate, flow_gt in stage flow) or None."""
    if stage == "gate":
        return model.gate_loss(target, sources, **(truth or {}))
    if stage == "rigid":
        return model.rigid_loss(target, sources, K, **(truth or {}))
    return model.flow_loss(target, sources, K, **(truth or {}))


class StageLossModule(torch.nn.Module):
    """The stage's loss as ``forward``: DDP prepares its gradient sync in ``forward``, and
    torch.compile wraps one call."""

    def __init__(self, model: GeoNet, stage: str):
        super().__init__()
        self.model = model
        self.stage = stage

    def forward(self, target, sources, K, truth: dict | None = None) -> StageLoss:
        return stage_loss(self.model, self.stage, target, sources, K, truth)


def autocast_nets(model: GeoNet, device_type: str, dtype: torch.dtype) -> None:
    """Run the three nets under autocast and hand float32 back: pixel coordinates, matrix
    inverses and the losses stay float32 (bf16 would round a 416-px coordinate to 2 px)."""
    for net in (model.depth_net, model.pose_net, model.flow_net):
        if net is None:
            continue

        def forward(*args, _inner=net.forward, **kwargs):
            with torch.autocast(device_type, dtype=dtype):
                out = _inner(*args, **kwargs)
            return [o.float() for o in out] if isinstance(out, (list, tuple)) else out.float()

        net.forward = forward  # an instance attribute: parameters and state_dict keys unchanged


def with_model_options_of_its_weights(cfg: TrainConfig) -> TrainConfig:
    """``cfg`` with the options that shape the nets taken from the weights the run starts from (``--resume`` or
    ``--init-checkpoint``) where the command line left them off: PoseNet's motion gate (``--pose-gate``,
    ``--hard-gate``; its width always theirs) and a direct ResFlowNet (``--direct-flow``). So fine-tuning a
    gated or direct model, the bundled one since issue 53, needs no flags to load it."""
    source = cfg.resume or cfg.init_checkpoint
    if not source:
        return cfg
    theirs = TrainConfig.from_dict(load_weights(source)["config"])
    weights, gate_width = cfg.weights, cfg.gate_width
    if theirs.weights.pose_gate > 0:  # their gate, as wide as they made it
        gate_width = theirs.gate_width
        if weights.pose_gate == 0:
            weights = replace(weights, pose_gate=theirs.weights.pose_gate)
    return replace(
        cfg,
        weights=weights,
        gate_width=gate_width,
        hard_gate=cfg.hard_gate or theirs.hard_gate,
        direct_flow=cfg.direct_flow or theirs.direct_flow,
    )


def check_options(cfg: TrainConfig, device: torch.device) -> None:
    if cfg.amp == "fp16" and device.type != "cuda":
        raise InputError(
            None, f"--amp fp16 needs a CUDA device, this run is on {device}", "use --amp bf16 or --amp off on the CPU"
        )
    if cfg.weights.keeps_pose and (cfg.resume or not cfg.init_checkpoint or cfg.stage != "rigid"):
        raise InputError(
            None,
            "--pose-keep and --pose-keep-shape hold PoseNet to the one it starts from: "
            "it needs stage rigid and --init-checkpoint, not --resume",
            "start a new run from the weights to keep (--init-checkpoint)",
        )
    if cfg.gate_only and (cfg.stage != "rigid" or cfg.weights.pose_gate <= 0):
        raise InputError(None, "--gate-only trains the motion gate of stage rigid", "pass --stage rigid --pose-gate W")
    if cfg.stage == "flow" and not (cfg.init_checkpoint or cfg.resume):
        raise InputError(None, "stage flow needs --init-checkpoint", "pass the last.pt of a stage rigid run")


class TrainSet(ConcatDataset):
    """The training samples of ``--data-dir`` and every ``--extra-data-dir``, shuffled together."""

    def set_epoch(self, epoch: int) -> None:
        for dataset in self.datasets:
            dataset.set_epoch(epoch)


def epoch_loader(dataset: TrainSet, sampler: DistributedSampler, cfg: TrainConfig, epoch: int, skip_batches: int = 0):
    """This rank's batches of one epoch in a seeded order (DistributedSampler: seed + epoch),
    starting after ``skip_batches`` so a resumed run sees the same data without loading it."""
    dataset.set_epoch(epoch)
    sampler.set_epoch(epoch)
    indices = list(sampler)[skip_batches * cfg.batch_size :]
    return iter(
        make_loader(
            dataset,
            cfg.batch_size,
            shuffle=False,
            num_workers=cfg.num_workers,
            seed=cfg.seed * 1000 + epoch,
            drop_last=True,
            sampler=indices,
        )
    )


TRUTH_KEYS = (
    *("depth_gt", "pose_gt", "flow_gt"),
    *("twin_target", "twin_sources", "has_twin", "next_target", "next_sources", "has_next"),
)


def to_device(batch: dict, device: torch.device) -> tuple:
    """-> (target, sources, K, truth or None): the stage loss's arguments; truth holds the
    batch's ground truth by name (depth_gt, pose_gt, flow_gt, the stride twins, the next snippets:
    those the run loads)."""
    truth = {k: batch[k].to(device, non_blocking=True) for k in TRUTH_KEYS if k in batch}
    return (
        *(batch[k].to(device, non_blocking=True) for k in ("target", "sources", "intrinsics")),
        truth or None,
    )


@torch.no_grad()
def validate(model: GeoNet, cfg: TrainConfig, val_set: SequenceDataset | None, device: torch.device) -> dict:
    if val_set is None or len(val_set) == 0:
        return {}
    set_modes(model, cfg, training=False)
    loader = make_loader(val_set, cfg.batch_size, shuffle=False, seed=cfg.seed)
    sums: dict[str, float] = {}
    count = 0
    for i, batch in enumerate(loader):
        if i >= cfg.val_batches:
            break
        for name, value in stage_loss(model, loss_name(cfg), *to_device(batch, device)).terms.items():
            sums[name] = sums.get(name, 0.0) + value
        count += 1
    set_modes(model, cfg, training=True)
    return {f"val_{k}": v / count for k, v in sums.items()}


# ------------------------------------------------------------------------ train
def init_from(model: GeoNet, cfg: TrainConfig) -> None:
    """Start from ``cfg.init_checkpoint`` (a checkpoint or a weights-only file) with a fresh optimizer.

    Stage rigid: its DepthNet and PoseNet (fine-tuning, e.g. on your own footage), PoseNet's motion gate
    new if it has none. Stage flow: its DepthNet and PoseNet (with the gate of a gated model), frozen, and
    its ResFlowNet too if it has one (else a new one).
    """
    init = load_weights(cfg.init_checkpoint, expect_arch=cfg.arch)
    state = {k: v for k, v in init["model"].items() if cfg.stage == "flow" or not k.startswith("flow_net.")}
    missing, unexpected = model.load_state_dict(state, strict=False)
    fresh = ("flow_net.", "pose_net.gate.") if cfg.stage == "rigid" else ("flow_net.",)  # may start new here
    missing = [k for k in missing if not k.startswith(fresh)]
    if missing or unexpected:
        raise InputError(
            cfg.init_checkpoint,
            f"weights do not fit this model (missing {missing[:3]}, unexpected {unexpected[:3]})",
            "use weights of the same --arch and --seq-length",
        )


def train(cfg: TrainConfig, progress: bool = True) -> dict:
    """Run one stage; returns {'step', 'log', 'last', 'best', 'metrics'}.

    Under torchrun every rank calls this; rank 0 writes the files.
    """
    rt = distributed.setup(cfg.device)
    try:
        result = Trainer(cfg, rt, progress).run()
    except BaseException:
        distributed.teardown(rt, clean=False)
        raise
    distributed.teardown(rt)
    return result


class Trainer:
    """One stage's run, monodepth2-style: ``__init__`` builds the data, the model, the optimizer and
    (``--resume``) the saved state; :meth:`run` loops :meth:`train_step` and, on rank 0,
    :meth:`end_of_step` (validate, log, checkpoint).

    The order of the calls that draw random numbers (seeding, model init, resumed RNG state, data
    order) is part of the ``--resume`` bit-for-bit contract: keep it when editing.
    """

    def __init__(self, cfg: TrainConfig, rt: distributed.Runtime, progress: bool):
        cfg = with_model_options_of_its_weights(cfg)
        check_options(cfg, rt.device)
        self.cfg, self.rt, self.progress = cfg, rt, progress
        self.out_dir = Path(cfg.out_dir)
        self.log_path = self.out_dir / "log.jsonl"
        # the samples carry their ground truth when the stage's loss is supervised by it
        self.load_depth = cfg.stage == "rigid" and cfg.weights.depth_supervision > 0
        self.load_flow = cfg.stage == "flow" and cfg.weights.flow_supervision > 0
        self.load_pose = cfg.stage == "rigid" and (cfg.weights.pose_supervision > 0 or cfg.gate_only)
        self.load_twins = cfg.stage == "rigid" and cfg.weights.pose_stride > 0
        self.load_next = cfg.stage == "rigid" and cfg.weights.pose_overlap > 0
        seed_everything(cfg.seed)
        self.train_set, self.sampler = self._train_data()
        self.val_set = self._val_data() if rt.is_main else None
        self.model, self.optimizer, self.scaler = self._build_model()
        self.step, self.best = 0, float("inf")
        if cfg.resume:
            self._resume()
        self.loss_fn = self._loss_fn()
        self.metrics: dict = {"best_val_total": self.best}
        self.epoch = 0
        self.started = 0.0

    # ------------------------------------------------------------------ setup
    def _train_data(self) -> tuple[TrainSet, DistributedSampler]:
        """The training samples of every data folder and this rank's sampler over them."""
        cfg, rt = self.cfg, self.rt
        train_set = TrainSet(
            [
                SequenceDataset(
                    root,
                    "train",
                    cfg.seq_length,
                    cfg.height,
                    cfg.width,
                    augment=cfg.augment,
                    share_color_gain=cfg.share_color_gain,
                    seed=cfg.seed + k,  # another augmentation stream per folder
                    load_depth=self.load_depth,
                    load_flow=self.load_flow,
                    load_pose=self.load_pose,
                    load_twins=self.load_twins,
                    load_next=self.load_next,
                )
                for k, root in enumerate([cfg.data_dir, *cfg.extra_data_dirs])
            ]
        )
        # drop_last: every rank gets as many samples, none twice (no padding with repeats)
        sampler = DistributedSampler(
            train_set, num_replicas=rt.world_size, rank=rt.rank, shuffle=True, seed=cfg.seed, drop_last=True
        )
        if len(sampler) < cfg.batch_size:
            per = f" per rank ({rt.world_size} ranks)" if rt.distributed else ""
            raise InputError(
                Path(cfg.data_dir) / "train.txt",
                f"{len(train_set)} samples, fewer than one batch of {cfg.batch_size}{per}",
                "prepare more data or lower --batch-size",
            )
        return train_set, sampler

    def _val_data(self) -> SequenceDataset | None:
        """``val.txt`` of ``--data-dir`` (rank 0 validates alone); None when there is none."""
        cfg = self.cfg
        val_path = Path(cfg.data_dir) / "val.txt"
        if not (val_path.is_file() and val_path.read_text().strip()):
            return None
        return SequenceDataset(
            cfg.data_dir,
            "val",
            cfg.seq_length,
            cfg.height,
            cfg.width,
            augment=False,
            seed=cfg.seed,
            load_depth=self.load_depth,
            load_flow=self.load_flow,
            load_pose=self.load_pose,
            load_twins=self.load_twins,
            load_next=self.load_next,
        )

    def _build_model(self) -> tuple[GeoNet, torch.optim.Optimizer, torch.amp.GradScaler]:
        """The model on its device (``--init-checkpoint`` loaded, stage flow's rigid nets frozen), the
        optimizer of the stage's trainable parameters and the fp16 grad scaler (disabled otherwise)."""
        cfg, rt = self.cfg, self.rt
        model = build_model(cfg)
        if cfg.init_checkpoint and not cfg.resume:
            init_from(model, cfg)
        if cfg.sync_bn:
            distributed.convert_sync_bn(model)
        model = model.to(rt.device, memory_format=torch.channels_last if cfg.channels_last else torch.preserve_format)
        if cfg.weights.keeps_pose:
            model.keep_pose_of(model.pose_net)
        trainable = trainable_modules(model, cfg)
        frozen = [m for m in (model.depth_net, model.pose_net, model.flow_net) if m is not None and m not in trainable]
        for module in frozen:
            module.requires_grad_(False)
        for module in trainable:  # after: the motion gate of --gate-only lies inside the frozen PoseNet
            module.requires_grad_(True)
        params = [p for m in trainable for p in m.parameters()]
        optimizer = torch.optim.Adam(params, lr=cfg.lr, betas=(cfg.beta1, cfg.beta2))
        scaler = torch.amp.GradScaler(rt.device.type, enabled=cfg.amp == "fp16")
        return model, optimizer, scaler

    def _resume(self) -> None:
        """Model, optimizer, grad scaler, step, best validation loss and every RNG state of ``--resume``."""
        ckpt = load_checkpoint(self.cfg.resume, expect_stage=self.cfg.stage, expect_arch=self.cfg.arch)
        self.model.load_state_dict(ckpt["model"])
        self.optimizer.load_state_dict(ckpt["optimizer"])
        if ckpt.get("grad_scaler"):
            self.scaler.load_state_dict(ckpt["grad_scaler"])
        self.step = ckpt["step"]
        self.best = ckpt["metrics"].get("best_val_total", self.best)
        set_rng_state(ckpt["rng"])

    def _loss_fn(self) -> torch.nn.Module:
        """The stage loss as one module: under autocast (``--amp``), DDP (torchrun) and torch.compile."""
        cfg, rt = self.cfg, self.rt
        if cfg.amp != "off":
            autocast_nets(self.model, rt.device.type, AMP_DTYPES[cfg.amp])
        loss_fn: torch.nn.Module = StageLossModule(self.model, loss_name(cfg))
        if rt.distributed:
            loss_fn = DistributedDataParallel(loss_fn, device_ids=[rt.device] if rt.device.type == "cuda" else None)
        if cfg.compile:
            loss_fn = torch.compile(loss_fn)
        return loss_fn

    # ------------------------------------------------------------------- loop
    def run(self) -> dict:
        """Train to ``--max-steps`` (or ``--max-minutes``); returns {'step', 'log', 'last', 'best', 'metrics'}."""
        cfg, rt = self.cfg, self.rt
        if rt.is_main:
            self.out_dir.mkdir(parents=True, exist_ok=True)
            (self.out_dir / "config.json").write_text(json.dumps(cfg.to_dict(), indent=2))
            if self.progress:
                print(
                    f"training on {rt.device}: {rt.world_size} process(es) x batch {cfg.batch_size} "
                    f"= effective batch {rt.world_size * cfg.batch_size}"
                )
        steps_per_epoch = len(self.sampler) // cfg.batch_size
        self.epoch = self.step // steps_per_epoch
        batches = epoch_loader(self.train_set, self.sampler, cfg, self.epoch, skip_batches=self.step % steps_per_epoch)
        set_modes(self.model, cfg, training=True)
        bar = tqdm(
            total=cfg.max_steps,
            initial=self.step,
            desc=f"train {cfg.stage}",
            disable=not (self.progress and rt.is_main),
            dynamic_ncols=True,
        )
        self.started = time.perf_counter()
        stalls = 0
        log = open(self.log_path, "a") if rt.is_main else None
        try:
            while self.step < cfg.max_steps:
                try:
                    batch = next(batches)
                except StopIteration:
                    self.epoch += 1
                    batches = epoch_loader(self.train_set, self.sampler, cfg, self.epoch)
                    continue
                except RuntimeError as exc:  # the loader's timeout: new workers, same position
                    if "timed out" not in str(exc) or stalls >= MAX_LOADER_STALLS:
                        raise
                    stalls += 1
                    print(f"step {self.step}: {exc}; restarting the data workers ({stalls}/{MAX_LOADER_STALLS})")
                    batches = epoch_loader(
                        self.train_set, self.sampler, cfg, self.epoch, skip_batches=self.step % steps_per_epoch
                    )
                    continue
                loss = self.train_step(batch)
                bar.update(1)
                terms, out_of_time = self._gather(loss.terms, self._out_of_time())
                if rt.is_main:
                    self.end_of_step(terms, self.step == cfg.max_steps or out_of_time, log, bar)
                if out_of_time:
                    if rt.is_main:
                        print(f"stopping at step {self.step}: --max-minutes {cfg.max_minutes} reached")
                    break
        finally:
            if log is not None:
                log.close()
            bar.close()
        return {
            "step": self.step,
            "log": self.log_path,
            "last": self.out_dir / "last.pt",
            "best": self.out_dir / "best.pt",
            "metrics": self.metrics,
        }

    def train_step(self, batch: dict) -> StageLoss:
        """One optimizer step on ``batch`` (every rank); returns its loss."""
        loss = self.loss_fn(*to_device(batch, self.rt.device))
        self.optimizer.zero_grad(set_to_none=True)
        self.scaler.scale(loss.total).backward()
        self.scaler.step(self.optimizer)
        self.scaler.update()
        self.step += 1
        return loss

    def _out_of_time(self) -> bool:
        return self.cfg.max_minutes is not None and time.perf_counter() - self.started > 60 * self.cfg.max_minutes

    def _gather(self, terms: dict[str, float], out_of_time: bool) -> tuple[dict[str, float], bool]:
        """Under torchrun, one collective: the losses averaged over the ranks for the log, and whether
        any rank ran out of time (then all stop at the same step)."""
        if not self.rt.distributed:
            return terms, out_of_time
        names = sorted(terms)
        packed = torch.tensor(
            [terms[k] for k in names] + [float(out_of_time)], dtype=torch.float64, device=self.rt.device
        )
        summed = distributed.all_reduce_sum(packed).tolist()
        return {k: v / self.rt.world_size for k, v in zip(names, summed)}, summed[-1] > 0

    def end_of_step(self, terms: dict[str, float], last_step: bool, log: TextIO, bar: tqdm) -> None:
        """Rank 0, after each step: validate (``best.pt`` on a new best), log, save ``last.pt``, each when
        its ``--*-every`` says or at the last step."""
        cfg, step = self.cfg, self.step
        row = {"step": step, "epoch": self.epoch, **terms}
        if step % cfg.val_every == 0 or last_step:
            row.update(validate(self.model, cfg, self.val_set, self.rt.device))
            if row.get("val_total", float("inf")) < self.best:
                self.best = row["val_total"]
                self.metrics.update({k: v for k, v in row.items() if k.startswith("val_")})
                self.metrics["best_val_total"] = self.best
                self.metrics["best_step"] = step
                self._save("best.pt")
        if step % cfg.log_every == 0 or "val_total" in row:
            row["elapsed_s"] = round(time.perf_counter() - self.started, 2)
            if self.rt.device.type == "cuda":
                row["cuda_max_mem_gb"] = round(torch.cuda.max_memory_allocated(self.rt.device) / 2**30, 2)
            log.write(json.dumps(row) + "\n")
            log.flush()
            bar.set_postfix({k: f"{v:.4f}" for k, v in terms.items()})
        if step % cfg.save_every == 0 or last_step:
            self._save("last.pt")

    def _save(self, name: str) -> None:
        save_checkpoint(self.out_dir / name, self.model, self.optimizer, self.step, self.cfg, self.metrics, self.scaler)


def main(argv=None) -> int:
    cfg = config_from_args(argv)
    try:
        result = train(cfg)
    except GeoNetError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    if distributed.is_main_process():
        print(f"done: step {result['step']}, checkpoint {result['last']}, log {result['log']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Device choice and data-parallel training under ``torchrun`` (DDP).

``torchrun --nproc_per_node N -m training.train ...`` sets RANK, LOCAL_RANK and
WORLD_SIZE; :func:`setup` then joins the process group (``gloo`` on CPU, ``nccl`` on
GPU). Each rank trains on its own shard of every batch, so the effective batch is
``--batch-size`` x WORLD_SIZE. Without torchrun everything here is a no-op.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass

import torch
import torch.distributed as dist

from geonet_infer.errors import GeoNetError, InputError
from training.networks import BatchNormNoScale

DEVICE_HINT = "use --device auto, cpu, cuda or cuda:N"


@dataclass(frozen=True)
class Runtime:
    device: torch.device
    rank: int = 0
    world_size: int = 1
    owns_group: bool = False  # this process created the process group (and must destroy it)

    @property
    def distributed(self) -> bool:
        return self.world_size > 1

    @property
    def is_main(self) -> bool:
        return self.rank == 0


def _no_cuda() -> GeoNetError:
    why = "this torch build has no CUDA" if torch.version.cuda is None else "no CUDA device is visible"
    return InputError(None, f"--device cuda: {why}", "use --device cpu (or auto)")


def resolve_device(spec: str, local_rank: int | None = None) -> torch.device:
    """``auto|cpu|cuda|cuda:N`` -> a torch.device that exists here; GeoNetError otherwise.

    Under torchrun (``local_rank`` given) ``cuda``/``auto`` mean this rank's GPU.
    """
    if spec not in ("auto", "cpu", "cuda") and not re.fullmatch(r"cuda:\d+", spec):
        raise InputError(None, f"--device {spec!r} is not a device", DEVICE_HINT)
    if spec == "cpu" or (spec == "auto" and not torch.cuda.is_available()):
        return torch.device("cpu")
    if not torch.cuda.is_available():
        raise _no_cuda()
    if spec.startswith("cuda:"):
        index = int(spec.split(":")[1])
        if local_rank is not None:
            raise InputError(
                None, f"--device {spec} under torchrun", "pass --device cuda: each rank takes the GPU of its LOCAL_RANK"
            )
        if index >= torch.cuda.device_count():
            raise InputError(None, f"--device {spec}: only {torch.cuda.device_count()} CUDA device(s)", DEVICE_HINT)
        return torch.device(spec)
    return torch.device("cuda", local_rank or 0)


def setup(device_spec: str) -> Runtime:
    """Pick the device; join the torchrun process group when WORLD_SIZE > 1."""
    world_size = int(os.environ.get("WORLD_SIZE", "1"))
    if world_size <= 1:
        return Runtime(resolve_device(device_spec))
    local_rank = int(os.environ["LOCAL_RANK"])
    device = resolve_device(device_spec, local_rank)
    owns = not dist.is_initialized()
    if owns:
        if device.type == "cuda":
            torch.cuda.set_device(device)
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo")
    return Runtime(device, dist.get_rank(), dist.get_world_size(), owns)


def teardown(rt: Runtime, clean: bool = True) -> None:
    """Leave the process group this process joined; ``clean=False`` after an error skips the
    barrier (the other ranks may never reach it)."""
    if rt.owns_group and dist.is_initialized():
        if clean:
            dist.barrier()  # nobody leaves while rank 0 still writes its last checkpoint
        dist.destroy_process_group()


def is_main_process() -> bool:
    """Rank 0, or not launched by torchrun (also after the group is gone)."""
    return int(os.environ.get("RANK", "0")) == 0


def all_reduce_sum(values: torch.Tensor) -> torch.Tensor:
    """Sum over ranks (a copy; identity when not distributed)."""
    out = values.clone()
    if dist.is_initialized() and dist.get_world_size() > 1:
        dist.all_reduce(out)
    return out


# --------------------------------------------------------------------- SyncBatchNorm
class _AllReduceSum(torch.autograd.Function):
    """Differentiable all-reduce: the gradient of a sum over ranks is the sum of gradients."""

    @staticmethod
    def forward(ctx, x):
        return all_reduce_sum(x)

    @staticmethod
    def backward(ctx, grad):
        return all_reduce_sum(grad)


class SyncBatchNormNoScale(BatchNormNoScale):
    """BatchNormNoScale whose training statistics cover every rank's batch.

    Written here because ``nn.SyncBatchNorm`` runs on GPUs only and its conversion drops
    our beta-only parameter; this one works on gloo (CPU) and nccl alike. Same state_dict
    keys as BatchNormNoScale, so checkpoints do not depend on the option. Two passes
    (mean, then squared deviations) keep the variance as exact as F.batch_norm's.
    """

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if not (self.training and dist.is_initialized() and dist.get_world_size() > 1):
            return super().forward(x)
        dims = (0, 2, 3)
        dtype, x = x.dtype, x.float()  # statistics in float32 under autocast too
        local_count = torch.full((1,), x.numel() / x.shape[1], device=x.device)
        totals = _AllReduceSum.apply(torch.cat([x.sum(dims), local_count]))  # one collective
        count = totals[-1:].detach()
        mean = totals[:-1] / count
        centred = x - mean[None, :, None, None]
        var = _AllReduceSum.apply((centred * centred).sum(dims)) / count
        with torch.no_grad():  # running statistics as nn.BatchNorm2d keeps them (unbiased var)
            self.num_batches_tracked.add_(1)
            self.running_mean.lerp_(mean.detach(), self.momentum)
            self.running_var.lerp_(var.detach() * count / (count - 1), self.momentum)
        out = centred * torch.rsqrt(var + self.eps)[None, :, None, None] + self.bias[None, :, None, None]
        return out.to(dtype)


def convert_sync_bn(module: torch.nn.Module) -> torch.nn.Module:
    """Swap every BatchNormNoScale for a SyncBatchNormNoScale in place (same parameters)."""
    for child in module.children():
        if type(child) is BatchNormNoScale:
            child.__class__ = SyncBatchNormNoScale  # same attributes, only forward differs
        else:
            convert_sync_bn(child)
    return module

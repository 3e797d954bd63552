"""Data-parallel training under torchrun on the CPU (gloo): two ranks of batch 2 take the
same step as one process of batch 4, and a DDP run resumes bit for bit.

BatchNorm: the nets train with batch statistics, so the ranks run with ``--sync-bn``
(statistics over all ranks); without it the two-rank gradient is off by O(1) (measured
1.4 relative). Tolerances: this loss's float32 gradient at initialisation is only good to
about 2e-3 relative (one process vs a float64 run of the same batch differed by 1.9e-3;
summation order moves it), and here the two-rank gradient is 4e-4 from the one-process
one, so gradients are compared at 1e-2. Adam's first step moves each weight by about
lr * sign(gradient), so a weight whose gradient is within that rounding of zero may step
the other way: 0.2-0.4 % of weights did; at most 2 % may (without --sync-bn: 27 %).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from training.checkpoint import build_model, load_checkpoint
from training.config import TrainConfig
from training.train import seed_everything, train

REPO = Path(__file__).resolve().parents[2]
H, W = 32, 96
COMMON = dict(
    arch="small", height=H, width=W, num_workers=0, log_every=1, val_every=1000, val_batches=1, save_every=1000, seed=3
)


def cli_args(**kw) -> list[str]:
    args = []
    for key, value in {**COMMON, **kw}.items():
        flag = "--" + key.replace("_", "-")
        args += [flag] if value is True else [flag, str(value)]
    return args


def torchrun(out_dir: Path, data_dir: Path, **kw) -> Path:
    """``torchrun --nproc_per_node 2 -m training.train ...`` with batch 2 per rank."""
    cmd = [
        sys.executable,
        "-m",
        "torch.distributed.run",
        "--standalone",
        "--nproc_per_node",
        "2",
        "-m",
        "training.train",
        *cli_args(data_dir=data_dir, out_dir=out_dir, batch_size=2, sync_bn=True, **kw),
    ]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "2 process(es) x batch 2 = effective batch 4" in proc.stdout
    return out_dir / "last.pt"


@pytest.fixture(scope="module")
def data(synth_prepared) -> Path:
    root = synth_prepared.parent
    n_train = len((root / "prepared" / "train.txt").read_text().split("\n")) - 1
    # 9 samples: 4 per rank, 2 steps per epoch, so a 4-step run crosses an epoch
    assert n_train // 2 // 2 == 2, n_train
    return root / "prepared"


@pytest.fixture(scope="module")
def one_ddp_step(data, tmp_path_factory) -> Path:
    return torchrun(tmp_path_factory.mktemp("ddp_1step"), data, max_steps=1)


def read_log(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()]


def trained_weights(state: dict) -> list[str]:
    return [k for k, v in state.items() if v.is_floating_point() and "running_" not in k]


def test_two_ranks_of_batch_2_step_like_one_rank_of_batch_4(data, one_ddp_step, tmp_path):
    cfg = TrainConfig(**COMMON, data_dir=str(data), out_dir=str(tmp_path), batch_size=4, max_steps=1)
    single = train(cfg, progress=False)
    ddp, one = load_checkpoint(one_ddp_step), load_checkpoint(single["last"])

    loss_ddp = read_log(one_ddp_step.parent / "log.jsonl")[0]["total"]  # mean over the ranks
    loss_one = read_log(single["log"])[0]["total"]
    assert loss_ddp == pytest.approx(loss_one, rel=1e-5)

    # After one Adam step the first moment is (1 - beta1) * gradient: the averaged gradient.
    grad = {
        name: torch.cat([s["exp_avg"].flatten() for s in c["optimizer"]["state"].values()])
        for name, c in (("ddp", ddp), ("one", one))
    }
    rel = ((grad["ddp"] - grad["one"]).norm() / grad["one"].norm()).item()
    print(f"gradient: two ranks vs one, relative difference {rel:.2e}")
    assert rel < 1e-2

    seed_everything(cfg.seed)
    init = build_model(cfg).state_dict()
    names = trained_weights(init)
    step = {
        name: torch.cat([(c["model"][k] - init[k]).flatten() for k in names])
        for name, c in (("ddp", ddp), ("one", one))
    }
    assert step["one"].abs().max() > 0.5 * cfg.lr  # the weights did move
    differing = ((step["ddp"] - step["one"]).abs() > 1e-3 * cfg.lr).float().mean().item()
    print(f"parameter update: {differing:.3%} of weights differ by more than lr/1000")
    assert differing < 0.02


def test_ddp_run_resumes_bit_for_bit(data, one_ddp_step, tmp_path):
    # Resume after step 1 (mid-epoch: the sampler must skip one batch), then cross into epoch 1.
    straight = torchrun(tmp_path / "straight", data, max_steps=4)
    shutil.copytree(one_ddp_step.parent, tmp_path / "resumed")
    resumed = torchrun(tmp_path / "resumed", data, max_steps=4, resume=tmp_path / "resumed" / "last.pt")
    a, b = load_checkpoint(straight), load_checkpoint(resumed)
    assert a["step"] == b["step"] == 4
    for key in a["model"]:
        assert torch.equal(a["model"][key], b["model"][key]), key
    log_a, log_b = read_log(straight.parent / "log.jsonl"), read_log(resumed.parent / "log.jsonl")
    assert [r["epoch"] for r in log_a] == [0, 0, 1, 1]
    assert log_a[-1]["total"] == log_b[-1]["total"]

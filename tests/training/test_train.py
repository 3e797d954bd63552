"""Trainer: the photometric loss falls on real frames, resume is exact, checkpoints are
weights only, devices and bad input are named."""

import io
import json
import math
import random
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from geonet_infer.errors import GeoNetError
from tests.conftest import require_realdata
from training import checkpoint, prepare
from training.checkpoint import (
    build_model,
    load_checkpoint,
    model_from_checkpoint,
    rng_state,
    save_checkpoint,
    set_rng_state,
)
from training.config import TrainConfig, config_from_args
from training.losses import LossWeights
from training.train import check_options, main, train

H, W = 64, 208  # CI-sized real frames: a quarter of the 128x416 pixels
SH, SW = 32, 96  # synthetic frames: only the mechanics are under test


@pytest.fixture(scope="module")
def kitti_prepared(tmp_path_factory):
    src = require_realdata("kitti_raw_2011_09_26_sfnd")
    out = tmp_path_factory.mktemp("prepared")
    prepare.main(
        [
            "--kind",
            "kitti_raw",
            "--src",
            str(src),
            "--out",
            str(out),
            "--split",
            "none",
            "--height",
            str(H),
            "--width",
            str(W),
            "--max-frames",
            "14",
            "--workers",
            "1",
            "--val-fraction",
            "0.2",
        ]
    )
    assert (out / "train.txt").is_file()
    return out


def config(data_dir, out_dir, **overrides) -> TrainConfig:
    """Synthetic-sized by default; real-frame tests pass height=H, width=W."""
    base = dict(
        stage="rigid",
        arch="small",
        data_dir=str(data_dir),
        out_dir=str(out_dir),
        height=SH,
        width=SW,
        batch_size=2,
        num_workers=0,
        augment=False,
        log_every=1,
        save_every=1000,
        val_every=1000,
        val_batches=2,
        seed=3,
    )
    base.update(overrides)
    return TrainConfig(**base)


def read_log(path):
    return [json.loads(line) for line in Path(path).read_text().splitlines()]


def test_photometric_loss_falls_on_real_frames(kitti_prepared, tmp_path):
    # bn_momentum 0.1: a 40-step run is far too short for the official 0.001.
    result = train(
        config(kitti_prepared, tmp_path, max_steps=40, lr=1e-3, bn_momentum=0.1, height=H, width=W), progress=False
    )
    rows = read_log(result["log"])
    first = sum(r["rigid_warp"] for r in rows[:5]) / 5
    last = sum(r["rigid_warp"] for r in rows[-5:]) / 5
    print(f"rigid_warp loss: first 5 steps {first:.4f}, last 5 steps {last:.4f}, drop {1 - last / first:.1%}")
    assert last < 0.9 * first, (first, last)
    assert {"rigid_warp", "disp_smooth", "total", "val_total"} <= set(rows[-1])


def test_resume_continues_bit_for_bit(synth_prepared, tmp_path):
    straight = train(config(synth_prepared, tmp_path / "a", max_steps=6, augment=True), progress=False)
    train(config(synth_prepared, tmp_path / "b", max_steps=3, save_every=3, augment=True), progress=False)
    resumed = train(
        config(synth_prepared, tmp_path / "b", max_steps=6, augment=True, resume=str(tmp_path / "b" / "last.pt")),
        progress=False,
    )
    a = load_checkpoint(straight["last"])["model"]
    b = load_checkpoint(resumed["last"])["model"]
    assert a.keys() == b.keys()
    for key in a:
        assert torch.equal(a[key], b[key]), key
    assert read_log(straight["log"])[-1]["total"] == read_log(resumed["log"])[-1]["total"]


def test_flow_stage_freezes_rigid_nets(synth_prepared, tmp_path):
    rigid = train(config(synth_prepared, tmp_path / "rigid", max_steps=2), progress=False)
    flow = train(
        config(synth_prepared, tmp_path / "flow", stage="flow", max_steps=3, init_checkpoint=str(rigid["last"])),
        progress=False,
    )
    before = load_checkpoint(rigid["last"])["model"]
    after = load_checkpoint(flow["last"], expect_stage="flow")["model"]
    for key, value in before.items():  # weights and BN running stats untouched
        assert torch.equal(value, after[key]), key
    assert any(k.startswith("flow_net.") for k in after)
    rows = read_log(flow["log"])
    assert {"flow_warp", "flow_smooth", "flow_consistency"} <= set(rows[-1])
    assert model_from_checkpoint(load_checkpoint(flow["last"])).flow_net is not None


def test_freeze_depth_trains_posenet_alone(synth_prepared, tmp_path):
    """--freeze-depth (issue 53): stage rigid leaves DepthNet's weights and batch-norm statistics as
    initialised. With --pose-keep and --pose-keep-shape (rounds 6-8) and --pose-steady (round 10) beside
    it: both pulls toward the starting PoseNet and the step spread are logged, and the frozen copy the
    pulls are measured against never reaches the checkpoint; either pull alone is refused without
    --init-checkpoint or with --resume."""
    first = train(config(synth_prepared, tmp_path / "a", max_steps=1), progress=False)
    keep = LossWeights(pose_keep=1.0, pose_keep_shape=1.0, pose_steady=1.0)
    init = str(first["last"])
    frozen = train(
        config(synth_prepared, tmp_path / "b", max_steps=2, freeze_depth=True, init_checkpoint=init, weights=keep),
        progress=False,
    )
    before = load_checkpoint(first["last"])["model"]
    after = load_checkpoint(frozen["last"])["model"]
    assert set(after) == set(before)
    depth = [k for k in before if k.startswith("depth_net.")]
    assert depth and all(torch.equal(before[k], after[k]) for k in depth)
    pose = [k for k in before if k.startswith("pose_net.") and before[k].dim() == 4]
    assert any(not torch.equal(before[k], after[k]) for k in pose)
    rows = read_log(frozen["log"])
    for term in ("pose_keep", "pose_keep_shape", "pose_steady"):
        assert all(math.isfinite(r[term]) and r[term] >= 0 for r in rows if "val_total" not in r)
    shape_only = LossWeights(pose_keep_shape=1.0)
    assert cfg_refused(config(synth_prepared, tmp_path / "c", weights=keep, resume=init))
    assert cfg_refused(config(synth_prepared, tmp_path / "d", weights=keep))
    assert cfg_refused(config(synth_prepared, tmp_path / "e", weights=shape_only))


def cfg_refused(cfg: TrainConfig) -> bool:
    try:
        check_options(cfg, torch.device("cpu"))
    except GeoNetError:
        return True
    return False


def test_init_checkpoint_fine_tunes_from_a_checkpoint_or_a_weights_file(synth_prepared, tmp_path):
    """--init-checkpoint starts from given weights with a fresh optimizer (lr 0: weights stay put)."""
    from training.checkpoint import WEIGHTS_FORMAT, load_checkpoint, save_weights

    rigid = train(config(synth_prepared, tmp_path / "rigid", max_steps=1), progress=False)
    flow = train(
        config(synth_prepared, tmp_path / "flow", stage="flow", max_steps=1, init_checkpoint=str(rigid["last"])),
        progress=False,
    )
    published = tmp_path / "weights.pt"
    save_weights(load_checkpoint(flow["last"]), published)
    assert torch.load(published, weights_only=True)["format"] == WEIGHTS_FORMAT
    source = load_checkpoint(flow["last"])["model"]

    def convs(state, prefix):
        return {k: v for k, v in state.items() if k.startswith(prefix) and v.dim() == 4}

    # stage rigid from the weights file: DepthNet/PoseNet start at the published (float16-stored) kernels
    tuned = train(
        config(synth_prepared, tmp_path / "tune", max_steps=1, lr=0.0, init_checkpoint=str(published)),
        progress=False,
    )
    after = load_checkpoint(tuned["last"])
    assert after["step"] == 1 and not any(k.startswith("flow_net.") for k in after["model"])
    for k, v in convs(source, "depth_net.").items():
        torch.testing.assert_close(after["model"][k], v, rtol=1e-3, atol=1e-4)
    # stage flow from a flow checkpoint: its ResFlowNet is fine-tuned, not re-initialised
    tuned_flow = train(
        config(
            synth_prepared, tmp_path / "tune_flow", stage="flow", max_steps=1, lr=0.0, init_checkpoint=str(flow["last"])
        ),
        progress=False,
    )
    after_flow = load_checkpoint(tuned_flow["last"])["model"]
    for k, v in convs(source, "flow_net.").items():
        assert torch.equal(after_flow[k], v), k


def test_interpolate_puts_a_fine_tuned_model_between_its_base_and_itself(synth_prepared, tmp_path):
    """--interpolate BASE TUNED 0.25 OUT: every float tensor is 0.75 * base + 0.25 * tuned."""
    from training.checkpoint import load_checkpoint, load_weights
    from training.checkpoint import main as checkpoint_main

    base = train(config(synth_prepared, tmp_path / "base", max_steps=1), progress=False)
    tuned = train(
        config(synth_prepared, tmp_path / "tuned", max_steps=3, lr=1e-2, init_checkpoint=str(base["last"])),
        progress=False,
    )
    out = tmp_path / "mix.pt"
    assert checkpoint_main(["--interpolate", str(base["last"]), str(tuned["last"]), "0.25", str(out)]) == 0
    a, b = load_checkpoint(base["last"])["model"], load_checkpoint(tuned["last"])["model"]
    mixed = load_weights(out)
    assert mixed["source"]["alpha"] == 0.25 and mixed["stage"] == "rigid"
    moved = 0
    for key, value in mixed["model"].items():
        if not value.is_floating_point():
            assert torch.equal(value, b[key]), key  # BN counters come from the tuned model
            continue
        expected = 0.75 * a[key] + 0.25 * b[key]
        tol = 2e-3 if value.dim() == 4 else 1e-6  # conv kernels are stored as float16
        torch.testing.assert_close(value, expected, rtol=tol, atol=tol * 1e-2, msg=key)
        moved += int(not torch.equal(a[key], b[key]))
    assert moved > 10  # the fine-tuning did change the weights, so the check above means something
    assert checkpoint_main(["--interpolate", str(base["last"]), str(tuned["last"]), "1.5", str(out)]) == 2


def test_init_checkpoint_of_another_arch_is_refused(synth_prepared, tmp_path):
    rigid = train(config(synth_prepared, tmp_path / "rigid", max_steps=1), progress=False)
    with pytest.raises(GeoNetError, match="arch is 'small', expected 'vgg'") as err:
        train(
            config(synth_prepared, tmp_path / "x", arch="vgg", max_steps=1, init_checkpoint=str(rigid["last"])),
            progress=False,
        )
    assert str(rigid["last"]) in str(err.value)


def test_missing_data_dir_is_a_clear_error(tmp_path, capsys):
    code = main(
        [
            "--data-dir",
            str(tmp_path / "nowhere"),
            "--out-dir",
            str(tmp_path / "run"),
            "--arch",
            "small",
            "--max-steps",
            "1",
        ]
    )
    assert code == 2
    message = capsys.readouterr().err
    assert str(tmp_path / "nowhere") in message and "training.prepare" in message


def test_empty_split_is_a_clear_error(tmp_path):
    (tmp_path / "train.txt").write_text("")
    with pytest.raises(GeoNetError, match="train.txt"):
        train(config(tmp_path, tmp_path / "run", max_steps=1), progress=False)


def test_corrupt_image_is_named(synth_prepared, tmp_path):
    data = tmp_path / "data"
    shutil.copytree(synth_prepared, data)
    folder, frame = (data / "train.txt").read_text().split()[:2]
    victim = data / folder / f"{frame}.jpg"
    victim.write_bytes(b"not a jpeg")
    (data / "train.txt").write_text(f"{folder} {frame}\n" * 4)
    with pytest.raises(GeoNetError) as err:
        train(config(data, tmp_path / "run", max_steps=1), progress=False)
    assert str(victim) in str(err.value)


def test_mask_out_of_view_drops_border_errors_from_the_rigid_loss():
    """--mask-out-of-view reaches the model, which then ignores pixels warped from outside."""
    flow = torch.zeros(1, 2, 4, 6)
    flow[:, 0] = 1.0  # the last column samples past the right edge
    error = torch.ones(1, 3, 4, 6)
    error[..., -1] = 100.0
    masked = build_model(config_from_args(["--arch", "small", "--mask-out-of-view"]))
    official = build_model(config_from_args(["--arch", "small"]))
    assert masked._photometric_mean(error, flow).item() == pytest.approx(1.0)
    assert official._photometric_mean(error, flow).item() == pytest.approx((5 + 100) / 6)


def test_automask_drops_pixels_the_unwarped_source_explains_better():
    flow = torch.zeros(1, 2, 4, 6)
    error = torch.ones(1, 3, 4, 6)
    error[..., 0] = 5.0  # the warp is worse than no warp in column 0 (e.g. a car moving with us)
    identity_error = torch.full((1, 3, 4, 6), 3.0)
    model = build_model(config_from_args(["--arch", "small", "--automask"]))
    assert model._photometric_mean(error, flow, identity_error).item() == pytest.approx(1.0)


# ------------------------------------------------------------------ checkpoints
def small_checkpoint(path: Path) -> Path:
    cfg = TrainConfig(arch="small", height=SH, width=SW)
    model = build_model(cfg)
    save_checkpoint(path, model, torch.optim.Adam(model.parameters()), 7, cfg, {})
    return path


def test_checkpoint_loads_weights_only_and_rebuilds_the_model(tmp_path):
    ckpt = load_checkpoint(small_checkpoint(tmp_path / "c.pt"))
    assert ckpt["step"] == 7
    # torch's own weights-only loader accepts the file: no pickled Python objects inside
    torch.load(tmp_path / "c.pt", weights_only=True)
    model = model_from_checkpoint(ckpt)
    assert all(torch.equal(v, model.state_dict()[k]) for k, v in ckpt["model"].items())


def test_a_checkpoint_that_runs_code_is_refused_and_the_code_never_runs(tmp_path):
    marker = tmp_path / "code-ran"

    class Payload:  # unpickling this calls open(marker, "w"), which creates the file
        def __reduce__(self):
            return (open, (str(marker), "w"))

    path = tmp_path / "evil.pt"
    torch.save({"format": "geonet-checkpoint-v2", "model": Payload()}, path)
    with pytest.raises(GeoNetError, match="refused") as err:
        load_checkpoint(path)
    assert str(path) in str(err.value) and "\n" not in str(err.value)
    assert not marker.exists()


@pytest.mark.parametrize(
    "content, problem",
    [
        (torch.zeros(3), "holds a Tensor"),
        ({"state_dict": {"w": torch.zeros(1)}}, "keys ['state_dict']"),
        ({"format": "geonet-checkpoint-v2", "model": {}}, "lacks stage"),
    ],
)
def test_a_checkpoint_that_is_not_ours_is_named(tmp_path, content, problem):
    path = tmp_path / "other.pt"
    torch.save(content, path)
    with pytest.raises(GeoNetError, match="not a|lacks") as err:
        load_checkpoint(path)
    assert str(path) in str(err.value) and problem in str(err.value)


def test_an_old_checkpoint_is_refused_with_the_upgrade_command_and_upgrades(tmp_path):
    path = small_checkpoint(tmp_path / "v1.pt")
    old = torch.load(path, weights_only=True)
    np_state = np.random.RandomState(5).get_state()
    old.update(
        format="geonet-checkpoint-v1",  # v1 pickled numpy's RNG state as is
        rng={"torch": torch.get_rng_state(), "numpy": np_state, "python": random.Random(5).getstate()},
    )
    del old["grad_scaler"]
    torch.save(old, path)
    with pytest.raises(GeoNetError, match=r"numpy.*--upgrade"):
        load_checkpoint(path)
    assert checkpoint.main(["--upgrade", str(path)]) == 0
    new = load_checkpoint(path)
    assert np.array_equal(new["rng"]["numpy"]["keys"].numpy(), np_state[1])
    assert all(torch.equal(v, new["model"][k]) for k, v in old["model"].items())


def test_rng_states_round_trip_as_tensors():
    buffer = io.BytesIO()
    torch.save(rng_state(), buffer)
    expected = (torch.rand(3), np.random.rand(3), random.random())
    buffer.seek(0)
    set_rng_state(torch.load(buffer, weights_only=True))  # tensors and plain values only
    again = (torch.rand(3), np.random.rand(3), random.random())
    assert torch.equal(expected[0], again[0])
    assert np.array_equal(expected[1], again[1]) and expected[2] == again[2]


# ------------------------------------------------------------------ devices
def test_device_cuda_without_cuda_is_a_clear_error(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)  # also on a machine that has one
    code = main(["--device", "cuda", "--data-dir", str(tmp_path), "--out-dir", str(tmp_path / "run")])
    assert code == 2
    message = capsys.readouterr().err
    assert message.startswith("error: --device cuda:") and "--device cpu" in message
    assert message.count("\n") == 1 and "Traceback" not in message


@pytest.mark.parametrize(
    "argv, problem",
    [
        (["--device", "gpu"], "--device 'gpu' is not a device"),
        (["--amp", "fp16", "--device", "cpu"], "--amp fp16 needs a CUDA device"),
    ],
)
def test_bad_device_options_are_clear_errors(tmp_path, capsys, argv, problem):
    assert main([*argv, "--data-dir", str(tmp_path), "--out-dir", str(tmp_path / "run")]) == 2
    assert problem in capsys.readouterr().err


def test_bf16_autocast_trains_and_keeps_float32_weights(synth_prepared, tmp_path):
    result = train(config(synth_prepared, tmp_path, max_steps=2, amp="bf16"), progress=False)
    ckpt = load_checkpoint(result["last"])
    assert all(v.dtype == torch.float32 for v in ckpt["model"].values() if v.is_floating_point())
    assert all(np.isfinite(r["total"]) for r in read_log(result["log"]))


# ------------------------------------------------------------------ scale_normalize
def test_scale_normalize_divides_each_disparity_map_by_its_mean():
    cfg = config_from_args(["--arch", "small", "--scale-normalize"])
    normalized = build_model(cfg).train()
    assert normalized.scale_normalize
    plain = build_model(config_from_args(["--arch", "small"])).train()
    plain.load_state_dict(normalized.state_dict())
    g = torch.Generator().manual_seed(0)
    target, sources = torch.rand(2, 3, SH, SW, generator=g), torch.rand(2, 2, 3, SH, SW, generator=g)
    K = torch.tensor([[40.0, 0, SW / 2], [0, 40.0, SH / 2], [0, 0, 1]]).expand(2, 3, 3)
    with torch.no_grad():
        out_n, _, _ = normalized.rigid_forward(target, sources, K)
        out_p, _, _ = plain.rigid_forward(target, sources, K)
    for d_n, d_p in zip(out_n.disp, out_p.disp):  # every scale, every image (target and sources)
        assert d_n.shape[0] == 6
        torch.testing.assert_close(d_n.mean(dim=(1, 2, 3)), torch.ones(6))
        torch.testing.assert_close(d_n * d_p.mean(dim=(1, 2, 3), keepdim=True), d_p)


def prepare_with_truth(synth_prepared, out, **truth):
    """The fixture's synthetic sequences prepared again with ground truth for the train samples
    (train_depth, train_flow or train_pose)."""
    prepare.prepare(
        prepare.PrepareConfig(
            kind="synth",
            src=synth_prepared.parent / "synth",
            out=out,
            height=SH,
            width=SW,
            heldout=0,
            val_fraction=0.2,
            **truth,
        )
    )
    return out


def assert_falls(rows, key):
    """The mean of ``key`` over the last 5 logged steps is below 0.8x that of the first 5."""
    first = sum(r[key] for r in rows[:5]) / 5
    last = sum(r[key] for r in rows[-5:]) / 5
    print(f"{key}: first 5 steps {first:.4f}, last 5 steps {last:.4f}")
    assert last < 0.8 * first, (first, last)


@pytest.mark.parametrize("truth", ["depth", "pose"])
def test_rigid_supervision_learns_synthetic_truth(synth_prepared, tmp_path, truth):
    """--depth-supervision / --pose-supervision on data prepared with --train-depth / --train-pose:
    the scale-invariant depth error / the scale-aligned pose error is logged and falls; the flag is
    off by default (the official loss)."""
    supervised = prepare_with_truth(synth_prepared, tmp_path / "prepared", **{f"train_{truth}": True})
    assert list(supervised.rglob(f"*_{truth}.*"))
    cfg = config_from_args(["--data-dir", str(supervised), f"--{truth}-supervision", "2.5"])
    weight = f"{truth}_supervision"
    assert getattr(cfg.weights, weight) == 2.5 and getattr(config_from_args([]).weights, weight) == 0.0
    # mixed with a folder without ground truth (as real footage is): those samples add no term
    result = train(
        config(
            supervised,
            tmp_path / "run",
            max_steps=30,
            lr=1e-3,
            bn_momentum=0.1,
            weights=cfg.weights,
            extra_data_dirs=[str(synth_prepared)],
        ),
        progress=False,
    )
    rows = read_log(result["log"])
    assert_falls(rows, f"{truth}_supervised")
    assert f"val_{truth}_supervised" in rows[-1]
    plain = train(config(synth_prepared, tmp_path / "plain", max_steps=1), progress=False)
    assert f"{truth}_supervised" not in read_log(plain["log"])[-1]


def test_pose_speed_is_a_logged_term_off_by_default(synth_prepared, tmp_path):
    """--pose-speed (issue 53, round 4) beside --pose-supervision: its term is logged, finite and
    non-negative; off by default, and absent from the log then."""
    supervised = prepare_with_truth(synth_prepared, tmp_path / "prepared", train_pose=True)
    cfg = config_from_args(["--data-dir", str(supervised), "--pose-supervision", "1", "--pose-speed", "3"])
    assert cfg.weights.pose_speed == 3.0 and config_from_args([]).weights.pose_speed == 0.0
    result = train(config(supervised, tmp_path / "run", max_steps=4, weights=cfg.weights), progress=False)
    rows = read_log(result["log"])
    assert all(math.isfinite(r["pose_speed"]) and r["pose_speed"] >= 0 for r in rows if "pose_speed" in r)
    assert any("pose_speed" in r for r in rows)
    plain = LossWeights(pose_supervision=1.0)
    result = train(config(supervised, tmp_path / "plain", max_steps=1, weights=plain), progress=False)
    assert "pose_speed" not in read_log(result["log"])[-1]


def test_flow_supervision_learns_synthetic_flow(synth_prepared, tmp_path):
    """--flow-supervision on data prepared with --train-flow: the end-point error against the
    generator's flow is logged and falls; the flag is off by default (the official loss)."""
    supervised = prepare_with_truth(synth_prepared, tmp_path / "prepared", train_flow=True)
    cfg = config_from_args(["--data-dir", str(supervised), "--stage", "flow", "--flow-supervision", "0.5"])
    assert cfg.weights.flow_supervision == 0.5 and config_from_args([]).weights.flow_supervision == 0.0
    rigid = train(config(synth_prepared, tmp_path / "rigid", max_steps=1), progress=False)
    result = train(
        config(
            supervised,
            tmp_path / "flow",
            stage="flow",
            max_steps=30,
            lr=1e-3,
            bn_momentum=0.1,
            weights=cfg.weights,
            init_checkpoint=str(rigid["last"]),
            extra_data_dirs=[str(synth_prepared)],  # samples without flow add no supervised term
        ),
        progress=False,
    )
    rows = read_log(result["log"])
    assert_falls(rows, "flow_supervised")
    assert "val_flow_supervised" in rows[-1]
    plain = train(
        config(synth_prepared, tmp_path / "plain", stage="flow", max_steps=1, init_checkpoint=str(rigid["last"])),
        progress=False,
    )
    assert "flow_supervised" not in read_log(plain["log"])[-1]


def test_photometric_scores_unlabelled_footage(synth_prepared, tmp_path):
    """training.photometric: the warp error of consecutive frames is lower than of a copy of the
    folder whose source frames are noise (the loss really reads the footage), one row per model."""
    from training.photometric import main as photometric_main
    from training.photometric import photometric_terms

    rigid = train(config(synth_prepared, tmp_path / "rigid", max_steps=1), progress=False)
    flow = train(
        config(synth_prepared, tmp_path / "flow", stage="flow", max_steps=1, init_checkpoint=str(rigid["last"])),
        progress=False,
    )
    noise = tmp_path / "noise"
    shutil.copytree(synth_prepared, noise)
    rng = np.random.default_rng(0)
    for jpg in noise.glob("*/*.jpg"):
        strip = cv2.imread(str(jpg))
        w = strip.shape[1] // 3
        strip[:, :w] = rng.integers(0, 256, size=strip[:, :w].shape, dtype=np.uint8)  # source t-1
        strip[:, 2 * w :] = rng.integers(0, 256, size=strip[:, 2 * w :].shape, dtype=np.uint8)  # source t+1
        cv2.imwrite(str(jpg), strip)
    real = photometric_terms(flow["last"], synth_prepared)
    scrambled = photometric_terms(flow["last"], noise)
    n_samples = sum(len((synth_prepared / f"{split}.txt").read_text().split()) // 2 for split in ("train", "val"))
    assert real["stage"] == "flow" and real["samples"] == n_samples
    assert real["terms"]["flow_warp"] < 0.8 * scrambled["terms"]["flow_warp"], (real, scrambled)
    rigid_terms = photometric_terms(rigid["last"], synth_prepared)
    assert rigid_terms["stage"] == "rigid" and "rigid_warp" in rigid_terms["terms"]
    with pytest.raises(GeoNetError, match="no ResFlowNet"):
        photometric_terms(rigid["last"], synth_prepared, stage="flow")
    assert photometric_main(["--checkpoint", str(flow["last"]), str(flow["last"]), "--data-dir", str(noise)]) == 0


def test_extra_data_dirs_are_shuffled_into_one_training_set(synth_prepared, tmp_path):
    from training.data import SequenceDataset
    from training.train import TrainSet

    assert config_from_args(["--extra-data-dir", "a", "--extra-data-dir", "b"]).extra_data_dirs == ["a", "b"]
    other = tmp_path / "other"
    shutil.copytree(synth_prepared, other)
    sets = [SequenceDataset(root, "train", height=SH, width=SW, augment=True) for root in (synth_prepared, other)]
    mixed = TrainSet(sets)
    assert len(mixed) == 2 * len(sets[0])
    mixed.set_epoch(4)
    assert [d.epoch for d in sets] == [4, 4]
    # an unreadable sample of the extra folder is named: the folder really is read
    for name in sets[1].names:
        folder, frame = name.split(" ")
        (other / folder / f"{frame}.jpg").write_bytes(b"not a jpeg")
    with pytest.raises(GeoNetError, match="other"):
        train(config(synth_prepared, tmp_path / "run", max_steps=4, extra_data_dirs=[str(other)]), progress=False)


class _StallingDataset(torch.utils.data.Dataset):
    """Item 0 loads at once; item 1 never comes back in time (a hung worker)."""

    def __len__(self) -> int:
        return 2

    def __getitem__(self, index: int):
        if index == 1:
            import time

            time.sleep(600)
        return torch.zeros(1)


@pytest.mark.slow  # ~35 s: a worker start, a 15 s timeout and the hung worker's shutdown
def test_loader_workers_come_from_a_forkserver_and_a_hang_is_an_error(monkeypatch):
    """Issue 46: a worker idle for 8 minutes at an epoch boundary stalled a run. Workers are not
    fork()ed from the threaded trainer, and a batch that does not come within the timeout raises
    (the trainer then restarts the workers) instead of hanging."""
    from training import data

    monkeypatch.setattr(data, "LOADER_TIMEOUT_S", 15)  # the first batch waits for the worker to start
    loader = data.make_loader(_StallingDataset(), batch_size=1, shuffle=False, num_workers=1)
    assert loader.multiprocessing_context.get_start_method() == "forkserver"
    batches = iter(loader)
    assert next(batches).shape == (1, 1)
    with pytest.raises(RuntimeError, match="timed out"):
        next(batches)
    del batches
    assert data.make_loader(_StallingDataset(), batch_size=1, shuffle=False).timeout == 0  # in-process: no timer


def test_pose_stride_term_trains_posenet_on_the_stride2_rows_only(tmp_path):
    """--pose-stride (round 13): with twins in the batch, rigid_loss logs ``pose_stride`` and its gradient
    reaches PoseNet; DepthNet gets none from it (the term sees translations only); a batch without any
    twin has no such term."""
    from geonet_infer.conventions import IMAGE_NORM
    from training.checkpoint import build_model

    torch.manual_seed(0)
    cfg = config(tmp_path, tmp_path / "o", weights=LossWeights(pose_stride=1.0))
    model = build_model(cfg)
    B, h, w = 2, 64, 192
    target, sources = torch.rand(B, 3, h, w), torch.rand(B, 2, 3, h, w)
    K = torch.tensor([[100.0, 0, w / 2], [0, 100.0, h / 2], [0, 0, 1]]).expand(B, 3, 3)
    twins = {"twin_target": target.clone(), "twin_sources": torch.rand(B, 2, 3, h, w)}
    loss = model.rigid_loss(target, sources, K, **twins, has_twin=torch.tensor([True, False]))
    assert "pose_stride" in loss.terms and math.isfinite(loss.terms["pose_stride"])
    model.weights = LossWeights(pose_stride=1.0, rigid_warp=0.0, disp_smooth=0.0)  # the stride term alone
    only = model.rigid_loss(target, sources, K, **twins, has_twin=torch.tensor([True, False]))
    only.total.backward()
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in model.pose_net.parameters())
    assert all(p.grad is None or p.grad.abs().sum() == 0 for p in model.depth_net.parameters())
    none = model.rigid_loss(target, sources, K, **twins, has_twin=torch.tensor([False, False]))
    assert "pose_stride" not in none.terms
    # The twins go through PoseNet in the batch's own call (round 13 ran them alone: a row or two under its
    # own batch-norm statistics, which also fed the running ones): in training mode their poses are those
    # of the joint batch, not of a call of their own.
    model.train()
    twin_input = IMAGE_NORM.apply(torch.cat([twins["twin_target"][:1], twins["twin_sources"][:1].flatten(1, 2)], dim=1))
    out, _, _ = model.rigid_forward(
        target, sources, K, extra_target=twins["twin_target"][:1], extra_sources=twins["twin_sources"][:1]
    )
    with torch.no_grad():
        main_input = IMAGE_NORM.apply(torch.cat([target, sources.flatten(1, 2)], dim=1))
        joint = model.pose_net(torch.cat([main_input, twin_input]))
        alone = model.pose_net(twin_input)
    torch.testing.assert_close(out.extra_poses.detach(), joint[B:])
    torch.testing.assert_close(out.poses.detach(), joint[:B])
    assert not torch.allclose(out.extra_poses.detach(), alone, atol=1e-4)


def test_pose_overlap_term_trains_posenet_with_the_next_snippets_in_the_batchs_call(tmp_path):
    """--pose-overlap (round 16): with next snippets in the batch, rigid_loss logs ``pose_overlap``, its
    gradient reaches PoseNet and not DepthNet; with twins too, both terms come from one PoseNet call
    (the twins' rows first, then the next snippets'), each term its own rows; no next snippet, no term."""
    from geonet_infer.conventions import IMAGE_NORM
    from training.checkpoint import build_model
    from training.geometry import pose_vec_to_mat
    from training.losses import overlap_step_error, stride_ratio_error

    torch.manual_seed(0)
    cfg = config(tmp_path, tmp_path / "o", weights=LossWeights(pose_overlap=1.0, rigid_warp=0.0, disp_smooth=0.0))
    model = build_model(cfg)
    B, h, w = 3, 64, 192
    target, sources = torch.rand(B, 3, h, w), torch.rand(B, 2, 3, h, w)
    K = torch.tensor([[100.0, 0, w / 2], [0, 100.0, h / 2], [0, 0, 1]]).expand(B, 3, 3)
    nxt = {"next_target": torch.rand(B, 3, h, w), "next_sources": torch.rand(B, 2, 3, h, w)}
    twins = {"twin_target": torch.rand(B, 3, h, w), "twin_sources": torch.rand(B, 2, 3, h, w)}
    loss = model.rigid_loss(target, sources, K, **nxt, has_next=torch.tensor([False, True, True]))
    loss.total.backward()
    assert loss.terms["pose_overlap"] > 0
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in model.pose_net.parameters())
    assert all(p.grad is None or p.grad.abs().sum() == 0 for p in model.depth_net.parameters())
    none = model.rigid_loss(target, sources, K, **nxt, has_next=torch.tensor([False, False, False]))
    assert "pose_overlap" not in none.terms

    model.weights = LossWeights(pose_overlap=1.0, pose_stride=1.0, rigid_warp=0.0, disp_smooth=0.0)
    model.eval()  # running statistics: each row's pose does not depend on the others, so it can be checked
    both = model.rigid_loss(
        target, sources, K, **twins, has_twin=torch.tensor([True, False, False]), **nxt,
        has_next=torch.tensor([False, True, True]),
    )  # fmt: skip

    @torch.no_grad()
    def motions(snippet_target, snippet_sources):  # (b, 2, 4, 4) from a call on these snippets alone
        pose_input = torch.cat([snippet_target, snippet_sources.flatten(1, 2)], dim=1)
        poses = model.pose_net(IMAGE_NORM.apply(pose_input))
        return pose_vec_to_mat(poses.flatten(0, 1)).view(*poses.shape[:2], 4, 4)

    T = motions(target, sources)
    T_twin = motions(twins["twin_target"][:1], twins["twin_sources"][:1])
    T_next = motions(nxt["next_target"][1:], nxt["next_sources"][1:])
    assert math.isclose(both.terms["pose_stride"], stride_ratio_error(T[:1], T_twin).item(), rel_tol=1e-4)
    assert math.isclose(both.terms["pose_overlap"], overlap_step_error(T[1:], T_next).item(), rel_tol=1e-4)


def test_gate_only_trains_the_motion_gate_alone(synth_prepared, tmp_path):
    """--gate-only --pose-gate (round 19): from an ungated model, the gate starts new and is the only thing
    that changes (DepthNet and PoseNet's trunk, batch-norm statistics included, stay as initialised); the
    checkpoint rebuilds a gated model, and a stage started from it keeps the gate without the flag. Refused
    without --pose-gate or outside stage rigid."""
    from training.checkpoint import load_weights, model_from_checkpoint

    init = str(train(config(synth_prepared, tmp_path / "a", max_steps=1), progress=False)["last"])
    gate = LossWeights(pose_gate=1.0)
    short, longer = (
        train(config(synth_prepared, tmp_path / n, max_steps=s, gate_only=True, init_checkpoint=init, weights=gate),
              progress=False)["last"]
        for n, s in (("b", 1), ("c", 3))
    )  # fmt: skip
    before, one, three = (load_checkpoint(p)["model"] for p in (init, short, longer))
    rest = [k for k in before if not k.startswith("flow_net.")]
    assert all(torch.equal(before[k], three[k]) for k in rest)
    gate_keys = [k for k in three if k.startswith("pose_net.gate.")]
    assert gate_keys and any(not torch.equal(one[k], three[k]) for k in gate_keys)
    assert all(math.isfinite(r["pose_gate"]) for r in read_log(tmp_path / "c" / "log.jsonl") if "pose_gate" in r)
    assert model_from_checkpoint(load_weights(longer)).pose_net.gate is not None
    # a gated model's next stage keeps its gate without the flag (the bundled model is gated since round 21)
    flow = train(config(synth_prepared, tmp_path / "d", stage="flow", max_steps=1, init_checkpoint=str(longer)),
                 progress=False)  # fmt: skip
    after_flow = load_checkpoint(flow["last"])["model"]
    assert all(torch.equal(three[k], after_flow[k]) for k in gate_keys)
    assert cfg_refused(config(synth_prepared, tmp_path / "e", gate_only=True))
    assert cfg_refused(
        config(synth_prepared, tmp_path / "f", gate_only=True, stage="flow", weights=gate, init_checkpoint=init)
    )


def test_rigid_corruption_scales_the_poses_behind_resflownets_input_in_training_only():
    """--rigid-corruption C (round 19): a quarter of a training batch's snippets get zero poses, so zero rigid
    flow (the identity warp, at every scale), the rest factors log-uniform in [1/C, C]; validation and
    inference (ResFlowNet in eval mode) use PoseNet's poses as they are."""
    from training.checkpoint import build_model

    torch.manual_seed(0)
    cfg = config("unused", "unused", stage="flow", rigid_corruption=3.0)
    model = build_model(cfg)
    factors = model.corrupted_pose_factors(8000, torch.device("cpu")).flatten()
    zero = factors == 0
    assert abs(float(zero.float().mean()) - 0.25) < 0.02
    assert float(factors[~zero].min()) >= 1 / 3 and float(factors[~zero].max()) <= 3
    assert abs(float(factors[~zero].log().mean())) < 0.05
    B, h, w = 2, 64, 192
    target, sources = torch.rand(B, 3, h, w), torch.rand(B, 2, 3, h, w)
    K = torch.tensor([[100.0, 0, w / 2], [0, 100.0, h / 2], [0, 0, 1]]).expand(B, 3, 3)
    model.eval()
    with torch.no_grad():
        still, _, _ = model.rigid_forward(target, sources, K, pose_factors=torch.zeros(B, 1, 1))
        assert all(float(f.abs().max()) < 1e-4 for f in still.fwd_flow + still.bwd_flow)
        plain = build_model(config("unused", "unused", stage="flow"))
        plain.load_state_dict(model.state_dict())
        plain.eval()
        a, b = model.flow_forward(target, sources, K)[0], plain.flow_forward(target, sources, K)[0]
        assert all(torch.equal(x, y) for x, y in zip(a, b))


def test_direct_flow_reads_the_frames_alone_and_its_graph_keeps_the_runtimes_interface():
    """--direct-flow (round 20): stage flow runs neither DepthNet nor PoseNet, ResFlowNet reads the frames as a
    camera at rest would give them (the source as its own warp, zero rigid flow) and its output is the flow. The
    export wrapper, fed the runtime's 12 channels with any rigid flow, returns that flow and flow - rigid."""
    from export.wrappers import build_wrapper
    from geonet_infer.conventions import IMAGE_NORM
    from training.checkpoint import build_model
    from training.model import flownet_input

    class Refuse(torch.nn.Module):
        def forward(self, x):
            raise AssertionError("a direct-flow stage ran a rigid net")

    torch.manual_seed(0)
    model = build_model(config("unused", "unused", stage="flow", direct_flow=True)).eval()
    B, h, w = 1, 64, 192
    target, sources = torch.rand(B, 3, h, w), torch.rand(B, 2, 3, h, w)
    wrapper = build_wrapper("resflownet", model)
    model.depth_net, model.pose_net = Refuse(), Refuse()
    K = torch.tensor([[100.0, 0, w / 2], [0, 100.0, h / 2], [0, 0, 1]]).expand(B, 3, 3)
    with torch.no_grad():
        fwd, _, _, _ = model.flow_forward(target, sources, K)
        next_source = IMAGE_NORM.apply(sources[:, model.next_source])
        rigid = torch.randn(B, 2, h, w)  # whatever the runtime's rigid op gave; the warp and error likewise
        runtime_input = flownet_input(
            IMAGE_NORM.apply(target), next_source, torch.rand(B, 3, h, w), rigid, torch.rand(B, 3, h, w)
        )
        residual, flow = wrapper(runtime_input)
    torch.testing.assert_close(flow, fwd[0][model.next_source * B :][:B], atol=1e-4, rtol=0)
    torch.testing.assert_close(residual + rigid, flow)


def test_recalibrate_sets_the_running_statistics_to_the_average_of_the_batch_statistics(synth_prepared, tmp_path):
    """python -m training.recalibrate (round 21): the stage's nets' running means become the plain average of
    their batch means over the batches it reads (measured here with a hook on the same batches, in the same
    order), every weight unchanged, the frozen nets' statistics untouched."""
    from torch.utils.data import ConcatDataset

    from training import recalibrate
    from training.checkpoint import load_weights, model_from_checkpoint
    from training.data import SequenceDataset, make_loader

    first = train(config(synth_prepared, tmp_path / "r", max_steps=1), progress=False)["last"]
    flow = train(config(synth_prepared, tmp_path / "f", stage="flow", max_steps=1, init_checkpoint=str(first)),
                 progress=False)["last"]  # fmt: skip
    out = tmp_path / "recalibrated.pt"
    assert recalibrate.main([str(flow), str(out), "--batches", "2", "--data-dir", str(synth_prepared)]) == 0
    before, after = load_weights(flow)["model"], load_weights(out)["model"]
    weights = [k for k in before if not k.endswith(("running_mean", "running_var", "num_batches_tracked"))]
    assert all(torch.allclose(before[k], after[k], rtol=1e-3, atol=1e-4) for k in weights)  # float16 kernels
    frozen = [k for k in before if k.endswith("running_mean") and not k.startswith("flow_net.")]
    assert frozen and all(torch.equal(before[k], after[k]) for k in frozen)

    model = model_from_checkpoint(load_weights(flow))
    norm = next(m for m in model.flow_net.modules() if isinstance(m, torch.nn.BatchNorm2d))
    name = next(k for k, m in model.named_modules() if m is norm)
    means = []
    norm.register_forward_hook(lambda m, inputs, _: means.append(inputs[0].mean(dim=(0, 2, 3))))
    cfg = TrainConfig.from_dict(load_weights(flow)["config"])
    data = ConcatDataset(
        [SequenceDataset(synth_prepared, "train", cfg.seq_length, cfg.height, cfg.width, augment=False)]
    )
    model.eval()
    with torch.no_grad():
        for k, batch in enumerate(make_loader(data, recalibrate.BATCH_SIZE, shuffle=True, seed=0, drop_last=True)):
            if k == 2:
                break
            model.flow_forward(batch["target"], batch["sources"], batch["intrinsics"])
    torch.testing.assert_close(after[f"{name}.running_mean"], torch.stack(means).mean(dim=0), rtol=1e-4, atol=1e-5)

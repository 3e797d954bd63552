"""Trainer: the photometric loss falls on real frames, resume is exact, bad input is named."""
import json
from pathlib import Path

import pytest
import torch

from geonet_infer.errors import GeoNetInputError
from training import prepare
from training.config import TrainConfig, config_from_args
from training.train import build_model, load_checkpoint, main, model_from_checkpoint, train

REALDATA = Path(__file__).resolve().parents[2] / "shared" / "realdata"
KITTI_RAW = REALDATA / "kitti_raw_2011_09_26_sfnd"
H, W = 64, 208  # CI-sized: a quarter of the 128x416 pixels


@pytest.fixture(scope="module")
def kitti_prepared(tmp_path_factory):
    if not KITTI_RAW.is_dir():
        pytest.skip("../shared/realdata is not available")
    out = tmp_path_factory.mktemp("prepared")
    prepare.main(["--kind", "kitti_raw", "--src", str(KITTI_RAW), "--out", str(out),
                         "--split", "none", "--height", str(H), "--width", str(W),
                         "--max-frames", "14", "--workers", "1", "--val-fraction", "0.2"])
    assert (out / "train.txt").is_file()
    return out


def config(data_dir, out_dir, **overrides) -> TrainConfig:
    base = dict(stage="rigid", arch="small", data_dir=str(data_dir), out_dir=str(out_dir),
                height=H, width=W, batch_size=2, num_workers=0, augment=False, log_every=1,
                save_every=1000, val_every=1000, val_batches=2, seed=3)
    base.update(overrides)
    return TrainConfig(**base)


def read_log(path):
    return [json.loads(line) for line in Path(path).read_text().splitlines()]


def test_photometric_loss_falls_on_real_frames(kitti_prepared, tmp_path):
    # bn_momentum 0.1: a 40-step run is far too short for the official 0.001.
    result = train(config(kitti_prepared, tmp_path, max_steps=40, lr=1e-3, bn_momentum=0.1),
                   progress=False)
    rows = read_log(result["log"])
    first = sum(r["rigid_warp"] for r in rows[:5]) / 5
    last = sum(r["rigid_warp"] for r in rows[-5:]) / 5
    print(f"rigid_warp loss: first 5 steps {first:.4f}, last 5 steps {last:.4f}, drop {1 - last / first:.1%}")
    assert last < 0.9 * first, (first, last)
    assert {"rigid_warp", "disp_smooth", "total", "val_total"} <= set(rows[-1])


def test_resume_continues_bit_for_bit(kitti_prepared, tmp_path):
    straight = train(config(kitti_prepared, tmp_path / "a", max_steps=6, augment=True), progress=False)
    train(config(kitti_prepared, tmp_path / "b", max_steps=3, save_every=3, augment=True), progress=False)
    resumed = train(config(kitti_prepared, tmp_path / "b", max_steps=6, augment=True,
                           resume=str(tmp_path / "b" / "last.pt")), progress=False)
    a = load_checkpoint(straight["last"])["model"]
    b = load_checkpoint(resumed["last"])["model"]
    assert a.keys() == b.keys()
    for key in a:
        assert torch.equal(a[key], b[key]), key
    assert read_log(straight["log"])[-1]["total"] == read_log(resumed["log"])[-1]["total"]


def test_flow_stage_freezes_rigid_nets(kitti_prepared, tmp_path):
    rigid = train(config(kitti_prepared, tmp_path / "rigid", max_steps=2), progress=False)
    flow = train(config(kitti_prepared, tmp_path / "flow", stage="flow", max_steps=3,
                        init_checkpoint=str(rigid["last"])), progress=False)
    before = load_checkpoint(rigid["last"])["model"]
    after = load_checkpoint(flow["last"], expect_stage="flow")["model"]
    for key, value in before.items():  # weights and BN running stats untouched
        assert torch.equal(value, after[key]), key
    assert any(k.startswith("flow_net.") for k in after)
    rows = read_log(flow["log"])
    assert {"flow_warp", "flow_smooth", "flow_consistency"} <= set(rows[-1])
    assert model_from_checkpoint(load_checkpoint(flow["last"])).flow_net is not None


def test_flow_stage_rejects_a_flow_checkpoint_as_init(kitti_prepared, tmp_path):
    rigid = train(config(kitti_prepared, tmp_path / "rigid", max_steps=1), progress=False)
    flow = train(config(kitti_prepared, tmp_path / "flow", stage="flow", max_steps=1,
                        init_checkpoint=str(rigid["last"])), progress=False)
    with pytest.raises(GeoNetInputError, match="stage 'flow', expected 'rigid'") as err:
        train(config(kitti_prepared, tmp_path / "flow2", stage="flow", max_steps=1,
                     init_checkpoint=str(flow["last"])), progress=False)
    assert str(flow["last"]) in str(err.value)


def test_missing_data_dir_is_a_clear_error(tmp_path, capsys):
    code = main(["--data-dir", str(tmp_path / "nowhere"), "--out-dir", str(tmp_path / "run"),
                 "--arch", "small", "--max-steps", "1"])
    assert code == 2
    message = capsys.readouterr().err
    assert str(tmp_path / "nowhere") in message and "training.prepare" in message


def test_empty_split_is_a_clear_error(tmp_path):
    (tmp_path / "train.txt").write_text("")
    with pytest.raises(GeoNetInputError, match="train.txt"):
        train(config(tmp_path, tmp_path / "run", max_steps=1), progress=False)


def test_corrupt_image_is_named(kitti_prepared, tmp_path):
    import shutil
    data = tmp_path / "data"
    shutil.copytree(kitti_prepared, data)
    folder, frame = (data / "train.txt").read_text().split()[:2]
    victim = data / folder / f"{frame}.jpg"
    victim.write_bytes(b"not a jpeg")
    (data / "train.txt").write_text(f"{folder} {frame}\n" * 4)
    with pytest.raises(GeoNetInputError) as err:
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

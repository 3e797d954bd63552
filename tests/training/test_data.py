"""training.data.SequenceDataset: format reading, augmentation geometry/colour, errors.

Prepared folders are written here by hand (cv2 + plain text), independent of training.prepare,
except for the held-out test which checks the two together.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from geonet_infer.errors import GeoNetError
from geonet_infer.io import write_calib_K, write_depth_kitti, write_flow_kitti
from training import data as D
from training import prepare as P

H, W = 128, 416
K0 = np.array([[200.0, 0.0, 208.0], [0.0, 190.0, 64.0], [0.0, 0.0, 1.0]])


def write_sample(root: Path, folder: str, frame: str, frames_rgb: list[np.ndarray], K: np.ndarray) -> None:
    """One prepared sample by hand: frames side by side in a q95 JPEG + official _cam.txt line."""
    (root / folder).mkdir(parents=True, exist_ok=True)
    strip = np.concatenate(frames_rgb, axis=1)
    cv2.imwrite(
        str(root / folder / f"{frame}.jpg"), cv2.cvtColor(strip, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 95]
    )
    fx, cx, fy, cy = K[0, 0], K[0, 2], K[1, 1], K[1, 2]
    (root / folder / f"{frame}_cam.txt").write_text(f"{fx},0.,{cx},0.,{fy},{cy},0.,0.,1.")


def write_lists(root: Path, train: list[str], val: list[str] = (), heldout: list[str] | None = None) -> None:
    (root / "train.txt").write_text("".join(n + "\n" for n in train))
    (root / "val.txt").write_text("".join(n + "\n" for n in val))
    if heldout is not None:
        (root / "heldout.txt").write_text("".join(n + "\n" for n in heldout))


def const_frames(values, h=H, w=W) -> list[np.ndarray]:
    return [np.full((h, w, 3), v, np.uint8) for v in values]


# --------------------------------------------------------------------------- shapes / order
@pytest.mark.parametrize("seq_length", [3, 5])
def test_shapes_ranges_and_temporal_order(tmp_path, seq_length):
    values = [20 + 40 * k for k in range(seq_length)]  # frame k has grey level values[k]
    write_sample(tmp_path, "s", "000007", const_frames(values), K0)
    write_lists(tmp_path, ["s 000007"], ["s 000007"])
    for split, aug in (("val", False), ("train", True)):
        ds = D.SequenceDataset(tmp_path, split, seq_length=seq_length, augment=aug, seed=3)
        item = ds[0]
        assert set(item) == {"target", "sources", "intrinsics", "name"}
        assert item["name"] == "s 000007"
        assert item["target"].shape == (3, H, W) and item["target"].dtype == torch.float32
        assert item["sources"].shape == (seq_length - 1, 3, H, W) and item["sources"].dtype == torch.float32
        assert item["intrinsics"].shape == (3, 3) and item["intrinsics"].dtype == torch.float32
        for t in (item["target"], item["sources"]):
            assert 0.0 <= float(t.min()) and float(t.max()) <= 1.0
    ds = D.SequenceDataset(tmp_path, "val", seq_length=seq_length)
    item = ds[0]
    mid = seq_length // 2
    src_values = values[:mid] + values[mid + 1 :]  # seq 3: [t-1, t+1]; seq 5: [t-2, t-1, t+1, t+2]
    assert abs(float(item["target"].mean()) - values[mid] / 255) < 2 / 255
    for s, v in zip(item["sources"], src_values):
        assert abs(float(s.mean()) - v / 255) < 2 / 255
    np.testing.assert_allclose(item["intrinsics"].numpy(), K0, rtol=1e-6)


# --------------------------------------------------------------------------- augmentation geometry
def blob_image(u: float, v: float, sigma: float = 2.5, h=H, w=W) -> np.ndarray:
    """(h, w, 3) uint8: black with a Gaussian spot centred at pixel (u, v) (pixel-centre coords)."""
    yy, xx = np.mgrid[0:h, 0:w]
    g = np.exp(-((xx - u) ** 2 + (yy - v) ** 2) / (2 * sigma**2))
    return np.repeat((g * 230)[..., None], 3, axis=2).round().astype(np.uint8)


def centroid(img_chw: np.ndarray) -> tuple[float, float]:
    """Intensity-weighted centre of the spot (background and JPEG noise thresholded away)."""
    g = img_chw.mean(axis=0)
    wgt = np.clip(g - 0.1 * g.max(), 0, None)
    yy, xx = np.mgrid[0 : g.shape[0], 0 : g.shape[1]]
    return float((wgt * xx).sum() / wgt.sum()), float((wgt * yy).sum() / wgt.sum())


def project(K: np.ndarray, X: np.ndarray) -> np.ndarray:
    p = K @ X
    return p[:2] / p[2]


X_POINT = np.array([1.3, -0.4, 7.0])  # metres, camera frame


def test_scale_crop_moves_pixels_where_new_K_projects():
    u, v = project(K0, X_POINT)
    frames = blob_image(u, v)[None].astype(np.float32) / 255
    offsets = set()
    for seed in range(8):
        out, K, info = D.random_scale_crop(frames, K0, np.random.default_rng(seed))
        assert out.shape == (1, H, W, 3)
        assert 1.0 <= info["sx"] <= 1.15 and 1.0 <= info["sy"] <= 1.15
        offsets.add((info["x0"], info["y0"]))
        cu, cv = centroid(out[0].transpose(2, 0, 1))
        pu, pv = project(K, X_POINT)
        # cv2 resizes with half-pixel centres, K with corner alignment: <= 0.5*(s-1) = 0.075 px apart
        assert abs(cu - pu) < 0.2 and abs(cv - pv) < 0.2, (seed, info, (cu, cv), (pu, pv))
    assert len(offsets) > 4  # the crop really moved around


def test_dataset_augmentation_updates_intrinsics(tmp_path):
    """End to end through the JPEG and the dataset: the spot lands where the item's K projects X."""
    u, v = project(K0, X_POINT)
    spot = blob_image(u, v)
    write_sample(tmp_path, "s", "000001", [spot, spot, spot], K0)
    write_lists(tmp_path, ["s 000001"], ["s 000001"])
    ds = D.SequenceDataset(tmp_path, "train", augment=True, seed=11)
    changed = 0
    for epoch in range(6):
        ds.set_epoch(epoch)
        item = ds[0]
        K = item["intrinsics"].numpy().astype(np.float64)
        changed += not np.allclose(K, K0)
        pu, pv = project(K, X_POINT)
        for img in (item["target"], *item["sources"]):
            cu, cv = centroid(img.numpy())
            assert abs(cu - pu) < 0.25 and abs(cv - pv) < 0.25, (epoch, (cu, cv), (pu, pv))
    assert changed == 6
    # determinism: same (seed, epoch, index) -> same item; another epoch -> another draw
    ds.set_epoch(2)
    a, b = ds[0], ds[0]
    assert torch.equal(a["target"], b["target"]) and torch.equal(a["intrinsics"], b["intrinsics"])
    ds.set_epoch(3)
    assert not torch.equal(a["intrinsics"], ds[0]["intrinsics"])
    # val and heldout are never augmented
    item = D.SequenceDataset(tmp_path, "val", augment=True)[0]
    np.testing.assert_allclose(item["intrinsics"].numpy(), K0, rtol=1e-6)


def test_augmented_depth_follows_the_frames_geometry(tmp_path):
    """Depth ground truth gets the frames' scale and crop: a depth map holding each pixel's own
    column number is, after augmentation, the column that the item's K maps back to."""
    # depth = (column + 1) / 4: no 0 (= none), and within the 16-bit encoding's 256 m
    columns = np.tile((np.arange(W, dtype=np.float32) + 1.0) / 4, (H, 1))
    write_sample(tmp_path, "s", "000001", const_frames([90, 100, 110]), K0)
    write_depth_kitti(tmp_path / "s" / "000001_depth.png", columns)
    write_sample(tmp_path, "r", "000001", const_frames([90, 100, 110]), K0)  # real footage: no depth file
    write_lists(tmp_path, ["s 000001", "r 000001"])
    ds = D.SequenceDataset(tmp_path, "train", augment=True, seed=5, load_depth=True)
    u = np.arange(W)
    for epoch in range(4):
        ds.set_epoch(epoch)
        item = ds[0]
        K = item["intrinsics"].numpy().astype(np.float64)
        depth = item["depth_gt"].numpy()[0]
        assert depth.shape == (H, W)
        expected = (u - K[0, 2]) * K0[0, 0] / K[0, 0] + K0[0, 2]  # source column of each output column
        # nearest-neighbour resize: within a pixel (plus the 4/256 px of the 16-bit encoding)
        assert np.abs(4 * depth[H // 2] - 1.0 - expected).max() <= 1.0, epoch
        assert np.ptp(depth, axis=0).max() < 0.01  # rows stay rows: no vertical mixing
    assert float(ds[1]["depth_gt"].abs().sum()) == 0.0  # a sample without ground truth: all zeros
    assert "depth_gt" not in D.SequenceDataset(tmp_path, "train")[0]  # only when asked for


def test_augmented_flow_follows_the_frames_geometry():
    """Flow ground truth gets the frames' scale and crop. Frame t+1 is frame t moved by exactly
    (-5, -2) px, so after augmentation the flow must be (-5 sx, -2 sy) with sx, sy read off the
    item's K (closed form), and warping t+1 with it must rebuild t (better than 0.9x or 1.1x it)."""
    rng = np.random.default_rng(0)
    texture = cv2.GaussianBlur(rng.uniform(0, 1, (H + 20, W + 40, 3)).astype(np.float32), (0, 0), 2)
    frame_t, frame_next = texture[10 : 10 + H, 20 : 20 + W], texture[12 : 12 + H, 25 : 25 + W]
    frames = np.stack([frame_t, frame_t, frame_next])
    flow = np.zeros((H, W, 3), np.float32)
    flow[..., 0], flow[..., 1], flow[..., 2] = -5.0, -2.0, 1.0
    xs, ys = np.meshgrid(np.arange(W, dtype=np.float32), np.arange(H, dtype=np.float32))
    for seed in range(4):
        out, K, _, out_flow = D.augment(frames, K0.copy(), np.random.default_rng(seed), True, None, flow)
        sx, sy = K[0, 0] / K0[0, 0], K[1, 1] / K0[1, 1]
        assert sx > 1.0 or sy > 1.0, seed  # the draw really scaled
        np.testing.assert_allclose(out_flow[..., 0], -5.0 * sx, rtol=1e-6)
        np.testing.assert_allclose(out_flow[..., 1], -2.0 * sy, rtol=1e-6)
        assert out_flow[..., 2].min() == 1.0
        errors = []
        for k in (0.9, 1.0, 1.1):
            warped = cv2.remap(out[2], xs + k * out_flow[..., 0], ys + k * out_flow[..., 1], cv2.INTER_LINEAR)
            errors.append(float(np.abs(warped - out[1])[12:-12, 12:-12].mean()))
        assert errors[1] < 0.3 * min(errors[0], errors[2]), (seed, errors)


def test_dataset_loads_flow_only_when_asked(tmp_path):
    write_sample(tmp_path, "s", "000001", const_frames([90, 100, 110]), K0)
    flow = np.zeros((H, W, 2), np.float32)
    flow[..., 0] = 1.5
    valid = np.ones((H, W), bool)
    valid[:, :10] = False
    write_flow_kitti(tmp_path / "s" / "000001_flow.png", flow, valid)
    write_sample(tmp_path, "r", "000001", const_frames([90, 100, 110]), K0)  # real footage: no flow file
    write_lists(tmp_path, ["s 000001", "r 000001"])
    ds = D.SequenceDataset(tmp_path, "train", augment=False, load_flow=True)
    item = ds[0]["flow_gt"].numpy()
    assert item.shape == (3, H, W)
    np.testing.assert_allclose(item[0][:, 10:], 1.5, atol=1 / 64)  # KITTI PNG: 1/64 px steps
    assert item[2, :, :10].max() == 0.0 and item[2, :, 10:].min() == 1.0
    assert float(ds[1]["flow_gt"].abs().sum()) == 0.0  # no ground truth: all zeros, valid 0
    assert "flow_gt" not in D.SequenceDataset(tmp_path, "train")[0]


# --------------------------------------------------------------------------- augmentation colour
def test_random_color_gain_shared_or_not():
    frames = np.full((3, 4, 5, 3), 0.5, np.float32)
    same = D.random_color(frames, np.random.default_rng(0), share_gain=True)
    assert np.array_equal(same[0], same[1]) and np.array_equal(same[0], same[2])
    diff = D.random_color(frames, np.random.default_rng(0), share_gain=False)
    assert not np.allclose(diff[0], diff[1]) and not np.allclose(diff[0], diff[2])
    # colour is (0.5 ** gamma) * brightness * gain, gamma in [0.8, 1.2], brightness in [0.5, 2],
    # gain in [0.8, 1.2]; channel ratios within a frame = gain ratios, in [0.8/1.2, 1.2/0.8]
    for out in (same, diff):
        assert 0.0 <= out.min() and out.max() <= 1.0
        px = out[:, 0, 0]
        assert px.min() >= 0.5**1.2 * 0.5 * 0.8 - 1e-6
        ratio = px.max(axis=1) / px.min(axis=1)
        assert np.all(ratio <= 1.2 / 0.8 + 1e-6)


@pytest.mark.parametrize("share", [True, False])
def test_dataset_color_gain_per_frame_quirk(tmp_path, share):
    """Identical frames stay identical only if the gain is shared."""
    rng = np.random.default_rng(5)
    # grey texture: JPEG chroma upsampling would blend across the frame borders of the strip
    tex = np.repeat(rng.integers(40, 200, size=(H, W, 1), dtype=np.uint8), 3, axis=2)
    write_sample(tmp_path, "s", "000001", [tex, tex, tex], K0)
    write_lists(tmp_path, ["s 000001"], ["s 000001"])
    plain = D.SequenceDataset(tmp_path, "val")[0]
    assert all(torch.equal(plain["target"], s) for s in plain["sources"])  # precondition
    ds = D.SequenceDataset(tmp_path, "train", augment=True, share_color_gain=share, seed=1)
    n_diff = 0
    for epoch in range(8):  # colour fires with p = 0.5
        ds.set_epoch(epoch)
        item = ds[0]
        d = max(float((item["target"] - s).abs().max()) for s in item["sources"])
        n_diff += d > 1e-3
        if share:
            assert d < 1e-6  # JPEG decodes the three copies identically; same ops on each
    if not share:
        assert n_diff >= 1


# --------------------------------------------------------------------------- held-out + prepare
def test_heldout_split_and_refusal(tmp_path):
    src = tmp_path / "synth"
    rng = np.random.default_rng(0)
    for s in range(3):
        d = src / f"seq_{s}"
        (d / "image").mkdir(parents=True)
        for i in range(4):
            cv2.imwrite(str(d / "image" / f"{i:06d}.png"), rng.integers(0, 256, (64, 96, 3), dtype=np.uint8))
            write_depth_kitti(d / "depth" / f"{i:06d}.png", np.full((64, 96), 10.0 + i))
        write_calib_K(d / "calib.txt", np.array([[80.0, 0, 48], [0, 80, 32], [0, 0, 1]]))
    out = tmp_path / "out"
    res = P.prepare(P.PrepareConfig("synth", src, out, height=32, width=48, heldout=1, val_fraction=0.3, seed=1))
    held = D.SequenceDataset(out, "heldout", height=32, width=48)
    assert sorted(held.names) == ["seq_2 000001", "seq_2 000002"]
    item = held[1]
    assert item["depth_gt"].shape == (1, 32, 48) and item["depth_gt"].dtype == torch.float32
    frame = int(item["name"].split()[1])
    assert torch.all(item["depth_gt"] == 10.0 + frame)
    train = D.SequenceDataset(out, "train", height=32, width=48)
    assert not set(train.names) & set(held.names) and len(train) == len(res.train)
    assert "depth_gt" not in train[0]
    # a train list that leaks a held-out sample is refused
    (out / "train.txt").write_text((out / "train.txt").read_text() + "seq_2 000001\n")
    with pytest.raises(GeoNetError, match="heldout"):
        D.SequenceDataset(out, "train", height=32, width=48)


# --------------------------------------------------------------------------- errors
def test_clear_errors(tmp_path):
    with pytest.raises(GeoNetError, match="training.prepare") as err:
        D.SequenceDataset(tmp_path / "nope")
    assert str(tmp_path / "nope") in str(err.value)
    (tmp_path / "empty").mkdir()
    with pytest.raises(GeoNetError, match="training.prepare") as err:
        D.SequenceDataset(tmp_path / "empty")
    assert "train.txt" in str(err.value)
    with pytest.raises(GeoNetError, match="heldout"):
        D.SequenceDataset(tmp_path / "empty", "heldout")

    root = tmp_path / "ds"
    write_sample(root, "s", "000001", const_frames([10, 20, 30]), K0)
    write_lists(root, ["s 000001", "s 000002"], [])
    with pytest.raises(GeoNetError, match="empty"):
        D.SequenceDataset(root, "val")
    ds = D.SequenceDataset(root, "train", augment=False)
    with pytest.raises(GeoNetError) as err:  # listed but missing
        ds[1]
    assert "000002.jpg" in str(err.value)
    (root / "s" / "000002.jpg").write_bytes(b"\xff\xd8garbage")
    (root / "s" / "000002_cam.txt").write_text("1,0,0,0,1,0,0,0,1")
    with pytest.raises(GeoNetError) as err:  # corrupt
        ds[1]
    assert str(root / "s" / "000002.jpg") in str(err.value)
    with pytest.raises(GeoNetError) as err:  # a seq-3 snippet read as seq 5
        D.SequenceDataset(root, "train", seq_length=5)[0]
    assert str(root / "s" / "000001.jpg") in str(err.value) and "seq_length=5" in str(err.value)
    assert "holds 3 frames" in str(err.value)
    (root / "s" / "000001_cam.txt").write_text("1,2,3")
    with pytest.raises(GeoNetError, match="_cam.txt"):
        ds[0]


def test_make_loader_is_seeded(tmp_path):
    names = [f"s {i:06d}" for i in range(6)]
    for i in range(6):
        write_sample(tmp_path, "s", f"{i:06d}", const_frames([i * 10] * 3, 16, 24), K0)
    write_lists(tmp_path, names)
    ds = D.SequenceDataset(tmp_path, "train", height=16, width=24, seed=4)

    def order(seed):
        return [n for b in D.make_loader(ds, 2, shuffle=True, num_workers=0, seed=seed) for n in b["name"]]

    assert order(7) == order(7) and sorted(order(7)) == names
    assert any(order(7) != order(s) for s in (8, 9, 10))
    batch = next(iter(D.make_loader(ds, 4, shuffle=False, seed=0)))
    assert batch["target"].shape == (4, 3, 16, 24) and batch["sources"].shape == (4, 2, 3, 16, 24)
    assert batch["intrinsics"].shape == (4, 3, 3)


def test_stride2_copies_load_their_normal_snippet_under_the_same_augmentation(tmp_path):
    """load_twins (--pose-stride): a ``_stride2`` sample carries its target's normal snippet, augmented with
    the same draws. Both hold the same target frame, so after the same scale, crop and colour the two
    targets are equal to the byte; the twin's sources are its own (t-1, t+1), not the stride-2 ones. A
    sample without a twin (a normal one, or a stride2 copy whose normal snippet is missing) says so."""
    rng = np.random.default_rng(0)
    t_minus2, t_minus1, t, t_plus1, t_plus2 = (rng.integers(0, 256, (H, W, 3), dtype=np.uint8) for _ in range(5))
    K = K0
    (tmp_path / "s").mkdir()
    for frame, frames in (("000004", [t_minus1, t, t_plus1]), ("000004_stride2", [t_minus2, t, t_plus2]),
                          ("000009_stride2", [t_minus2, t, t_plus2])):  # fmt: skip
        # PNG bytes under the .jpg name (OpenCV reads by content): the frames stay exact
        ok, png = cv2.imencode(".png", cv2.cvtColor(np.concatenate(frames, axis=1), cv2.COLOR_RGB2BGR))
        (tmp_path / "s" / f"{frame}.jpg").write_bytes(png.tobytes())
        (tmp_path / "s" / f"{frame}_cam.txt").write_text(f"{K[0, 0]},0.,{K[0, 2]},0.,{K[1, 1]},{K[1, 2]},0.,0.,1.")
    write_lists(tmp_path, ["s 000004", "s 000004_stride2", "s 000009_stride2"])
    for epoch in range(3):  # several draws of scale, crop and colour
        ds = D.SequenceDataset(tmp_path, "train", augment=True, seed=epoch, load_twins=True)
        ds.set_epoch(epoch)
        normal, fast, orphan = ds[0], ds[1], ds[2]
        assert fast["has_twin"] and not normal["has_twin"] and not orphan["has_twin"]
        torch.testing.assert_close(fast["twin_target"], fast["target"], rtol=0, atol=0)
        plain = D.SequenceDataset(tmp_path, "train", augment=False, load_twins=True)[1]
        for k, frame in enumerate((t_minus1, t_plus1)):  # unaugmented: the twin's sources are t-1 and t+1
            torch.testing.assert_close(plain["twin_sources"][k], torch.from_numpy(frame).permute(2, 0, 1) / 255.0)
        assert not torch.equal(fast["twin_sources"], fast["sources"])
    assert "has_twin" not in D.SequenceDataset(tmp_path, "train")[1]  # only when asked


def test_a_snippet_loads_the_next_targets_snippet_under_the_same_augmentation(tmp_path):
    """load_next (--pose-overlap): sample t (t-1, t, t+1) carries the snippet of target t+1 (t, t+1, t+2)
    under the same draws, so frames t and t+1, held by both, are equal to the byte after the same scale,
    crop and (shared) colour. No neighbour for the last listed target, for a motion-mix copy, or for a
    target whose neighbour another split lists."""
    rng = np.random.default_rng(1)
    f = [rng.integers(0, 256, (H, W, 3), dtype=np.uint8) for _ in range(6)]  # frames 3..8
    (tmp_path / "s").mkdir()
    snippets = {"000004": f[0:3], "000005": f[1:4], "000006": f[2:5], "000007": f[3:6], "000004_static": [f[1]] * 3}
    for frame, frames in snippets.items():
        ok, png = cv2.imencode(".png", cv2.cvtColor(np.concatenate(frames, axis=1), cv2.COLOR_RGB2BGR))
        (tmp_path / "s" / f"{frame}.jpg").write_bytes(png.tobytes())
        (tmp_path / "s" / f"{frame}_cam.txt").write_text(f"{K0[0, 0]},0.,{K0[0, 2]},0.,{K0[1, 1]},{K0[1, 2]},0.,0.,1.")
    write_lists(tmp_path, ["s 000004", "s 000005", "s 000004_static", "s 000007"], val=["s 000006"])
    for epoch in range(3):
        ds = D.SequenceDataset(tmp_path, "train", augment=True, share_color_gain=True, seed=epoch, load_next=True)
        ds.set_epoch(epoch)
        first, second, still, last = ds[0], ds[1], ds[2], ds[3]
        assert first["has_next"] and not second["has_next"] and not still["has_next"] and not last["has_next"]
        # frame t+1: source 1 of snippet t, the target of snippet t+1; frame t: the target, then source 0
        torch.testing.assert_close(first["next_target"], first["sources"][1], rtol=0, atol=0)
        torch.testing.assert_close(first["next_sources"][0], first["target"], rtol=0, atol=0)
    plain = D.SequenceDataset(tmp_path, "train", augment=False, load_next=True)[0]
    torch.testing.assert_close(plain["next_sources"][1], torch.from_numpy(f[3]).permute(2, 0, 1) / 255.0)
    assert "has_next" not in D.SequenceDataset(tmp_path, "train")[0]  # only when asked

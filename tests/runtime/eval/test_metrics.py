"""Golden-value tests of geonet_infer.eval.metrics; every expected number is worked out by hand below."""

import math

import numpy as np
import pytest

from geonet_infer.errors import GeoNetError
from geonet_infer.eval.metrics import (
    aggregate,
    ate_rmse_true,
    ate_snippet,
    crop_mask,
    depth_floor_share,
    depth_metrics,
    flow_epe,
    resize_depth_to,
    resize_flow_nearest,
    rigid_inverse,
    snippet_poses_to_global,
)


# --------------------------------------------------------------------------- depth
def test_median_scaling_gives_zero_error_for_proportional_prediction():
    # gt = [2, 4], pred = [1, 2]: scale = median(gt)/median(pred) = 3/1.5 = 2 -> pred = gt exactly.
    m = depth_metrics(np.array([[2.0, 4.0]]), np.array([[1.0, 2.0]]), crop=None)
    assert m["scale"] == pytest.approx(2.0)
    for key in ("abs_rel", "sq_rel", "rmse", "rmse_log"):
        assert m[key] == pytest.approx(0.0, abs=1e-12)
    assert (m["a1"], m["a2"], m["a3"]) == (1.0, 1.0, 1.0)


def test_depth_floor_share_of_a_ramp_and_of_a_clamped_ramp():
    # Rows 50 m (top) to 1 m (bottom), log-spaced: neighbouring rows differ by 2 %, ten bins of 0.2 %,
    # so each of the lower half's 100 rows has a bin of its own.
    ramp = np.geomspace(50.0, 1.0, 200)[:, None] * np.ones((1, 30))
    assert depth_floor_share(ramp) == pytest.approx(1 / 100)
    # Clamped at row 160's depth: rows 160-199 (40 of the lower 100) share one value.
    assert depth_floor_share(np.maximum(ramp, ramp[160, 0])) == pytest.approx(40 / 100)
    assert depth_floor_share(np.full((4, 6), 3.0)) == 1.0  # a constant map is all floor
    with pytest.raises(GeoNetError, match="finite positive"):
        depth_floor_share(np.zeros((4, 6)))


def test_known_errors_without_scaling_and_invalid_gt_ignored():
    # Pixels with gt = 0 are outside (1e-3, 80) and must be ignored (pred 1000 there).
    # Valid: gt = [2, 4], pred = [1, 5]; diffs 1 and -1.
    # abs_rel = (1/2 + 1/4)/2 = 0.375; sq_rel = (1/2 + 1/4)/2 = 0.375; rmse = sqrt((1+1)/2) = 1
    # rmse_log = sqrt((ln2^2 + ln1.25^2)/2) = sqrt((0.480453 + 0.049793)/2) = 0.514901
    # delta = [max(2, .5), max(.8, 1.25)] = [2, 1.25]
    # a1: < 1.25 strict -> none -> 0; a2: < 1.5625 -> 0.5; a3: < 1.953125 -> 0.5
    gt = np.array([[2.0, 4.0, 0.0]])
    pred = np.array([[1.0, 5.0, 1000.0]])
    m = depth_metrics(gt, pred, crop=None, median_scaling=False)
    assert m["n_valid"] == 2
    assert m["scale"] == 1.0
    assert m["abs_rel"] == pytest.approx(0.375)
    assert m["sq_rel"] == pytest.approx(0.375)
    assert m["rmse"] == pytest.approx(1.0)
    assert m["rmse_log"] == pytest.approx(0.514901, abs=1e-6)
    assert (m["a1"], m["a2"], m["a3"]) == (0.0, 0.5, 0.5)


def test_known_errors_with_median_scaling():
    # gt = [2, 4, 6], pred = [1, 3, 2]: medians 4 and 2 -> scale 2 -> pred = [2, 6, 4]
    # abs_rel = (0 + 2/4 + 2/6)/3 = 0.2777...; rmse = sqrt((0 + 4 + 4)/3) = 1.632993
    # delta = [1, 1.5, 1.5] -> a1 = 1/3, a2 = a3 = 1
    m = depth_metrics(np.array([[2.0, 4.0, 6.0]]), np.array([[1.0, 3.0, 2.0]]), crop=None)
    assert m["scale"] == pytest.approx(2.0)
    assert m["abs_rel"] == pytest.approx(5.0 / 18.0)
    assert m["rmse"] == pytest.approx(math.sqrt(8.0 / 3.0))
    assert m["a1"] == pytest.approx(1.0 / 3.0)
    assert (m["a2"], m["a3"]) == (1.0, 1.0)


def test_median_scaling_invariance():
    rng = np.random.default_rng(0)
    gt = rng.uniform(1.0, 70.0, size=(6, 7))
    pred = gt * rng.uniform(0.7, 1.3, size=gt.shape)
    a = depth_metrics(gt, pred, crop=None)
    b = depth_metrics(gt, pred * 7.0, crop=None)
    assert b["scale"] == pytest.approx(a["scale"] / 7.0)
    for key in ("abs_rel", "sq_rel", "rmse", "rmse_log", "a1", "a2", "a3"):
        assert b[key] == pytest.approx(a[key], rel=1e-12, abs=1e-12)


def test_clamp_happens_after_median_scaling():
    # A net whose raw depths are all below min_depth = 1e-3 (unscaled monocular output):
    # gt = [1, 2, 3], pred = [1e-4, 2e-4, 3e-4].
    # Official (scale, then clamp): scale = 2/2e-4 = 1e4 -> pred = [1, 2, 3] -> abs_rel 0.
    # Wrong order (clamp, then scale): pred -> [1e-3]*3, scale 2000 -> [2, 2, 2]
    #   -> abs_rel = (1/1 + 0 + 1/3)/3 = 4/9. So this test fails for the wrong order.
    m = depth_metrics(np.array([[1.0, 2.0, 3.0]]), np.array([[1e-4, 2e-4, 3e-4]]), crop=None)
    assert m["abs_rel"] == pytest.approx(0.0, abs=1e-9)


def test_clamp_to_max_depth_after_scaling():
    # gt = [10, 20, 30], pred = [1, 2, 30]: scale = 20/2 = 10 -> [10, 20, 300] -> clamp 80
    # abs_rel = (0 + 0 + 50/30)/3 = 5/9
    m = depth_metrics(np.array([[10.0, 20.0, 30.0]]), np.array([[1.0, 2.0, 30.0]]), crop=None)
    assert m["abs_rel"] == pytest.approx(5.0 / 9.0)


def test_gt_range_is_exclusive():
    # gt exactly 80 is excluded (gt < max_depth is strict); gt 79.9 is kept.
    m = depth_metrics(np.array([[80.0, 79.9]]), np.array([[1.0, 79.9]]), crop=None, median_scaling=False)
    assert m["n_valid"] == 1 and m["abs_rel"] == pytest.approx(0.0)


def test_garg_crop_boundaries_on_kitti_size():
    # H = 375, W = 1242, truncated like np.int32:
    # rows: 0.40810811*375 = 153.04 -> 153 ; 0.99189189*375 = 371.96 -> 371  => rows 153..370
    # cols: 0.03594771*1242 = 44.65 -> 44 ; 0.96405229*1242 = 1197.35 -> 1197 => cols 44..1196
    mask = crop_mask((375, 1242), "garg")
    rows = np.flatnonzero(mask.any(axis=1))
    cols = np.flatnonzero(mask.any(axis=0))
    assert (rows[0], rows[-1], cols[0], cols[-1]) == (153, 370, 44, 1196)
    assert mask.sum() == (371 - 153) * (1197 - 44)


def test_eigen_crop_boundaries_on_kitti_size():
    # rows: 0.3324324*375 = 124.66 -> 124 ; 0.91351351*375 = 342.57 -> 342
    # cols: 0.0359477*1242 = 44.65 -> 44 ; 0.96405229*1242 = 1197.35 -> 1197
    mask = crop_mask((375, 1242), "eigen")
    rows = np.flatnonzero(mask.any(axis=1))
    cols = np.flatnonzero(mask.any(axis=0))
    assert (rows[0], rows[-1], cols[0], cols[-1]) == (124, 341, 44, 1196)


def test_garg_crop_applied_in_depth_metrics():
    gt = np.full((375, 1242), 10.0)
    pred = gt.copy()
    pred[152, 600] = 1.0  # one row above the crop: ignored
    pred[300, 43] = 1.0  # one column left of the crop: ignored
    pred[300, 1197] = 1.0  # first column right of the crop: ignored
    m = depth_metrics(gt, pred)
    assert m["abs_rel"] == 0.0
    assert m["n_valid"] == (371 - 153) * (1197 - 44)
    pred[153, 600] = 1.0  # first row inside: counted. Median unchanged (10) -> scale 1.
    m = depth_metrics(gt, pred)
    assert m["abs_rel"] == pytest.approx(0.9 / m["n_valid"])


def test_depth_shape_mismatch_is_a_clear_error():
    with pytest.raises(GeoNetError, match="resize_depth_to"):
        depth_metrics(np.ones((4, 4)), np.ones((2, 2)), crop=None)


def test_resize_depth_to_shape():
    out = resize_depth_to(np.ones((128, 416)) * 3.0, (375, 1242))
    assert out.shape == (375, 1242) and np.allclose(out, 3.0)


def test_aggregate_is_mean_over_images():
    out = aggregate([{"abs_rel": 0.1, "a1": 1.0}, {"abs_rel": 0.3, "a1": 0.0}])
    assert out["abs_rel"] == pytest.approx(0.2) and out["a1"] == pytest.approx(0.5) and out["count"] == 2


# --------------------------------------------------------------------------- flow
def test_flow_epe_and_outliers_on_hand_built_field():
    # 2x2 field:
    #  (0,0) gt (10,0)  pred (10,0)  -> epe 0
    #  (0,1) gt (3,4)   pred (3,0)   -> epe 4 > 3 and 4/5 = 0.8 > 0.05     -> outlier
    #  (1,0) gt (100,0) pred (104,0) -> epe 4 > 3 but 4/100 = 0.04 <= 0.05 -> not an outlier
    #  (1,1) invalid    pred (50,50) -> ignored
    # EPE = (0 + 4 + 4)/3 = 8/3; Fl = 1/3; ACC = 2/3
    gt = np.array([[[10, 0], [3, 4]], [[100, 0], [0, 0]]], dtype=float)
    pred = np.array([[[10, 0], [3, 0]], [[104, 0], [50, 50]]], dtype=float)
    valid = np.array([[True, True], [True, False]])
    out = flow_epe(gt, valid, pred)
    assert out["n_valid"] == 3
    assert out["epe"] == pytest.approx(8.0 / 3.0)
    assert out["fl"] == pytest.approx(1.0 / 3.0)
    assert out["acc"] == pytest.approx(2.0 / 3.0)


def test_flow_epe_exactly_3px_is_not_an_outlier():
    # epe = 3 exactly: the rule is EPE > 3 (strict).
    gt = np.zeros((1, 1, 2))
    pred = np.array([[[3.0, 0.0]]])
    assert flow_epe(gt, np.ones((1, 1), bool), pred)["fl"] == 0.0


def test_resize_flow_nearest_scales_vectors():
    # 2x2 -> 4x6: each source pixel becomes a 2x3 block; u x (6/2) = 3, v x (4/2) = 2.
    flow = np.zeros((2, 2, 2), np.float32)
    flow[..., 0] = [[1, 2], [3, 4]]
    flow[..., 1] = [[10, 20], [30, 40]]
    out = resize_flow_nearest(flow, (4, 6))
    assert out.shape == (4, 6, 2)
    expected_u = np.array([[3, 3, 3, 6, 6, 6]] * 2 + [[9, 9, 9, 12, 12, 12]] * 2)
    expected_v = np.array([[20, 20, 20, 40, 40, 40]] * 2 + [[60, 60, 60, 80, 80, 80]] * 2)
    np.testing.assert_array_equal(out[..., 0], expected_u)
    np.testing.assert_array_equal(out[..., 1], expected_v)


# --------------------------------------------------------------------------- pose
def test_ate_quirk_on_hand_computed_example():
    # gt = [(0,0,0), (1,0,0), (2,0,0)], pred = [(5,5,5), (6,5,5), (8,5,5)]
    # shift: offset = gt0 - pred0 = (-5,-5,-5) -> pred = [(0,0,0), (1,0,0), (3,0,0)]
    # scale = sum(gt*pred)/sum(pred^2) = (0 + 1 + 6)/(0 + 1 + 9) = 0.7
    # errors: 0, 0.7-1 = -0.3, 2.1-2 = 0.1 -> sum of squares = 0.10
    # quirk value = sqrt(0.10)/3 = 0.105409 ; true RMSE = sqrt(0.10/3) = 0.182574
    gt = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0]], float)
    pred = np.array([[5, 5, 5], [6, 5, 5], [8, 5, 5]], float)
    assert ate_snippet(gt, pred) == pytest.approx(math.sqrt(0.10) / 3)
    assert ate_rmse_true(gt, pred) == pytest.approx(math.sqrt(0.10 / 3))


def test_ate_is_zero_for_scaled_and_shifted_prediction():
    # Snippets are in their first frame's coordinates, so gt[0] = 0 (origin).
    rng = np.random.default_rng(1)
    gt = np.vstack([np.zeros(3), rng.normal(size=(4, 3))])
    pred = gt * 0.37 + np.array([4.0, -2.0, 9.0])
    assert ate_snippet(gt, pred) == pytest.approx(0.0, abs=1e-12)
    assert ate_rmse_true(gt, pred) == pytest.approx(0.0, abs=1e-12)


def test_ate_quirk_relation_to_true_rmse():
    rng = np.random.default_rng(2)
    gt = np.vstack([np.zeros(3), rng.normal(size=(4, 3))])
    pred = gt + rng.normal(scale=0.1, size=gt.shape)
    assert ate_snippet(gt, pred) == pytest.approx(ate_rmse_true(gt, pred) / math.sqrt(5))


def _rot_z(angle):
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def _rigid(R, t):
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def test_rigid_inverse_closed_form():
    T = _rigid(_rot_z(0.3), [1.0, 2.0, 3.0])
    np.testing.assert_allclose(rigid_inverse(T) @ T, np.eye(4), atol=1e-12)
    np.testing.assert_allclose(rigid_inverse(np.stack([T, T]))[1], np.linalg.inv(T), atol=1e-12)


def test_snippet_poses_to_global_hand_example():
    # 3 frames, target in the middle. Target->frame transforms are pure translations:
    # T_0 = translate(+1, 0, 0), T_1 = I (target), T_2 = translate(-1, 0, 0).
    # G_p = T_0 @ inv(T_p): G_0 = I, G_1 = translate(+1,0,0), G_2 = translate(+2,0,0).
    T0 = _rigid(np.eye(3), [1, 0, 0])
    T2 = _rigid(np.eye(3), [-1, 0, 0])
    G = snippet_poses_to_global(np.stack([T0, T2]), target_index=1)
    assert G.shape == (3, 4, 4)
    np.testing.assert_allclose(G[0], np.eye(4), atol=1e-12)
    np.testing.assert_allclose(G[1][:3, 3], [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(G[2][:3, 3], [2, 0, 0], atol=1e-12)


def test_snippet_poses_to_global_with_rotation_matches_general_inverse():
    Ts = np.stack([_rigid(_rot_z(a), [a, 2 * a, -a]) for a in (0.1, 0.0, -0.2, 0.4, 0.05)])
    G = snippet_poses_to_global(Ts)
    expected = np.stack([Ts[0] @ np.linalg.inv(T) for T in Ts])
    np.testing.assert_allclose(G, expected, atol=1e-12)


def test_ate_zero_motion_prediction_is_not_fitted_to_gt_rounding_noise():
    # GT whose first position is 1e-9 (text rounding), a prediction standing still:
    # the scale stays 1, so the error is the GT path itself (hand-computed).
    gt = np.array([[1e-9, 0, 0], [0, 0, 1.0], [0, 0, 2.0]])
    pred = np.zeros((3, 3))
    expected = math.sqrt(1.0 + 4.0) / 3  # errors (0,0,-1) and (0,0,-2) after the shift by gt[0]
    assert ate_snippet(gt, pred) == pytest.approx(expected, rel=1e-6)

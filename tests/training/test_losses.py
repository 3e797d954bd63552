import math

import torch

from training.losses import dssim, edge_aware_smoothness, flow_endpoint_error, masked_mean, photometric_error, ssim


def rand(*shape, seed=0):
    return torch.rand(*shape, generator=torch.Generator().manual_seed(seed)) * 2 - 1


def test_ssim_of_identical_images_is_one():
    x = rand(2, 3, 16, 20)
    assert torch.allclose(ssim(x, x), torch.ones_like(x), atol=1e-6)
    assert dssim(x, x).abs().max() < 1e-6
    assert photometric_error(x, x).abs().max() < 1e-6


def test_ssim_border_windows_exclude_padding():
    # A constant image has SSIM 1 everywhere only if border means ignore the zero padding.
    x = torch.full((1, 1, 5, 5), 0.7)
    y = torch.full((1, 1, 5, 5), 0.7)
    assert torch.allclose(ssim(x, y), torch.ones(1, 1, 5, 5), atol=1e-6)


def test_ssim_of_constant_images_by_hand():
    # Constant a vs b: sigmas are 0, so SSIM = (2ab + C1) / (a^2 + b^2 + C1).
    a, b, C1 = 0.5, -0.25, 0.01**2
    s = ssim(torch.full((1, 1, 4, 4), a), torch.full((1, 1, 4, 4), b))
    assert torch.allclose(s, torch.full_like(s, (2 * a * b + C1) / (a * a + b * b + C1)), atol=1e-6)


def test_photometric_error_weights():
    # Constant images: DSSIM from the hand formula above, L1 = |a - b|.
    a, b, C1 = 0.5, -0.25, 0.01**2
    x, y = torch.full((1, 3, 4, 4), a), torch.full((1, 3, 4, 4), b)
    s = (2 * a * b + C1) / (a * a + b * b + C1)
    expected = 0.85 * (1 - s) / 2 + 0.15 * abs(a - b)
    assert torch.allclose(photometric_error(x, y), torch.full_like(x, expected), atol=1e-6)


def test_smoothness_of_constant_field_is_zero():
    assert edge_aware_smoothness(torch.full((2, 1, 8, 8), 3.0), rand(2, 3, 8, 8)).item() == 0.0
    assert edge_aware_smoothness(torch.full((2, 2, 8, 8), -1.5), rand(2, 3, 8, 8)).item() == 0.0


def test_smoothness_ramp_by_hand():
    # field = x (ramp of slope 1), flat image -> weights 1: x-term = 1, y-term = 0.
    field = torch.arange(6.0).expand(1, 1, 4, 6)
    assert abs(edge_aware_smoothness(field, torch.zeros(1, 3, 4, 6)).item() - 1.0) < 1e-6
    # An image edge with |dI| = 2 on every channel damps the x-term to exp(-2).
    image = torch.arange(6.0).mul(2).expand(1, 3, 4, 6)
    assert abs(edge_aware_smoothness(field, image).item() - torch.exp(torch.tensor(-2.0)).item()) < 1e-6


def test_masked_mean_by_hand():
    values = torch.tensor([[[[1.0, 2.0], [3.0, 4.0]], [[3.0, 4.0], [5.0, 6.0]]]])  # channel means 2,3,4,5
    mask = torch.tensor([[[[1.0, 0.0], [0.0, 1.0]]]])
    assert masked_mean(values, mask).item() == (2.0 + 5.0) / 2
    assert masked_mean(values, torch.zeros_like(mask)).item() == 0.0


def test_scale_invariant_log_error_by_hand():
    from training.losses import scale_invariant_log_error

    gt = torch.tensor([[[[2.0, 4.0, 0.0]]], [[[1.0, 1.0, 1.0]]], [[[0.0, 0.0, 0.0]]]])  # 0 = no ground truth
    # image 0: log ratios (0, 2) on its two GT pixels -> mean 1, mean square 2, spread sqrt(2 - 1) = 1
    # image 1: the ground truth times 7 everywhere -> 0 (one global scale is free)
    # image 2: no ground truth -> left out of the mean, whatever is predicted
    pred = torch.tensor(
        [[[[2.0, 4.0 * torch.e**2, 123.0]]], [[[7.0, 7.0, 7.0]]], [[[5.0, 0.1, 9.0]]]], dtype=torch.float32
    )
    value = scale_invariant_log_error(pred, gt)
    torch.testing.assert_close(value, torch.tensor((1.0 + 0.0) / 2), atol=1e-4, rtol=0)
    assert float(scale_invariant_log_error(pred[2:], gt[2:])) == 0.0
    pred.requires_grad_(True)
    scale_invariant_log_error(pred, gt).backward()
    assert torch.isfinite(pred.grad).all() and pred.grad[2].abs().sum() == 0 and pred.grad[0, 0, 0, 2] == 0


# --------------------------------------------------------------------------- flow supervision
def test_flow_endpoint_error_closed_form():
    gt = torch.zeros(2, 3, 8, 12)
    gt[:, 0], gt[:, 1], gt[:, 2] = 2.0, -1.0, 1.0
    exact = gt[:, :2].clone()
    assert float(flow_endpoint_error(exact, gt)) < 1e-3
    # off by (3, 4) px everywhere: EPE 5
    torch.testing.assert_close(
        flow_endpoint_error(exact + torch.tensor([3.0, 4.0]).view(1, 2, 1, 1), gt), torch.tensor(5.0)
    )
    # half resolution: (1, -0.5) px there is (2, -1) px at 8x12, so exact again
    half = torch.empty(2, 2, 4, 6)
    half[:, 0], half[:, 1] = 1.0, -0.5
    assert float(flow_endpoint_error(half, gt)) < 1e-3
    # only valid pixels count, and an image without any is left out of the mean
    off = exact.clone()
    off[:, 0, :, :6] += 10.0
    gt_left_invalid = gt.clone()
    gt_left_invalid[:, 2, :, :6] = 0.0
    assert float(flow_endpoint_error(off, gt_left_invalid)) < 1e-3
    gt_left_invalid[1, 2] = 0.0
    off[0] += 1.0  # image 0: EPE sqrt(2) on its valid pixels; image 1 has none
    torch.testing.assert_close(flow_endpoint_error(off, gt_left_invalid), torch.tensor(2.0**0.5))


def _motion(angle_z: float, t) -> torch.Tensor:
    """4x4 rotation about z by ``angle_z`` radians, then translation ``t``."""
    c, s = torch.cos(torch.tensor(angle_z)), torch.sin(torch.tensor(angle_z))
    T = torch.eye(4)
    T[:2, :2] = torch.tensor([[c, -s], [s, c]])
    T[:3, 3] = torch.tensor(t, dtype=torch.float32)
    return T


def test_scale_aligned_pose_error_closed_form():
    from training.losses import scale_aligned_pose_error

    truth = torch.stack([_motion(0.0, [0, 0, -1.0]), _motion(0.0, [0, 0, 1.0])])[None]  # (1, 2, 4, 4)
    # the same motion at a third of the scale: a monocular net's scale is free, so no error
    third = truth.clone()
    third[..., :3, 3] /= 3
    assert scale_aligned_pose_error(third, truth).item() < 1e-6
    # a rotation of theta about z on both sources: chordal ||R - I||_F = 2 sqrt(2) sin(theta / 2)
    theta = 0.1
    rotated = torch.stack([_motion(theta, [0, 0, -1.0]), _motion(theta, [0, 0, 1.0])])[None]
    expected = 2 * 2**0.5 * torch.sin(torch.tensor(theta / 2))
    torch.testing.assert_close(scale_aligned_pose_error(rotated, truth), expected)
    # translations at right angles to the truth: the aligned scale is 0, error = path / path = 1
    sideways = truth.clone()
    sideways[..., :3, 3] = torch.tensor([[1.0, 0, 0], [-1.0, 0, 0]])
    torch.testing.assert_close(scale_aligned_pose_error(sideways, truth), torch.tensor(1.0))
    # a snippet without true poses (zeros) adds nothing and does not count
    both = torch.cat([sideways, torch.zeros_like(truth)])
    torch.testing.assert_close(
        scale_aligned_pose_error(both, torch.cat([truth, torch.zeros_like(truth)])), torch.tensor(1.0)
    )
    assert scale_aligned_pose_error(sideways, torch.zeros_like(truth)).item() == 0.0


def test_a_still_snippet_is_taught_to_predict_no_motion():
    """Identity labels (a still camera, issue 53): the error is the predicted path over the batch's
    mean moving step, whatever the scale; zero for a zero prediction; the gradient shrinks t."""
    from training.losses import STILL_REF_STEP, scale_aligned_pose_error

    moving_truth = torch.stack([_motion(0.0, [0, 0, -1.0]), _motion(0.0, [0, 0, 1.0])])[None]
    moving_pred = moving_truth.clone()
    moving_pred[..., :3, 3] *= 0.2  # the net's unit: steps of 0.2
    still_truth = torch.eye(4).expand(1, 2, 4, 4).clone()
    still_pred = torch.stack([_motion(0.0, [0, 0, -0.05]), _motion(0.0, [0, 0, 0.05])])[None].requires_grad_()
    error = scale_aligned_pose_error(torch.cat([moving_pred, still_pred]), torch.cat([moving_truth, still_truth]))
    # moving snippet: 0 (exact up to scale); still one: path 0.1 over 2 steps of 0.2 -> 0.25; mean of two
    torch.testing.assert_close(error, torch.tensor(0.125))
    error.backward()
    assert still_pred.grad[0, 0, 2, 3] < 0 < still_pred.grad[0, 1, 2, 3]  # descent moves -0.05 and 0.05 toward 0
    # alone in its batch: the bundled model's step is the unit; a zero prediction has no error
    torch.testing.assert_close(
        scale_aligned_pose_error(still_pred.detach(), still_truth), torch.tensor(0.1 / (2 * STILL_REF_STEP))
    )
    assert scale_aligned_pose_error(still_truth, still_truth).item() == 0.0


def test_speed_error_sees_the_jitter_the_scale_aligned_error_forgives():
    """Issue 53, round 4: two snippets at the same true speed, predicted at 0.1 and 0.2 per step. Each is
    exact up to its own scale (scale-aligned error 0); under one unit for both the speeds disagree."""
    from training.losses import SpeedUnit, path_lengths, scale_aligned_pose_error, speed_error

    truth = torch.stack([_motion(0.0, [0, 0, -1.0]), _motion(0.0, [0, 0, 1.0])])[None].repeat(2, 1, 1, 1)
    pred = truth.clone()
    pred[0, :, :3, 3] *= 0.1
    pred[1, :, :3, 3] *= 0.2
    assert scale_aligned_pose_error(pred, truth).item() < 1e-6
    paths = path_lengths(pred, truth)
    torch.testing.assert_close(paths[0], torch.tensor([0.2, 0.4]))
    torch.testing.assert_close(paths[1], torch.tensor([2.0, 2.0]))
    # unit 10 (true metres per predicted unit): errors |2 - 2| / 2 = 0 and |4 - 2| / 2 = 1 -> mean 0.5
    torch.testing.assert_close(speed_error(*paths, torch.tensor(10.0)), torch.tensor(0.5))
    # the run's unit from this batch: least squares sum(t p) / sum(p^2) = (0.4 + 0.8) / (0.04 + 0.16) = 6;
    # its mean moving path (0.2 + 0.4) / 2 = 0.3
    run = SpeedUnit(momentum=0.9)
    unit, path = run.update(*paths)
    torch.testing.assert_close((unit, path), (torch.tensor(6.0), torch.tensor(0.3)))
    # a second batch at exactly 10 (paths 0.2) moves both a tenth of the way: 6.4 and 0.29
    slow = truth.clone()
    slow[..., :3, 3] *= 0.1
    unit, path = run.update(*path_lengths(slow, truth))
    torch.testing.assert_close((unit, path), (torch.tensor(6.4), torch.tensor(0.29)))
    # still snippets (identity truth) and snippets without truth (zeros) neither count nor move the unit
    others = torch.cat([torch.eye(4).expand(1, 2, 4, 4), torch.zeros(1, 2, 4, 4)])
    still_paths = path_lengths(pred, others)
    assert still_paths[2].sum().item() == 0.0
    assert speed_error(*still_paths, torch.tensor(10.0)).item() == 0.0
    torch.testing.assert_close(run.update(*still_paths), (torch.tensor(6.4), torch.tensor(0.29)))
    assert SpeedUnit().update(*still_paths) == (torch.tensor(1.0), None)


def test_a_still_batch_is_measured_against_the_runs_step():
    """Round 4's scale collapse: a batch of still snippets alone was measured against the constant
    STILL_REF_STEP, which shrinks every step whatever the net's unit; given the run's step it is not."""
    from training.losses import STILL_REF_STEP, scale_aligned_pose_error

    still_truth = torch.eye(4).expand(1, 2, 4, 4).clone()
    still_pred = torch.stack([_motion(0.0, [0, 0, -0.05]), _motion(0.0, [0, 0, 0.05])])[None]
    torch.testing.assert_close(
        scale_aligned_pose_error(still_pred, still_truth), torch.tensor(0.1 / (2 * STILL_REF_STEP))
    )
    # the run's step 0.5: path 0.1 over 2 steps of 0.5
    torch.testing.assert_close(
        scale_aligned_pose_error(still_pred, still_truth, still_ref_step=torch.tensor(0.5)), torch.tensor(0.1)
    )


def test_pose_keep_error_closed_form():
    """Issue 53, round 6: zero for the starting motion; a 0.1 sideways offset on both steps of a
    2-unit path is 0.2 / 2; a rotation of theta adds 2 sqrt(2) sin(theta / 2); unkept snippets add nothing."""
    from training.losses import pose_keep_error

    start = torch.stack([_motion(0.0, [0, 0, -1.0]), _motion(0.0, [0, 0, 1.0])])[None]
    keep = torch.ones(1)
    assert pose_keep_error(start, start, keep).item() == 0.0
    shifted = start.clone()
    shifted[..., 0, 3] += 0.1
    torch.testing.assert_close(pose_keep_error(shifted, start, keep), torch.tensor(0.1))
    theta = 0.1
    turned = torch.stack([_motion(theta, [0, 0, -1.0]), _motion(theta, [0, 0, 1.0])])[None]
    torch.testing.assert_close(pose_keep_error(turned, start, keep), 2 * 2**0.5 * torch.sin(torch.tensor(theta / 2)))
    both = torch.cat([shifted, turned])
    torch.testing.assert_close(
        pose_keep_error(both, torch.cat([start, start]), torch.tensor([1.0, 0.0])), torch.tensor(0.1)
    )
    assert pose_keep_error(shifted, start, torch.zeros(1)).item() == 0.0


def test_pose_keep_error_scale_free_closed_form():
    """Issue 53, round 8: the shape-only pull ignores each snippet's speed (a motion 3x as fast, or a
    tenth as fast, costs nothing) but not its directions: the first step turned from -z to +x on a
    path of 2 units moves its normalised translation from (0, 0, -1/2) to (1/2, 0, 0), |.| = sqrt(2)/2."""
    from training.losses import pose_keep_error

    start = torch.stack([_motion(0.0, [0, 0, -1.0]), _motion(0.0, [0, 0, 1.0])])[None]
    keep = torch.ones(1)
    for speed in (3.0, 0.1):
        faster = start.clone()
        faster[..., :3, 3] *= speed
        assert pose_keep_error(faster, start, keep, scale_free=True).item() < 1e-6
        assert pose_keep_error(faster, start, keep).item() > 0.5  # round 6's term holds the speed
    sideways = torch.stack([_motion(0.0, [3.0, 0, 0]), _motion(0.0, [0, 0, 3.0])])[None]  # and 3x as fast
    torch.testing.assert_close(pose_keep_error(sideways, start, keep, scale_free=True), torch.tensor(2**0.5 / 2))


def test_steady_speed_error_closed_form():
    """Issue 53, round 10: steps taken in time order around the target. A constant 1-unit step costs
    nothing, moving or standing; steps of 1 and 3 (previous frame 1 behind, next frame 3 ahead) spread
    1 from their mean 2, so the error is 1 / 2 of its own mean step, and 1 / 10 against a reference step
    of 10; a still snippet of near-zero steps pays little against a moving reference."""
    from training.losses import steady_speed_error

    steady = torch.stack([_motion(0.0, [0, 0, -1.0]), _motion(0.0, [0, 0, 1.0])])[None]
    assert steady_speed_error(steady).item() < 1e-6
    uneven = torch.stack([_motion(0.0, [0, 0, -1.0]), _motion(0.0, [0, 0, 3.0])])[None]
    torch.testing.assert_close(steady_speed_error(uneven), torch.tensor(0.5))
    torch.testing.assert_close(steady_speed_error(uneven, torch.tensor(10.0)), torch.tensor(0.1))
    seq5 = torch.stack(
        [_motion(0.0, [0, 0, -2.0]), _motion(0.0, [0, 0, -1.0]), _motion(0.0, [0, 0, 1.0]), _motion(0.0, [0, 0, 2.0])]
    )[None]  # four steps of 1
    assert steady_speed_error(seq5).item() < 1e-6
    still = uneven.clone()
    still[..., :3, 3] *= 1e-3
    assert steady_speed_error(still, torch.tensor(1.0)).item() < 1e-3


def test_batch_reference_step_is_half_the_median_snippet_step():
    """The reference of --pose-steady: half the median over the batch of each snippet's mean step between
    consecutive frames, for 3- and 5-frame snippets alike (5 frames 2 units apart: 1, not the 1.5 of the
    mean distance from the target, which the term used before and which equals the step for 3 frames only)."""
    from training.losses import batch_reference_step

    def snippet(step: float, n_sources: int) -> torch.Tensor:
        k = n_sources // 2
        offsets = [-(k - i) for i in range(k)] + [i + 1 for i in range(k)]
        return torch.stack([_motion(0.0, [0, 0, step * o]) for o in offsets])

    seq3 = torch.stack([snippet(s, 2) for s in (1.0, 2.0, 4.0)])  # mean steps 1, 2, 4: median 2
    torch.testing.assert_close(batch_reference_step(seq3), torch.tensor(1.0))
    seq5 = torch.stack([snippet(2.0, 4)] * 3)
    torch.testing.assert_close(batch_reference_step(seq5), torch.tensor(1.0))


def test_stride_ratio_error_is_zero_at_twice_the_step_and_log_squared_off_it():
    """--pose-stride: a stride-2 snippet whose translations are twice its twin's pays 0 whatever the rotation
    and direction; the same step pays (log 2)^2 (a speed-blind PoseNet); three times pays (log 1.5)^2;
    the mean is over snippets and sources."""
    from training.losses import stride_ratio_error

    def snippet(step: float, angle: float = 0.0) -> torch.Tensor:
        return torch.stack([_motion(angle, [0.1 * step, 0, -step]), _motion(-angle, [0, 0.2 * step, step])])

    slow = torch.stack([snippet(0.7), snippet(1.3)])
    torch.testing.assert_close(
        stride_ratio_error(torch.stack([snippet(1.4, 0.3), snippet(2.6)]), slow), torch.tensor(0.0)
    )
    blind = stride_ratio_error(slow.clone(), slow)
    torch.testing.assert_close(blind, torch.tensor(math.log(2.0) ** 2))
    mixed = stride_ratio_error(torch.stack([snippet(1.4), snippet(3.9)]), slow)  # 2x and 3x
    torch.testing.assert_close(mixed, torch.tensor(math.log(1.5) ** 2 / 2))


def test_overlap_step_error_compares_the_shared_step_of_two_neighbouring_snippets():
    """--pose-overlap: snippet t (sources t-1, t+1) and snippet t+1 (sources t, t+2) share the step
    t -> t+1: it is T_this[:, 1] and the inverse of T_next[:, 0], a motion and its inverse having
    translations of the same length. Equal lengths pay 0 whatever the rotations and the other steps;
    a step 1.5 times as long pays (log 1.5)^2; the mean is over snippets."""
    from training.geometry import invert_rigid
    from training.losses import overlap_step_error

    shared = _motion(0.2, [0.1, 0.05, 0.9])  # t -> t+1
    this = torch.stack([_motion(-0.1, [0, 0, -0.5]), shared])[None]  # t -> t-1 (another length), t -> t+1
    back = invert_rigid(shared[None])[0]  # t+1 -> t
    following = torch.stack([back, _motion(0.3, [0.2, 0, 2.0])])[None]  # t+1 -> t, t+1 -> t+2
    torch.testing.assert_close(overlap_step_error(this, following), torch.tensor(0.0), atol=1e-10, rtol=0)
    longer = following.clone()
    longer[0, 0, :3, 3] *= 1.5
    torch.testing.assert_close(overlap_step_error(this, longer), torch.tensor(math.log(1.5) ** 2))
    batch = overlap_step_error(torch.cat([this, this]), torch.cat([following, longer]))
    torch.testing.assert_close(batch, torch.tensor(math.log(1.5) ** 2 / 2))


def test_motion_labels_call_identity_true_poses_still_and_every_other_snippet_moving():
    """Round 19's gate labels: a snippet with identity true poses (a still copy, a synthetic stop) is still;
    true poses that move, and no true poses at all (driving footage, all zeros), are moving."""
    from training.losses import motion_labels

    still = torch.eye(4).expand(2, 4, 4)
    moving = still.clone()
    moving[1, 2, 3] = 0.8  # the camera 0.8 m ahead at the second source
    none = torch.zeros(2, 4, 4)
    assert motion_labels(torch.stack([still, moving, none])).tolist() == [0.0, 1.0, 1.0]


def test_gate_error_is_the_cross_entropy_of_the_gate_probability():
    from training.losses import gate_error

    logits, labels = torch.tensor([2.0, -1.0]), torch.tensor([1.0, 0.0])
    p = [1 / (1 + math.exp(-2.0)), 1 / (1 + math.exp(1.0))]  # sigmoid by hand
    expected = -(math.log(p[0]) + math.log(1 - p[1])) / 2
    assert abs(float(gate_error(logits, labels)) - expected) < 1e-6

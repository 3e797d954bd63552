"""``--output-size network`` (issue 54): depth and flow left at the network's size, nothing interpolated.

Golden values: the input-size outputs are the network-size ones resized with OpenCV (disparity bilinear,
depth its inverse; flow bilinear with u, v scaled by the size ratio), so resizing what the network mode
wrote, here, must give what the input mode wrote; K scales by the same ratios (closed form).
"""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

import geonet_infer
from geonet_infer.cli import main
from geonet_infer.errors import InputError
from geonet_infer.io import list_images, read_camera, read_flow_kitti


@pytest.fixture(scope="module")
def both(tmp_path_factory, kitti_raw):
    root = tmp_path_factory.mktemp("size")
    frames = list_images(kitti_raw / "image_02" / "data")[:5]
    folder = root / "frames"
    folder.mkdir()
    for f in frames:
        (folder / f.name).symlink_to(f)
    calib = str(kitti_raw / "calib_cam_to_cam.txt")
    for mode in ("input", "network"):
        args = ["predict", str(folder), "--out", str(root / mode), "--calib", calib, "--output-size", mode]
        assert main([*args, "--no-progress", "--quiet"]) == 0
    return root


def test_network_outputs_resized_here_are_the_input_outputs(both):
    summary = json.loads((both / "network" / "summary.json").read_text())
    assert summary["output_size"]["mode"] == "network" and summary["output_size"]["size"] == [416, 128]
    to_x, to_y = summary["output_size"]["to_input"]
    assert (to_x, to_y) == pytest.approx((1242 / 416, 375 / 128))
    for name in ("0000000000", "0000000002"):
        small = np.load(both / "network" / "depth" / f"{name}.npy")
        full = np.load(both / "input" / "depth" / f"{name}.npy")
        assert small.shape == (128, 416) and full.shape == (375, 1242)
        resized = 1.0 / cv2.resize(1.0 / small, (1242, 375), interpolation=cv2.INTER_LINEAR)
        np.testing.assert_allclose(resized, full, rtol=1e-5)
        flow_small, valid_small = read_flow_kitti(both / "network" / "flow" / f"{name}.png")
        flow_full, _ = read_flow_kitti(both / "input" / "flow" / f"{name}.png")
        assert flow_small.shape == (128, 416, 2) and valid_small.all()
        up = cv2.resize(flow_small, (1242, 375), interpolation=cv2.INTER_LINEAR) * [to_x, to_y]
        # KITTI PNG steps of 1/64 px, each side rounded: within 1/64 * (1 + the scale)
        np.testing.assert_allclose(up, flow_full, atol=(1 + max(to_x, to_y)) / 64 + 1e-6)
    same = [p.name for p in (both / "input").iterdir()]
    assert sorted(same) == sorted(p.name for p in (both / "network").iterdir())  # the same files, smaller
    np.testing.assert_array_equal(
        np.loadtxt(both / "input" / "poses_kitti.txt"), np.loadtxt(both / "network" / "poses_kitti.txt")
    )


def test_the_api_scales_k_with_the_outputs(kitti_raw):
    frames = list_images(kitti_raw / "image_02" / "data")[:3]
    camera = read_camera(kitti_raw / "calib_cam_to_cam.txt")
    result = next(iter(geonet_infer.load().iter_sequence(frames, camera, output_size="network")))
    K = camera.K
    expected = np.array(
        [[K[0, 0] * 416 / 1242, 0, K[0, 2] * 416 / 1242], [0, K[1, 1] * 128 / 375, K[1, 2] * 128 / 375], [0, 0, 1]]
    )
    np.testing.assert_allclose(result.intrinsics, expected, rtol=1e-9)
    assert result.depth.shape == (128, 416) and result.flow.shape == (128, 416, 2)
    with pytest.raises(InputError, match="DIS and ORB-VO"):
        geonet_infer.load().iter_sequence(frames, camera, output_size="network", flow_method="dis")
    with pytest.raises(InputError, match="unknown output size"):
        geonet_infer.load().iter_sequence(frames, camera, output_size="half")

"""The bundled model sees a stop (issue 53): a still clip gives a near-identity pose and a near-zero rigid flow.

The still clip is one real frame (KITTI odometry 06 frame 12, grey, a frame no training used) and
five copies of it made here: each shifted by at most a quarter pixel (OpenCV warpAffine) and given
Gaussian noise of 2 grey levels, the jitter and noise of a camera standing with its engine running.
The moving clip is frames 0-5 of the same sequence (the car drives about 0.9 m a frame).

Thresholds (written here, not fitted to the model): the still clip's median step is at most a third of
the moving clip's, the issue's bar for stopped stretches; its rigid flow's median length is at most a
third of the moving clip's and under 1 input pixel.
"""

from __future__ import annotations

import cv2
import numpy as np

import geonet_infer
from geonet_infer.io import list_images, read_camera, read_image

STILL_COPIES = 5


def still_clip(frame: np.ndarray) -> list[np.ndarray]:
    rng = np.random.default_rng(53)
    h, w = frame.shape[:2]
    copies = [frame]
    for _ in range(STILL_COPIES):
        dx, dy = rng.uniform(-0.25, 0.25, size=2) * (w / 416)  # a quarter pixel at the network's size
        shifted = cv2.warpAffine(frame, np.float32([[1, 0, dx], [0, 1, dy]]), (w, h), borderMode=cv2.BORDER_REFLECT)
        noisy = shifted.astype(np.float32) + rng.normal(0, 2.0, size=shifted.shape)
        copies.append(np.clip(np.rint(noisy), 0, 255).astype(np.uint8))
    return copies


def steps_and_rigid(predictor, frames, camera) -> tuple[float, float]:
    results = list(predictor.iter_sequence(frames, camera))
    centres = np.array([r.camera_to_world[:3, 3] for r in results])
    steps = np.linalg.norm(np.diff(centres, axis=0), axis=1)
    rigid = [np.linalg.norm(r.rigid_flow, axis=-1) for r in results if r.flow is not None]
    return float(np.median(steps)), float(np.median(np.concatenate([x.ravel() for x in rigid])))


def test_a_still_clip_gives_a_near_identity_pose_and_near_zero_rigid_flow(kitti_odometry_06):
    seq = kitti_odometry_06 / "sequences" / "06"
    camera = read_camera(seq / "calib.txt", "P0")
    images = list_images(seq / "image_0")  # frames 0-50 (the colour folder holds four)
    predictor = geonet_infer.load()
    moving_step, moving_rigid = steps_and_rigid(predictor, [read_image(p) for p in images[:6]], camera)
    still_step, still_rigid = steps_and_rigid(predictor, still_clip(read_image(images[12])), camera)
    assert moving_rigid > 2.0  # the yardstick moves
    assert still_step <= moving_step / 3
    assert still_rigid <= moving_rigid / 3 and still_rigid < 1.0

"""The adaptation recipe runs as written on a real dashcam clip and yields a loadable model.

Two fine-tuning steps per stage keep it short: this checks the plumbing (prepare -> stage rigid
from the published weights -> combine -> stage flow -> export -> geonet_infer.load), not accuracy.
"""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch

import geonet_infer
from geonet_infer.io import list_images, read_camera
from training.checkpoint import load_checkpoint, load_weights

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.slow
def test_adapt_to_clip_script_on_a_real_clip(realdata, tmp_path):
    clip = realdata / "udacity_dashcam" / "test_video.mp4"
    calib = realdata / "udacity_dashcam" / "calib_advanced_lane_lines.txt"
    out = tmp_path / "adapt"
    env = {**os.environ, "STEPS": "2", "FLOW_STEPS": "2", "PRECISION": "fp32"}
    proc = subprocess.run(
        ["bash", "scripts/adapt_to_clip.sh", str(clip), str(calib), str(out), "0,229,1280,394"],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    # the flow stage started from the published ResFlowNet and the fine-tuned DepthNet/PoseNet
    combined = load_weights(out / "combined.pt")
    published = load_weights(ROOT / "weights" / "small_synth.pt")
    rigid = load_checkpoint(out / "rigid" / "last.pt")
    flow_keys = [k for k in published["model"] if k.startswith("flow_net.") and published["model"][k].dim() == 4]
    assert flow_keys and all(torch.equal(combined["model"][k], published["model"][k]) for k in flow_keys)
    depth_keys = [k for k in rigid["model"] if k.startswith("depth_net.") and rigid["model"][k].dim() == 4]
    assert all(torch.allclose(combined["model"][k], rigid["model"][k], rtol=1e-3, atol=1e-4) for k in depth_keys)
    # the model directory loads in the runtime and predicts on the clip's own frames
    manifest = json.loads((out / "model" / "manifest.json").read_text())
    assert manifest["provenance"]["checkpoint_stage"] == "flow"
    predictor = geonet_infer.load(out / "model")
    frames = list_images(out / "data" / ".frames" / "test_video")[:3]
    K = read_camera(calib).K.copy()
    K[1, 2] -= 229
    K = K * np.array([[416 / 1280], [128 / 394], [1]])  # crop, then 1280x394 -> 416x128, by hand
    seq = predictor.predict_sequence(frames, camera=K)
    assert seq.depth.shape == (3, 128, 416) and np.isfinite(seq.depth).all() and (seq.depth > 0).all()
    assert seq.flow.shape == (2, 128, 416, 2) and np.isfinite(seq.flow).all()

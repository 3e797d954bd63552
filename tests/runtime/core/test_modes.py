"""Latency and throughput modes (issue 54): the same frames, in order, within the rigid op's bound.

Throughput mode computes a sequence's batches on several threads at once, each graph call on one thread.
The batches, so the graph calls, are those of latency mode: the outputs must match latency mode's to float
rounding; with the numpy rigid op the flow moves by what the op's own bound allows once ResFlowNet has seen
it (measured 5e-4 px on the drive).
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import geonet_infer as gi
from geonet_infer.errors import InputError

DRIVE = Path(__file__).resolve().parents[3] / "../shared/realdata/kitti_raw_2011_09_26_sfnd"
FRAMES = sorted((DRIVE / "image_02" / "data").glob("*.png"))[:7]  # batches of 2: 4 batches, the last one short
K = np.array([[721.5377, 0, 609.5593], [0, 721.5377, 172.854], [0, 0, 1]])
NUMPY_OP_FLOW_PX = 5e-3  # the numpy op's rigid flow is within 2e-4 px of the graph's; ResFlowNet sees it

pytestmark = pytest.mark.skipif(not FRAMES, reason="../shared/realdata/kitti_raw_2011_09_26_sfnd missing")


@pytest.fixture(scope="module")
def latency():
    return list(gi.load(mode="latency").iter_sequence(FRAMES, K, batch_size=2))


def _compare(a, b, flow_px: float) -> None:
    assert [r.index for r in b] == list(range(len(FRAMES)))
    assert [r.name for r in a] == [r.name for r in b]
    for x, y in zip(a, b):
        np.testing.assert_allclose(y.depth, x.depth, rtol=1e-5)
        np.testing.assert_allclose(y.camera_to_world, x.camera_to_world, atol=1e-5)
        np.testing.assert_array_equal(y.intrinsics, x.intrinsics)
        if x.flow is None:
            assert y.flow is None and x.index == len(FRAMES) - 1
            continue
        assert np.abs(y.flow - x.flow).max() <= flow_px
        assert (x.check is None) == (y.check is None)


def test_throughput_mode_gives_latency_modes_outputs(latency):
    if gi.engines.usable_cpus() < 2:
        pytest.skip("one usable CPU: throughput mode has one worker")
    predictor = gi.load(mode="throughput", threads=2)
    assert predictor.workers == 2
    _compare(latency, list(predictor.iter_sequence(FRAMES, K, batch_size=2)), flow_px=1e-4)


def test_throughput_mode_with_the_numpy_op_within_its_bound(latency):
    predictor = gi.load(mode="throughput", rigid_op="numpy")
    assert predictor.engines["rigidflow"] == "numpy"
    _compare(latency, list(predictor.iter_sequence(FRAMES, K, batch_size=2)), flow_px=NUMPY_OP_FLOW_PX)


def test_a_consumer_that_stops_early_and_a_bad_frame_mid_sequence(tmp_path):
    predictor = gi.load(mode="throughput")
    results = predictor.iter_sequence(FRAMES, K, batch_size=1)
    assert next(results).index == 0
    results.close()  # the pool shuts down with work queued: no hang, no error
    bad = tmp_path / "0000000005.png"
    bad.write_bytes(b"not a png")
    frames = [*FRAMES[:5], bad, *FRAMES[6:]]
    with pytest.raises(InputError, match="0000000005.png"):
        list(predictor.iter_sequence(frames, K, batch_size=1))


def test_an_unknown_mode_is_refused():
    with pytest.raises(InputError, match="unknown mode 'fast'.*latency, throughput"):
        gi.load(mode="fast")


def test_predict_and_bench_record_the_mode(tmp_path):
    out = tmp_path / "out"
    cli = [sys.executable, "-m", "geonet_infer.cli"]
    subprocess.run(
        [*cli, "predict", str(DRIVE), "--out", str(out), "--max-frames", "4", "--no-progress", "--quiet", "--no-vis",
         "--batch-size", "3"],
        check=True,
    )  # fmt: skip
    model = json.loads((out / "summary.json").read_text())["model"]
    assert (model["mode"], model["workers"], model["batch_size"]) == ("throughput", gi.engines.usable_cpus(), 3)
    assert model["graphs"]["rigidflow"]["engine"] == "onnxruntime"
    bench = tmp_path / "bench.json"
    subprocess.run(
        [*cli, "bench", "--tasks", "sequence", "--modes", "e2e", "--precision", "fp32", "--iters", "1",
         "--warmup", "0", "--seq-frames", "4", "--mode", "throughput", "--json", str(bench)],
        check=True, stdout=subprocess.DEVNULL,
    )  # fmt: skip
    env = json.loads(bench.read_text())["environment"]
    assert env["mode"] == {"name": "throughput", "workers": gi.engines.usable_cpus()}

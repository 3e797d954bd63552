"""Every parser of a file a user hands us, fuzzed with hypothesis (issue 55, item 3): valid files mutated
(bytes flipped, cut, inserted) and random bytes. Property: a value or the package's own GeoNetError, never
another exception; each call's Python-side allocations (tracemalloc: numpy reports its arrays there) under
MEMORY_BOUND, and each call within hypothesis' deadline (no hang).

Examples per parser: EXAMPLES (``derandomize=True``: the same examples on every run, so CI stays
repeatable and bounded: 12 tests x 300 = 3,600 calls, about 30 s on 2 cores).
"""

from __future__ import annotations

import json
import shutil
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from geonet_infer.convert.tf_checkpoint import BundleReader, write_checkpoint  # noqa: E402
from geonet_infer.errors import GeoNetError  # noqa: E402
from geonet_infer.io.calib import read_calib_file, read_camera  # noqa: E402
from geonet_infer.io.depth import read_depth_kitti, write_depth_kitti  # noqa: E402
from geonet_infer.io.flow import read_flow_kitti, write_flow_kitti  # noqa: E402
from geonet_infer.io.poses import read_kitti_poses, read_tum_poses  # noqa: E402
from geonet_infer.models import bundled_models  # noqa: E402
from geonet_infer.models.manifest import load_manifest  # noqa: E402

EXAMPLES = 300
MEMORY_BOUND = 256 * 2**20
FUZZ = settings(
    max_examples=EXAMPLES,
    deadline=5000,  # ms per call: a parser sized by a claimed count would hang here
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)


@st.composite
def mutated(draw, seed: bytes) -> bytes:
    """``seed`` with a few bytes flipped, a cut, and an insertion (each maybe), or random bytes."""
    if draw(st.integers(0, 9)) == 0:
        return draw(st.binary(max_size=4096))
    data = bytearray(seed)
    for _ in range(draw(st.integers(0, 8))):
        if data:
            data[draw(st.integers(0, len(data) - 1))] = draw(st.integers(0, 255))
    if data and draw(st.booleans()):
        del data[draw(st.integers(0, len(data) - 1)) :]
    if draw(st.booleans()):
        at = draw(st.integers(0, len(data)))
        data[at:at] = draw(st.binary(max_size=64))
    return bytes(data)


def parses_or_refuses(call) -> None:
    tracemalloc.start()
    try:
        call()
    except GeoNetError:
        pass
    finally:
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    assert peak < MEMORY_BOUND, f"{peak / 2**20:.0f} MiB allocated"


# ------------------------------------------------------------------------------ TF checkpoints
def _checkpoint(folder: Path) -> Path:
    rng = np.random.default_rng(0)
    values = {"net/Conv/weights": rng.normal(size=(3, 3, 2, 4)).astype(np.float32), "global_step": np.int64(7)}
    values["net/Conv/BatchNorm/beta"] = rng.normal(size=4).astype(np.float32)
    return write_checkpoint(folder / "model-7", values)


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory) -> Path:
    return _checkpoint(tmp_path_factory.mktemp("ckpt"))


def _read_all(prefix: Path) -> None:
    reader = BundleReader(prefix)
    for name in reader.entries:
        reader.tensor(name)


@pytest.mark.parametrize("part", ["index", "data-00000-of-00001"])
@FUZZ
@given(data=st.data())
def test_checkpoint_files_parse_or_are_refused(tmp_path_factory, checkpoint, part, data):
    folder = tmp_path_factory.mktemp(part[:5])
    for f in checkpoint.parent.iterdir():
        shutil.copy(f, folder / f.name)
    target = folder / f"model-7.{part}"
    target.write_bytes(data.draw(mutated(target.read_bytes())))
    parses_or_refuses(lambda: _read_all(folder / "model-7"))


# ------------------------------------------------------------------------------ the model manifest
@FUZZ
@given(data=st.data())
def test_the_manifest_loads_or_is_refused(tmp_path_factory, data):
    model = tmp_path_factory.mktemp("model")
    source = bundled_models()["small_synth"] / "manifest.json"
    text = source.read_bytes()
    if data.draw(st.booleans()):  # structured: one value anywhere replaced by any JSON value
        manifest = json.loads(text)
        paths, stack = [], [((), manifest)]
        while stack:
            where, node = stack.pop()
            items = node.items() if isinstance(node, dict) else enumerate(node) if isinstance(node, list) else ()
            for key, value in items:
                paths.append((*where, key))
                stack.append(((*where, key), value))
        path = data.draw(st.sampled_from(paths))
        leaf = st.one_of(st.none(), st.booleans(), st.integers(-(2**70), 2**70), st.floats(), st.text(max_size=8))
        value = data.draw(
            st.recursive(
                leaf,
                lambda c: st.lists(c, max_size=3) | st.dictionaries(st.text(max_size=4), c, max_size=3),
                max_leaves=6,
            )
        )
        node = manifest
        for key in path[:-1]:
            node = node[key]
        node[path[-1]] = value
        text = json.dumps(manifest).encode()
    else:
        text = data.draw(mutated(text))
    (model / "manifest.json").write_bytes(text)
    parses_or_refuses(lambda: load_manifest(model, verify_files=False))


# ------------------------------------------------------------------------------ calibration files
CALIBS = {
    "kitti_raw": b"S_rect_02: 1.242000e+03 3.750000e+02\nP_rect_02: 721.5377 0 609.5593 44.85728 0 721.5377 172.854 "
    b"0.2163791 0 0 1 0.002745884\n",
    "kitti_odometry": b"P0: 718.856 0 607.1928 0 0 718.856 185.2157 0 0 0 1 0\n"
    b"P2: 718.856 0 607.1928 45.38225 0 718.856 185.2157 -0.1130887 0 0 1 0.003779761\n",
    "euroc_yaml": b"sensor_type: camera\nresolution: [752, 480]\ncamera_model: pinhole\n"
    b"intrinsics: [458.654, 457.296, 367.215, 248.375] #fu, fv, cu, cv\ndistortion_model: radial-tangential\n"
    b"distortion_coefficients: [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]\n",
    "plain_K": b"721.5 0 609.5\n0 721.5 172.8\n0 0 1\n",
    "key_values": b"# camera\nfx 1158.77\nfy 1154.08\ncx 669.64\ncy 388.08\ndist -0.24 -0.05 0.0 0.0 0.03\n"
    b"image_width 1280\nimage_height 720\n",
}


@pytest.mark.parametrize("kind", list(CALIBS))
@FUZZ
@given(data=st.data())
def test_calibration_files_parse_or_are_refused(tmp_path_factory, kind, data):
    path = tmp_path_factory.mktemp("calib") / "calib.txt"
    path.write_bytes(data.draw(mutated(CALIBS[kind])))
    parses_or_refuses(lambda: read_camera(path))
    parses_or_refuses(lambda: read_calib_file(path))


# ------------------------------------------------------------------------------ KITTI PNGs
@pytest.fixture(scope="module")
def pngs(tmp_path_factory) -> dict[str, bytes]:
    folder = tmp_path_factory.mktemp("png")
    rng = np.random.default_rng(1)
    write_flow_kitti(folder / "flow.png", rng.normal(0, 5, (12, 20, 2)).astype(np.float32))
    write_depth_kitti(folder / "depth.png", rng.uniform(1, 80, (12, 20)).astype(np.float32))
    return {name: (folder / f"{name}.png").read_bytes() for name in ("flow", "depth")}


@pytest.mark.parametrize("kind", ["flow", "depth"])
@FUZZ
@given(data=st.data())
def test_kitti_pngs_parse_or_are_refused(tmp_path_factory, pngs, kind, data):
    path = tmp_path_factory.mktemp(kind) / f"{kind}.png"
    path.write_bytes(data.draw(mutated(pngs[kind])))
    parses_or_refuses(lambda: (read_flow_kitti if kind == "flow" else read_depth_kitti)(path))


# ------------------------------------------------------------------------------ poses
POSES = {
    "kitti": b"1 0 0 0 0 1 0 0 0 0 1 0\n0.9998 0.0175 0 0.1 -0.0175 0.9998 0 0 0 0 1 1.2\n",
    "tum": b"# timestamp tx ty tz qx qy qz qw\n0.0 0 0 0 0 0 0 1\n0.1 0.1 0 1.2 0 0.0087 0 0.99996\n",
}


@pytest.mark.parametrize("kind", list(POSES))
@FUZZ
@given(data=st.data())
def test_pose_files_parse_or_are_refused(tmp_path_factory, kind, data):
    path = tmp_path_factory.mktemp("poses") / "poses.txt"
    path.write_bytes(data.draw(mutated(POSES[kind])))
    parses_or_refuses(lambda: (read_kitti_poses if kind == "kitti" else read_tum_poses)(path))

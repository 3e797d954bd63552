"""Shared fixtures.

``realdata``: the shared real-data folder ``../shared/realdata`` (next to the repository).
Tests that use it are skipped when it is missing, except on CI (env var ``CI`` set to
anything but ``""``, ``0``, ``false`` or ``no``), where a missing folder is a failure:
there the data is expected, and a silent skip would hide that nothing was tested.
"""

from __future__ import annotations

import os
import sys
import types
from pathlib import Path

import pytest

# Test files share helpers as `from tests.runtime.batch.test_batch import ...`. The development run
# has the repository root on sys.path; the runtime-only run (scripts/test_runtime.sh) must not (it
# tests the installed package), so `tests` is made importable here by its folder alone.
if "tests" not in sys.modules:
    _tests = types.ModuleType("tests")
    _tests.__path__ = [str(Path(__file__).resolve().parent)]
    sys.modules["tests"] = _tests

# The CLI as a subprocess, as users run it: the venv's console script. `python -m geonet_infer.cli` from
# the repository root would import the source tree (the working directory comes first on sys.path),
# not the installed package the runtime-only run tests.
_SCRIPT = Path(sys.executable).with_name("geonet-infer")
GEONET_CLI = [str(_SCRIPT)] if _SCRIPT.exists() else [sys.executable, "-m", "geonet_infer.cli"]

REALDATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "realdata"
KITTI_RAW = "kitti_raw_2011_09_26_sfnd"  # one KITTI raw drive: image_02, Velodyne scans, calibration
KITTI_ODOMETRY = "kitti_odometry_00"  # KITTI odometry sequence 00, grey frames and calib.txt
KITTI_ODOMETRY_06 = "kitti_odometry_06"  # sequence 06: grey frames 0-50 (and a few colour ones), poses
KITTI_OBJECT = "kitti_object_3frames"  # KITTI object benchmark: 3 frames, Velodyne scans, per-frame calib
KITTI2015_STEREO = "kitti2015_000046_stereo"  # KITTI 2015 stereo scene 000046 with disp_occ_0
KITTI2015_FLOW = "kitti2015_flow_000010"  # KITTI 2015 flow pair 000010 with flow_occ / flow_noc


def on_ci() -> bool:
    return os.environ.get("CI", "").strip().lower() not in ("", "0", "false", "no")


def require_realdata(rel: str = "") -> Path:
    """``../shared/realdata/<rel>``; if it is missing: fail on CI, skip otherwise."""
    path = REALDATA / rel
    if not path.exists():
        msg = f"{path} not present (real test data, see ../shared/realdata/README.md)"
        if on_ci():
            pytest.fail(f"{msg}; CI is set, so missing real data is an error", pytrace=False)
        pytest.skip(msg)
    return path


@pytest.fixture(scope="session")
def require_real():
    """:func:`require_realdata` as a fixture, for test files that run against the installed
    package (the runtime-only venv cannot import ``tests.conftest``)."""
    return require_realdata


@pytest.fixture(scope="session")
def realdata() -> Path:
    """Path of ``../shared/realdata`` (fails on CI / skips elsewhere when it is missing)."""
    return require_realdata()


@pytest.fixture(scope="session")
def kitti_raw() -> Path:
    """Path of ``../shared/realdata/kitti_raw_2011_09_26_sfnd`` (fails on CI / skips elsewhere when missing)."""
    return require_realdata(KITTI_RAW)


@pytest.fixture(scope="session")
def kitti_odometry() -> Path:
    """Path of ``../shared/realdata/kitti_odometry_00`` (fails on CI / skips elsewhere when missing)."""
    return require_realdata(KITTI_ODOMETRY)


@pytest.fixture(scope="session")
def kitti_odometry_06() -> Path:
    """Path of ``../shared/realdata/kitti_odometry_06`` (fails on CI / skips elsewhere when missing)."""
    return require_realdata(KITTI_ODOMETRY_06)


@pytest.fixture(scope="session")
def kitti_object() -> Path:
    """Path of ``../shared/realdata/kitti_object_3frames`` (fails on CI / skips elsewhere when missing)."""
    return require_realdata(KITTI_OBJECT)


@pytest.fixture(scope="session")
def kitti2015_stereo() -> Path:
    """Path of ``../shared/realdata/kitti2015_000046_stereo`` (fails on CI / skips elsewhere when missing)."""
    return require_realdata(KITTI2015_STEREO)


@pytest.fixture(scope="session")
def kitti2015_flow() -> Path:
    """Path of ``../shared/realdata/kitti2015_flow_000010`` (fails on CI / skips elsewhere when missing)."""
    return require_realdata(KITTI2015_FLOW)


@pytest.fixture(scope="session")
def synth_prepared(tmp_path_factory) -> Path:
    """2 synthetic sequences x 8 frames at 32x96, prepared (val fraction 0.2) by the real tools.

    Trainer tests (single process and torchrun) share it; the training extra is imported here,
    not at module level, so the runtime-only test run never needs it.
    """
    from training.prepare import PrepareConfig, prepare
    from training.synth import SynthConfig, generate

    root = tmp_path_factory.mktemp("synth")
    generate(SynthConfig(out=root / "synth", sequences=2, frames=8, seed=1, height=32, width=96))
    prepare(
        PrepareConfig(
            kind="synth", src=root / "synth", out=root / "prepared", height=32, width=96, heldout=0, val_fraction=0.2
        )
    )
    return root / "prepared"


@pytest.fixture(scope="session")
def dashcam() -> Path:
    """Path of ``../shared/realdata/udacity_dashcam`` (fails on CI / skips elsewhere when missing)."""
    return require_realdata("udacity_dashcam")


@pytest.fixture(scope="session")
def ffmpeg() -> str:
    """Path of the ffmpeg program (.ci/run installs it): fails on CI / skips elsewhere when missing."""
    import shutil

    path = shutil.which("ffmpeg")
    if path is None:
        if on_ci():
            pytest.fail("ffmpeg not installed; CI is set, so .ci/run should have installed it", pytrace=False)
        pytest.skip("ffmpeg not installed (Debian: apt-get install ffmpeg)")
    return path

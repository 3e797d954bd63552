"""The installed runtime (scripts/test_runtime.sh: `pip install .` in a venv without torch).

Skipped in the development venv; scripts/test_runtime.sh sets GEONET_RUNTIME_ONLY=1.
"""

import importlib.util
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

import geonet_infer
from geonet_infer.models import DEFAULT_MODEL, bundled_models
from geonet_infer.samples import SAMPLE_CALIB, SAMPLE_FRAMES

ROOT = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.skipif(
    os.environ.get("GEONET_RUNTIME_ONLY") != "1", reason="runs in the runtime-only venv of scripts/test_runtime.sh"
)


def test_imported_from_the_installed_package_not_the_source_tree():
    installed = Path(geonet_infer.__file__).resolve().parent
    assert installed != (ROOT / "geonet_infer").resolve()
    assert installed.parent.name == "site-packages"


def test_no_torch_in_this_environment():
    assert importlib.util.find_spec("torch") is None


def test_package_data_is_installed():
    models = bundled_models()
    assert DEFAULT_MODEL in models
    predictor = geonet_infer.load()  # verifies every graph's sha256 against the manifest
    assert predictor.model_dir == models[DEFAULT_MODEL]
    assert set(predictor.graphs) >= {"depthnet", "posenet", "rigidflow", "resflownet"}
    assert geonet_infer.load(precision="int8").precision == "int8"
    assert SAMPLE_CALIB.is_file() and len(list(SAMPLE_FRAMES.glob("*.png"))) >= 5


def test_console_script_is_installed():
    script = shutil.which("geonet-infer", path=str(Path(sys.executable).parent))
    assert script is not None
    result = subprocess.run([script, "--help"], capture_output=True, text=True)
    assert result.returncode == 0 and "predict" in result.stdout

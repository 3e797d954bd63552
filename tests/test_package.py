"""Package boundaries: the runtime never imports torch, training or export; the wheel ships only it."""
import pkgutil
import subprocess
import sys
import tomllib
from pathlib import Path

import geonet_infer

ROOT = Path(__file__).resolve().parents[1]


def test_runtime_modules_import_without_torch():
    modules = [m.name for m in pkgutil.walk_packages(geonet_infer.__path__, "geonet_infer.")
               if not m.name.endswith("__main__")]
    assert {"geonet_infer.predictor", "geonet_infer.cli", "geonet_infer.io.frames", "geonet_infer.models"} <= set(modules)
    code = ("import sys\n"
            f"for name in {modules!r}: __import__(name)\n"
            "bad = sorted(m for m in sys.modules if m.split('.')[0] in ('torch', 'training', 'export'))\n"
            "print(bad)\n"
            "sys.exit(1 if bad else 0)\n")
    result = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True)
    assert result.returncode == 0, result.stdout + result.stderr


def test_wheel_ships_only_geonet_infer():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert project["tool"]["setuptools"]["packages"]["find"]["include"] == ["geonet_infer*"]
    runtime_deps = " ".join(project["project"]["dependencies"])
    assert "torch" not in runtime_deps
    assert project["project"]["scripts"]["geonet-infer"] == "geonet_infer.cli:main"

"""Package boundaries: the runtime never imports torch, training or export."""
import pkgutil
import subprocess
import sys
from pathlib import Path

import geonet_infer

ROOT = Path(__file__).resolve().parents[1]


def test_runtime_modules_import_without_torch():
    modules = [f"geonet_infer.{m.name}" for m in pkgutil.iter_modules(geonet_infer.__path__)]
    assert len(modules) >= 4
    code = ("import sys\n"
            f"for name in {modules!r}: __import__(name)\n"
            "bad = sorted(m for m in sys.modules if m.split('.')[0] in ('torch', 'training', 'export'))\n"
            "print(bad)\n"
            "sys.exit(1 if bad else 0)\n")
    result = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True)
    assert result.returncode == 0, result.stdout + result.stderr


def test_wheel_ships_only_geonet_infer():
    text = (ROOT / "pyproject.toml").read_text()
    assert 'packages = ["geonet_infer"]' in text
    runtime_deps = text.split("dependencies = [")[1].split("]")[0]
    assert "torch" not in runtime_deps

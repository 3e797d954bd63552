"""Packaging: the wheel ships only the runtime (the import contract is in test_import_contract.py)."""

from pathlib import Path

import tomllib

ROOT = Path(__file__).resolve().parents[1]


def test_wheel_ships_only_geonet_infer():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert project["tool"]["setuptools"]["packages"]["find"]["include"] == ["geonet_infer*"]
    runtime_deps = " ".join(project["project"]["dependencies"])
    assert "torch" not in runtime_deps
    assert project["project"]["scripts"]["geonet-infer"] == "geonet_infer.cli:main"


def test_one_version_and_an_spdx_licence():
    import geonet_infer

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    assert isinstance(project["license"], str)  # SPDX expression; the table form warns on every install
    assert geonet_infer.__version__ == project["version"]  # read from the installed metadata, not retyped

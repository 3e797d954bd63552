"""``python experiments/import_time.py``: import times and what each import loads, in fresh interpreters."""

from __future__ import annotations

import json
from pathlib import Path

from experiments.import_time import main, measure


def fake_tree(root: Path, cli_imports: str) -> Path:
    """A checkout whose geonet_infer is two modules (the package and core); its cli imports ``cli_imports``."""
    pkg = root / "geonet_infer"
    pkg.mkdir(parents=True)
    (pkg / "__init__.py").write_text("from geonet_infer import core\n")
    (pkg / "core.py").write_text("import json\n")
    (pkg / "cli.py").write_text(cli_imports)
    (pkg / "output.py").write_text("")
    return root


def test_the_modules_each_import_loads_are_counted(tmp_path):
    lean = fake_tree(tmp_path / "lean", "")
    eager = fake_tree(tmp_path / "eager", "from geonet_infer import output\nimport wave\n")
    result = measure([lean, eager], rounds=1)
    # geonet_infer + geonet_infer.core; the cli adds itself (and output in the eager tree)
    assert result[str(lean)]["geonet_infer"]["package_modules"] == 2
    assert result[str(lean)]["geonet_infer.cli"]["package_modules"] == 3
    assert result[str(eager)]["geonet_infer.cli"]["package_modules"] == 4
    assert result[str(eager)]["geonet_infer.cli"]["modules"] > result[str(lean)]["geonet_infer.cli"]["modules"]
    assert result[str(lean)]["geonet_infer"]["median_ms"] > 0


def test_the_command_prints_a_row_per_tree_and_import_and_writes_json(tmp_path, capsys):
    tree = fake_tree(tmp_path / "t", "")
    assert main(["--root", str(tree), "--rounds", "2", "--json", str(tmp_path / "r.json")]) == 0
    rows = [line for line in capsys.readouterr().out.splitlines() if line.startswith(f"| {tree}")]
    assert len(rows) == 2
    assert set(json.loads((tmp_path / "r.json").read_text())[str(tree)]) == {"geonet_infer", "geonet_infer.cli"}

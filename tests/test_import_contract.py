"""Import contract: the runtime ``geonet_infer`` never imports torch, training or export.

Checked two ways: statically (every import statement of every runtime module, including
imports inside functions, which a plain ``import geonet_infer`` would not execute) and
dynamically (importing every runtime module in a fresh interpreter loads none of them).
"""

from __future__ import annotations

import ast
import pkgutil
import subprocess
import sys
from pathlib import Path

import geonet_infer

ROOT = Path(__file__).resolve().parents[1]
RUNTIME = ROOT / "geonet_infer"
FORBIDDEN = ("torch", "training", "export")


def imported_modules(tree: ast.AST) -> list[tuple[int, str]]:
    """(line, top-level module) of every absolute import statement in ``tree``."""
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name.split(".")[0]) for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            found.append((node.lineno, node.module.split(".")[0]))
    return found


def test_the_ast_walk_sees_nested_imports():
    """The checker itself: an import inside a function body is found (so the next test can fail)."""
    tree = ast.parse("def f():\n    from torch import nn\n    import training.train as t\n")
    assert imported_modules(tree) == [(2, "torch"), (3, "training")]


def test_no_runtime_module_imports_torch_training_or_export():
    files = sorted(RUNTIME.rglob("*.py"))
    assert RUNTIME / "predictor.py" in files and len(files) > 20
    bad = [
        f"{f.relative_to(ROOT)}:{line} imports {mod}"
        for f in files
        for line, mod in imported_modules(ast.parse(f.read_text(), str(f)))
        if mod in FORBIDDEN
    ]
    assert not bad, "\n".join(bad)


def test_importing_every_runtime_module_loads_none_of_them():
    modules = [
        m.name for m in pkgutil.walk_packages(geonet_infer.__path__, "geonet_infer.") if not m.name.endswith("__main__")
    ]
    assert {"geonet_infer.predictor", "geonet_infer.cli", "geonet_infer.io.frames"} <= set(modules)
    code = (
        "import sys\n"
        "import geonet_infer\n"
        f"for name in {modules!r}: __import__(name)\n"
        f"print(sorted(m for m in sys.modules if m.split('.')[0] in {FORBIDDEN!r}))\n"
    )
    run = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    assert run.stdout.strip() == "[]", run.stdout

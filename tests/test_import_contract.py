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


def module_imports(path: Path, name: str, known: set[str]) -> set[str]:
    """The ``geonet_infer`` modules that module ``name`` (file ``path``) imports, anywhere in it.

    ``from a.b import c`` counts as an import of ``a.b.c`` when that is a module, else of ``a.b``;
    relative imports are resolved against ``name``'s package.
    """
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(parts + ([base] if base else []))
            targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in known else base for a in node.names]
        else:
            continue
        found |= {t for t in targets if t in known and t != name}
    return found


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import cycle of ``graph`` (module -> modules it imports) as [a, b, ..., a], or None."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    path: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        path.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                return path[path.index(nxt) :] + [nxt]
            if nxt not in state and (cycle := visit(nxt)):
                return cycle
        state[node] = 2
        path.pop()
        return None

    for start in sorted(graph):
        if start not in state and (cycle := visit(start)):
            return cycle
    return None


def runtime_import_graph() -> dict[str, set[str]]:
    files = {
        ".".join(f.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__"): f for f in RUNTIME.rglob("*.py")
    }
    known = set(files)
    return {name: module_imports(path, name, known) for name, path in files.items()}


def test_the_cycle_finder_finds_a_cycle_and_accepts_a_tree():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b", "c"}, "b": {"c"}, "c": set()}) is None


def test_the_import_graph_sees_this_package():
    graph = runtime_import_graph()
    assert "geonet_infer.errors" in graph["geonet_infer.predictor"]
    assert "geonet_infer.cli.predict" in graph["geonet_infer.cli"]  # `from geonet_infer.cli import predict`


def test_no_import_cycle_inside_geonet_infer():
    """Every import counts, also inside functions and TYPE_CHECKING blocks: a cycle hidden in a
    function body is still two modules that cannot be understood (or moved) one without the other."""
    cycle = find_cycle(runtime_import_graph())
    assert cycle is None, "import cycle: " + " -> ".join(cycle)

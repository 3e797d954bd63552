"""Import contract: the runtime ``geonet_infer`` never imports torch, training, export or benchmarks (the
repository's developer tools, its catalogue of ../shared real sets among them: not in the wheel).

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

ROOT = Path(__file__).resolve().parents[2]
RUNTIME = ROOT / "geonet_infer"
FORBIDDEN = ("torch", "training", "export", "benchmarks")
TOP_LEVEL = {
    "geonet_infer",
    "training",
    "export",
    "benchmarks",
    "experiments",
    "tests",
    "scripts",
}  # the repository's packages


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
    assert RUNTIME / "core" / "predictor.py" in files and len(files) > 20
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
    assert {"geonet_infer.core.predictor", "geonet_infer.cli", "geonet_infer.io.frames"} <= set(modules)
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
    """The modules of ``known`` that module ``name`` (file ``path``) imports, anywhere in it.

    ``from a.b import c`` counts as an import of ``a.b.c`` when that is a module, else of ``a.b``;
    relative imports are resolved against ``name``'s package, and a plain ``import x`` that names no
    known module against the folder (the scripts of benchmarks/ import their neighbours so).
    """
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]

    def sibling(target: str) -> str:
        return target if target in known or not package else f"{package}.{target}"

    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            targets = [sibling(alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(parts + ([base] if base else []))
            base = sibling(base) if node.level == 0 and base.split(".")[0] not in TOP_LEVEL else base
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


def import_graph(files: list[Path]) -> dict[str, set[str]]:
    """module -> the modules of ``files`` it imports (names from the paths under the repository root)."""
    named = {".".join(f.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__"): f for f in files}
    known = set(named)
    return {name: module_imports(path, name, known) for name, path in named.items()}


def runtime_import_graph() -> dict[str, set[str]]:
    return import_graph(list(RUNTIME.rglob("*.py")))


def repository_files() -> list[Path]:
    """Every Python file of the repository: packages, scripts, benchmarks and tests (not venvs, builds, data)."""
    return [
        f
        for f in ROOT.rglob("*.py")
        if not any(part.startswith(".") or part in ("build", "data", "runs") for part in f.relative_to(ROOT).parts)
    ]


def test_the_cycle_finder_finds_a_cycle_and_accepts_a_tree():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b", "c"}, "b": {"c"}, "c": set()}) is None


def test_the_import_graph_sees_this_package():
    graph = runtime_import_graph()
    assert "geonet_infer.errors" in graph["geonet_infer.core.predictor"]
    assert "geonet_infer.cli" in graph["geonet_infer.cli.predict"]  # `from geonet_infer.cli import COMMANDS`
    assert (
        "geonet_infer.eval.metrics" in graph["geonet_infer.eval.evaluation"]
    )  # `from geonet_infer.eval import metrics`


def test_no_import_cycle_inside_geonet_infer():
    """Every import counts, also inside functions and TYPE_CHECKING blocks: a cycle hidden in a
    function body is still two modules that cannot be understood (or moved) one without the other."""
    cycle = find_cycle(runtime_import_graph())
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


def modules_loaded_by(statement: str) -> list[str]:
    """The ``geonet_infer`` modules a fresh interpreter has loaded after running ``statement``."""
    code = f"import sys\n{statement}\nprint(sorted(m for m in sys.modules if m.startswith('geonet_infer')))"
    run = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    return eval(run.stdout)  # a printed list of str


# Not on the runtime's import path: what `import geonet_infer` (and so `load()`) must not pay for.
OFF_THE_RUNTIME_PATH = ("geonet_infer.eval", "geonet_infer.bench", "geonet_infer.batch", "geonet_infer.output")


def test_import_geonet_infer_loads_no_eval_bench_batch_or_output_module():
    loaded = modules_loaded_by("import geonet_infer")
    assert "geonet_infer.core.predictor" in loaded  # the check can fail: it sees what the import loads
    off = [m for m in loaded if m.startswith(OFF_THE_RUNTIME_PATH)]
    assert not off, off


def test_import_geonet_infer_does_not_read_package_metadata():
    """``__version__`` is read on first use (importlib.metadata alone costs about 0.1 s)."""
    loaded = modules_loaded_by("import geonet_infer, importlib.util\nassert 'importlib.metadata' not in sys.modules")
    assert "geonet_infer" in loaded


def test_import_cli_loads_no_subcommand_and_a_command_loads_only_its_own():
    from geonet_infer.cli import COMMANDS

    loaded = modules_loaded_by("import geonet_infer.cli")
    assert "geonet_infer.cli" in loaded
    assert not [m for m in loaded if m.startswith("geonet_infer.cli.")], loaded
    info = modules_loaded_by("from geonet_infer.cli import build_parser\nbuild_parser('info')")
    assert "geonet_infer.cli.info" in info
    assert not [f"geonet_infer.cli.{c}" for c in COMMANDS if c != "info" and f"geonet_infer.cli.{c}" in info]
    assert not [m for m in info if m.startswith(("geonet_infer.eval", "geonet_infer.batch"))]


def test_no_import_cycle_anywhere_in_the_repository():
    """training, export, benchmarks, scripts and tests too, imports inside functions included (the
    export cycle build <-> from_tf of issue 42 was two imports inside functions)."""
    graph = import_graph(repository_files())
    assert {"export.build", "export.from_tf", "training.train", "experiments.speed_targets"} <= set(graph)
    assert "export.source" in graph["export.from_tf"]  # the imports inside functions are seen
    assert "experiments.target_limits" in graph["experiments.speed_targets"]  # `import target_limits`
    cycle = find_cycle(graph)
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


def reachable(graph: dict[str, set[str]], start: str) -> set[str]:
    """Every module ``start`` imports, directly or through others (imports inside functions included;
    importing ``a.b.c`` runs the packages ``a`` and ``a.b`` first)."""
    seen, todo = set(), [start]
    while todo:
        module = todo.pop()
        parents = {module.rsplit(".", n)[0] for n in range(1, module.count(".") + 1)}
        for nxt in graph.get(module, set()) | parents:
            if nxt not in seen:
                seen.add(nxt)
                todo.append(nxt)
    return seen


def test_the_core_never_imports_output_batch_eval_or_bench():
    """The core is what ``import geonet_infer`` and ``load()`` can run: everything the package's
    ``__init__`` reaches, statically, through imports anywhere in a module (not only those executed)."""
    graph = runtime_import_graph()
    core = reachable(graph, "geonet_infer")
    assert {"geonet_infer.core.predictor", "geonet_infer.engines", "geonet_infer.io.frames"} <= core
    bad = sorted(m for m in core if m.startswith((*OFF_THE_RUNTIME_PATH, "geonet_infer.cli")))
    assert not bad, bad


def test_no_module_of_core_reaches_output_batch_eval_or_bench():
    """geonet_infer/core/ (what load() runs), each module and all it imports, statically."""
    graph = runtime_import_graph()
    core = [m for m in graph if m.startswith("geonet_infer.core.")]
    assert {"geonet_infer.core.predictor", "geonet_infer.core.cascade", "geonet_infer.core.graphs"} <= set(core)
    bad = {
        m: sorted(r for r in reachable(graph, m) if r.startswith((*OFF_THE_RUNTIME_PATH, "geonet_infer.cli")))
        for m in core
    }
    assert not {m: r for m, r in bad.items() if r}, bad


def test_no_two_test_files_share_a_name():
    """pytest imports test files by their base name (no __init__.py in tests/): two of one name stop a
    one-process run of the whole suite at collection (issue 55), though each passes alone."""
    tests = Path(__file__).resolve().parents[1]
    names = [p.name for p in tests.rglob("test_*.py")]
    assert sorted({n for n in names if names.count(n) > 1}) == []


# The floors of the runtime, top first (docs/architecture.md): a module imports only its own floor and the
# floors above it. The shared modules and the package itself are the top floor; the package's __init__
# (the API's front door) is the one module that may import from below.
FLOORS = (
    ("geonet_infer", "geonet_infer.errors", "geonet_infer.conventions", "geonet_infer.limits"),
    ("geonet_infer.io",),
    ("geonet_infer.models", "geonet_infer.samples"),  # model directories (manifest, graph checks, names); data
    ("geonet_infer.engines",),
    ("geonet_infer.classical",),
    ("geonet_infer.core",),
    ("geonet_infer.output",),
    ("geonet_infer.batch",),
    ("geonet_infer.eval",),
    ("geonet_infer.bench",),
    ("geonet_infer.convert",),
    ("geonet_infer.cli",),
)


def floor_of(module: str) -> int:
    """The floor of ``module``: the floor naming it or the package it is in (the longest match)."""
    matches = [(len(name), k) for k, names in enumerate(FLOORS) for name in names
               if module == name or (name != "geonet_infer" and module.startswith(name + "."))]  # fmt: skip
    if not matches:
        raise AssertionError(f"{module} is in no floor: add it to FLOORS (or move it into one)")
    return max(matches)[1]


def test_the_package_top_holds_only_the_shared_modules_and_the_floors():
    top = sorted(p.name for p in RUNTIME.glob("*.py"))
    assert top == ["__init__.py", "conventions.py", "errors.py", "limits.py"]
    assert floor_of("geonet_infer.core.check") == 5 and floor_of("geonet_infer.conventions") == 0


def test_no_import_runs_back_up_a_floor():
    """Issue 56: each module imports only modules of its own floor or the floors above it (every import
    counts, also inside functions), so a floor can be read without the floors below it."""
    graph = runtime_import_graph()
    up = {
        f"{module} -> {imported}"
        for module, imports in graph.items()
        if module != "geonet_infer"
        for imported in imports
        if floor_of(imported) > floor_of(module)
    }
    assert not up, sorted(up)

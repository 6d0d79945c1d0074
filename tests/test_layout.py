"""The package's architecture as a law of its imports: every module of ``jcomps`` sits in a layer, and no module
imports one from a layer above its own or forms an import circle with its neighbours, lazy imports inside functions
included (read from the source, nothing is imported)."""

import ast
import pathlib

import pytest

SRC = pathlib.Path(__file__).resolve().parents[1] / "src" / "jcomps"

LAYERS = (
    ("jcomps", "jcomps.numerics", "jcomps.progress", "jcomps.registry", "jcomps.configs", "jcomps.migrations"),
    ("jcomps.envs",),
    ("jcomps.training",),
    ("jcomps.methods",),
    ("jcomps.continual",),
    ("jcomps.runner",),
    ("jcomps.analysis",),
    ("jcomps.console",),
)
"""From the bottom: what every layer uses (numbers, progress events, registries, config dataclasses as options),
the task families, the RL building blocks, the methods, the continual protocol (a method over a task sequence, its
evaluations), the study runner, the report, the console the scripts show it on."""


def _module(path: pathlib.Path) -> str:
    parts = path.relative_to(SRC.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {_module(p): p for p in sorted(SRC.rglob("*.py"))}


def _layer(module: str) -> int:
    best = None
    for i, prefixes in enumerate(LAYERS):
        for prefix in prefixes:
            if module == prefix or (prefix != "jcomps" and module.startswith(prefix + ".")):
                if best is None or len(prefix) > best[1]:
                    best = (i, len(prefix))
    assert best is not None, f"{module} is in no layer of LAYERS: give it one"
    return best[0]


def _imports(module: str) -> set:
    """The jcomps modules ``module`` imports, anywhere in its source."""
    tree = ast.parse(MODULES[module].read_text())
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names if a.name.startswith("jcomps")}
        elif isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("jcomps"):
            for a in node.names:
                name = f"{node.module}.{a.name}"
                out.add(name if name in MODULES else node.module)
    return {m for m in out if m in MODULES and m != module}


GRAPH = {m: _imports(m) for m in MODULES}


def test_every_module_has_a_layer():
    for module in MODULES:
        _layer(module)


@pytest.mark.parametrize("module", sorted(MODULES))
def test_no_module_imports_one_above_it(module):
    above = sorted(m for m in GRAPH[module] if _layer(m) > _layer(module))
    assert not above, f"{module} (layer {_layer(module)}) imports {above} from a layer above it"


def test_the_imports_form_no_circle():
    state, stack = {}, []

    def visit(m):
        state[m] = "open"
        stack.append(m)
        for n in sorted(GRAPH[m]):
            if state.get(n) == "open":
                raise AssertionError("import circle: " + " -> ".join(stack[stack.index(n):] + [n]))
            if n not in state:
                visit(n)
        stack.pop()
        state[m] = "done"

    for m in sorted(GRAPH):
        if m not in state:
            visit(m)


def test_the_law_catches_a_violation():
    """The checks see what they are meant to see: the report is above the runner, the runner above the methods."""
    assert _layer("jcomps.analysis.report") > _layer("jcomps.runner.experiment") > _layer("jcomps.methods.comps")
    assert "jcomps.runner.results" in GRAPH["jcomps.analysis.report"]



MAX_FUNCTION_LINES = 80
MAX_RUNNER_CLASS_LINES = 150


def _sizes(source: str, kind):
    """(name, lines) of every node of ``kind`` in ``source``, nested ones included."""
    return [(n.name, n.end_lineno - n.lineno + 1) for n in ast.walk(ast.parse(source)) if isinstance(n, kind)]


FUNCTIONS = (ast.FunctionDef, ast.AsyncFunctionDef)


def test_functions_stay_short():
    """Issue 59: every function in ``src/`` under 80 lines (a longer one is two functions a reader must hold at once)."""
    long = [f"{m}.{n}: {k} lines" for m, p in MODULES.items() for n, k in _sizes(p.read_text(), FUNCTIONS)
            if k >= MAX_FUNCTION_LINES]
    assert not long, f"functions of {MAX_FUNCTION_LINES} lines or more: {long}"


def test_runner_classes_stay_small():
    """Issue 59: no class of the runner over 150 lines (the hub it was is split into its parts)."""
    big = [f"{m}.{n}: {k} lines" for m, p in MODULES.items() if m.startswith("jcomps.runner")
           for n, k in _sizes(p.read_text(), ast.ClassDef) if k > MAX_RUNNER_CLASS_LINES]
    assert not big, f"runner classes over {MAX_RUNNER_CLASS_LINES} lines: {big}"


def test_the_size_checks_count_lines():
    source = "class A:\n    def f(self):\n        def g():\n            return 1\n        return g\n"
    assert sorted(_sizes(source, FUNCTIONS)) == [("f", 4), ("g", 2)]
    assert _sizes(source, ast.ClassDef) == [("A", 5)]

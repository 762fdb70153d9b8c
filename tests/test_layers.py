"""The shape of the code, checked from its imports (parsed, not grepped): layers import only
downward, only algebra/ touches petsc4py and slepc4py, no import circles among modules, and
every import inside a function says why in a comment (docs/architecture.md)."""
import ast
import pathlib

import pytest

pytestmark = pytest.mark.serial_only        # reads files; nothing MPI about it

ROOT = pathlib.Path(__file__).resolve().parent.parent / "parflow"

# layer of each package or top-level module: a module may import its own layer and below
LAYERS = {
    "errors": 0, "__init__": 0, "schema": 0,
    "geometry": 1, "state": 1,
    "packing": 2, "algebra": 2, "observables": 2, "io": 2,
    "dynamics": 3,
    "models": 4,
    "protocol": 5, "scene": 5, "provenance": 5, "checkpoint": 5,
    "run": 6, "ensemble": 6,
    "post": 6, "plot": 7,
    "cli": 8, "shear": 8, "spectrum": 8, "modes": 8, "prepare": 8, "chain_split": 8,
}
PETSC_OK = {"algebra", "cli"}          # cli.init_petsc initialises PETSc with the command line


def _modules():
    for p in sorted(ROOT.rglob("*.py")):
        rel = p.relative_to(ROOT)
        yield p, rel, ast.parse(p.read_text())


def _target(rel, node):
    """Top-level parflow name (package or module) an import node refers to, or None."""
    if isinstance(node, ast.ImportFrom):
        if node.level == 0:
            mod = node.module or ""
            return mod.split(".")[1] if mod.startswith("parflow.") else None
        base = list(rel.parts[:-1])
        base = base[:len(base) - (node.level - 1)] if node.level > 1 else base
        parts = base + (node.module.split(".") if node.module else [])
        if not parts:                  # from . import x  (at the top of the package)
            return node.names[0].name.split(".")[0]
        return parts[0]
    return None


def _imports(tree):
    for node in ast.walk(tree):
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            yield node


def _layer(name):
    return LAYERS[name.removesuffix(".py")]


def test_every_module_has_a_layer():
    names = {p.relative_to(ROOT).parts[0].removesuffix(".py") for p in ROOT.rglob("*.py")}
    assert names <= set(LAYERS), names - set(LAYERS)


def test_layers_import_only_downward():
    bad = []
    for p, rel, tree in _modules():
        own = _layer(rel.parts[0])
        for node in _imports(tree):
            t = _target(rel, node)
            if t is not None and t in LAYERS and LAYERS[t] > own:
                bad.append(f"{rel}:{node.lineno} imports {t} (layer {LAYERS[t]} > {own})")
    assert not bad, "\n".join(bad)


def test_only_algebra_imports_petsc():
    bad = []
    for p, rel, tree in _modules():
        if rel.parts[0].removesuffix(".py") in PETSC_OK:
            continue
        for node in _imports(tree):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else [node.module or ""]
            if any(n.split(".")[0] in ("petsc4py", "slepc4py") for n in names):
                if not (rel.name == "provenance.py" and names == ["slepc4py"]):   # its version only
                    bad.append(f"{rel}:{node.lineno}")
    assert not bad, bad


def test_no_import_circles():
    graph = {}
    for p, rel, tree in _modules():
        me = ".".join(rel.with_suffix("").parts)
        deps = set()
        for node in tree.body:                     # module-level imports make the circles
            if isinstance(node, ast.ImportFrom) and node.level:
                base = list(rel.with_suffix("").parts[:-1])
                base = base[:len(base) - (node.level - 1)] if node.level > 1 else base
                if node.module:
                    deps.add(".".join(base + node.module.split(".")))
                else:
                    deps.update(".".join(base + [a.name]) for a in node.names)
        graph[me] = {d for d in deps if d != me}
    names = set(graph)

    def resolve(d):       # a package import means its __init__
        return d if d in names else (d + ".__init__" if d + ".__init__" in names else None)
    graph = {k: {resolve(d) for d in v} - {None} for k, v in graph.items()}
    state, stack, cycles = {}, [], []

    def visit(u):
        state[u] = 1
        stack.append(u)
        for v in graph[u]:
            if state.get(v) == 1:
                cycles.append(stack[stack.index(v):] + [v])
            elif v not in state:
                visit(v)
        stack.pop()
        state[u] = 2
    for u in sorted(graph):
        if u not in state:
            visit(u)
    assert not cycles, cycles


def test_function_local_imports_say_why():
    """An import inside a function has a comment on its line or within the few lines above
    it (inside the function, the same block of imports): why it is not at the top."""
    bad = []
    for p, rel, tree in _modules():
        lines = p.read_text().splitlines()
        for fn in ast.walk(tree):
            if not isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            for node in ast.walk(fn):
                if not isinstance(node, (ast.Import, ast.ImportFrom)):
                    continue
                lo = max(fn.lineno, node.lineno - 8)
                near = lines[lo:node.lineno]
                if not any("#" in ln for ln in near):
                    bad.append(f"{rel}:{node.lineno}: {lines[node.lineno - 1].strip()}")
    assert not bad, "\n".join(bad)

"""Which way imports go (issue 31): no library module imports the command line, nothing below training reaches up
into it, the shared helpers import no layer, and no two modules import each other, however indirectly. Checked on
the package's syntax trees (imports inside functions included), so a new import that breaks a layer fails here."""
from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "lsgan"
# package (or module) -> what it may not import: the layers above it (data, models, motion, then train / eval /
# generate / generation / timeline side by side, then export / deploy / serve); lsgan.cli and lsgan.demo sit on top
FORBIDDEN = {
    "lsgan.data": ("lsgan.cli", "lsgan.train", "lsgan.eval", "lsgan.export", "lsgan.serve", "lsgan.deploy",
                   "lsgan.generate", "lsgan.generation", "lsgan.timeline", "lsgan.motion"),
    "lsgan.models": ("lsgan.cli", "lsgan.train", "lsgan.eval", "lsgan.export", "lsgan.serve", "lsgan.deploy",
                     "lsgan.generate", "lsgan.generation", "lsgan.timeline", "lsgan.motion"),
    "lsgan.motion": ("lsgan.cli", "lsgan.train", "lsgan.eval", "lsgan.export", "lsgan.serve", "lsgan.deploy",
                     "lsgan.generate", "lsgan.generation", "lsgan.timeline"),
    "lsgan.eval": ("lsgan.cli", "lsgan.train", "lsgan.export", "lsgan.serve", "lsgan.deploy"),
    "lsgan.train": ("lsgan.cli", "lsgan.export", "lsgan.serve", "lsgan.deploy"),
    "lsgan.generate": ("lsgan.cli", "lsgan.train", "lsgan.export", "lsgan.serve", "lsgan.deploy"),
    "lsgan.generation": ("lsgan.cli", "lsgan.train", "lsgan.export", "lsgan.serve", "lsgan.deploy"),
    "lsgan.timeline": ("lsgan.cli", "lsgan.train", "lsgan.export", "lsgan.serve", "lsgan.deploy"),
    "lsgan.export": ("lsgan.cli", "lsgan.train", "lsgan.serve", "lsgan.deploy"),
    "lsgan.deploy": ("lsgan.cli", "lsgan.train", "lsgan.serve"),
    "lsgan.serve": ("lsgan.cli", "lsgan.train"),
}
LAYERS = ("lsgan.data", "lsgan.models", "lsgan.motion", "lsgan.train", "lsgan.eval", "lsgan.generate", "lsgan.generation",
          "lsgan.timeline", "lsgan.export", "lsgan.deploy", "lsgan.serve", "lsgan.demo", "lsgan.cli")
# below every layer: what any of them may use (errors, outputs, pickles, threads, ...); they import no layer
HELPERS = ("lsgan.device", "lsgan.errors", "lsgan.faults", "lsgan.interrupts", "lsgan.io", "lsgan.outputs",
           "lsgan.pickles", "lsgan.recipes", "lsgan.textcache", "lsgan.threads")
TOP = ("lsgan.cli", "lsgan.demo")  # only the command line imports these (the demo is run by one of its commands)


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports(path: Path) -> set[str]:
    """Every module ``path`` imports, at any depth of the file (function-level imports included)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            found.add(node.module)
            found.update(f"{node.module}.{a.name}" for a in node.names)
    return found


def violations() -> list[str]:
    out = []
    for path in sorted(PACKAGE.rglob("*.py")):
        name = module_name(path)
        for layer, banned in FORBIDDEN.items():
            if name != layer and not name.startswith(layer + "."):
                continue
            out += [f"{name} imports {m}" for m in sorted(imports(path))
                    if any(m == b or m.startswith(b + ".") for b in banned)]
    return out


def within(name: str, prefixes: tuple[str, ...]) -> bool:
    return any(name == p or name.startswith(p + ".") for p in prefixes)


def import_graph() -> dict[str, set[str]]:
    """Module -> the package's modules it imports (``from a.b import c`` is ``a.b.c`` when that is a module)."""
    paths = {module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}

    def module(name: str) -> str:
        while name and name not in paths:
            name = name.rpartition(".")[0]
        return name

    return {name: {module(m) for m in imports(path) if m.startswith("lsgan")} - {"", name}
            for name, path in paths.items()}


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan's algorithm, iteratively)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found = []
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    work.append((child, iter(sorted(graph.get(child, ())))))
                elif child in stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = stack[stack.index(node):]
                del stack[stack.index(node):]
                if len(component) > 1:
                    found.append(sorted(component))
    return found


def test_imports_go_down_the_layers() -> None:
    assert violations() == []


def test_helpers_import_no_layer_and_only_the_cli_imports_the_top() -> None:
    graph = import_graph()
    upward = [f"{m} imports {n}" for m, deps in graph.items() for n in sorted(deps)
              if (within(m, HELPERS) and within(n, LAYERS)) or (within(n, TOP) and not within(m, TOP))
              or (within(n, ("lsgan.cli",)) and not within(m, ("lsgan.cli",)))]
    assert upward == []


def test_no_import_cycles() -> None:
    """Neither between modules nor between packages (lsgan.eval, lsgan.motion, ...: each taken as one node)."""
    graph = import_graph()
    assert cycles(graph) == []
    packages: dict[str, set[str]] = {}
    for module, deps in graph.items():
        top = ".".join(module.split(".")[:2])
        packages.setdefault(top, set()).update(".".join(d.split(".")[:2]) for d in deps)
    assert cycles({p: deps - {p} for p, deps in packages.items()}) == []


def test_the_cycle_check_finds_one() -> None:
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a", "d"}, "d": set(), "e": {"e2"}, "e2": {"e"}}
    assert sorted(cycles(graph)) == [["a", "b", "c"], ["e", "e2"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_the_check_sees_a_forbidden_import(tmp_path, monkeypatch) -> None:
    """The walker finds an upward import written inside a function, as the serve worker's import of the CLI was."""
    fake = tmp_path / "lsgan" / "serve"
    fake.mkdir(parents=True)
    (fake / "worker.py").write_text("def f():\n    from lsgan.cli import describe\n    import lsgan.train.common\n")
    monkeypatch.setattr(__import__(__name__), "PACKAGE", tmp_path / "lsgan")
    assert violations() == ["lsgan.serve.worker imports lsgan.cli", "lsgan.serve.worker imports lsgan.cli.describe",
                            "lsgan.serve.worker imports lsgan.train.common"]


def test_the_quick_subset_exercises_every_package() -> None:
    """Each layer is imported by a module of the quick subset (lsgan.generate, torch generation, runs there through
    ``lsgan generate`` in test_timeline and test_rigid; the helpers are under everything)."""
    from conftest import QUICK

    tests = Path(__file__).resolve().parent
    imported = set().union(*(imports(tests / name.partition("::")[0]) for name in QUICK))
    wanted = [layer for layer in LAYERS if layer != "lsgan.generate"]
    missing = [p for p in wanted if not any(m == p or m.startswith(p + ".") for m in imported)]
    assert missing == []

"""Which way imports go (issue 31): no library module imports the command line, and nothing below training reaches
up into it. Checked on the package's syntax trees, so a new import that breaks a layer fails here."""
from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "lsgan"
# package (or module) -> what it may not import; lsgan.cli and lsgan.demo sit on top and may import anything
FORBIDDEN = {
    "lsgan.data": ("lsgan.cli", "lsgan.train", "lsgan.eval", "lsgan.export", "lsgan.serve", "lsgan.deploy",
                   "lsgan.generate", "lsgan.generation"),
    "lsgan.models": ("lsgan.cli", "lsgan.train", "lsgan.export", "lsgan.serve", "lsgan.deploy"),
    "lsgan.eval": ("lsgan.cli", "lsgan.train", "lsgan.serve", "lsgan.deploy"),
    "lsgan.export": ("lsgan.cli", "lsgan.train", "lsgan.serve", "lsgan.deploy"),
    "lsgan.generate": ("lsgan.cli", "lsgan.train", "lsgan.serve"),
    "lsgan.generation": ("lsgan.cli", "lsgan.train", "lsgan.serve"),
    "lsgan.deploy": ("lsgan.cli", "lsgan.train", "lsgan.serve"),
    "lsgan.serve": ("lsgan.cli", "lsgan.train"),
    "lsgan.train": ("lsgan.cli", "lsgan.serve", "lsgan.deploy"),
}


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


def test_imports_go_down_the_layers() -> None:
    assert violations() == []


def test_the_check_sees_a_forbidden_import(tmp_path, monkeypatch) -> None:
    """The walker finds an upward import written inside a function, as the serve worker's import of the CLI was."""
    fake = tmp_path / "lsgan" / "serve"
    fake.mkdir(parents=True)
    (fake / "worker.py").write_text("def f():\n    from lsgan.cli import describe\n    import lsgan.train.common\n")
    monkeypatch.setattr(__import__(__name__), "PACKAGE", tmp_path / "lsgan")
    assert violations() == ["lsgan.serve.worker imports lsgan.cli", "lsgan.serve.worker imports lsgan.cli.describe",
                            "lsgan.serve.worker imports lsgan.train.common"]

"""The package's import graph and names: no cycles, our own modules imported at the top of
a file, no private name taken from another module, and an ``__all__`` in every module.

A function-level import of an snds module hides a dependency from the reader and, most
often, a cycle from the interpreter. It is allowed only for the optional extras (modules
that need packages a plain install lacks), which must stay out of ``import snds``. A name
with a leading underscore is its module's own business: another module that needs it needs
a public name.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src"
PACKAGE = SRC / "snds"

#: Modules that need an extra (``pip install 'snds[...]'``): they may be imported lazily.
OPTIONAL = ("snds.sim", "snds.export", "snds.app")

#: Function-level imports that are the design: (importing module, imported module) and why.
DELIBERATE: dict[tuple[str, str], str] = {
    ("snds.run", "snds.plotting"): "matplotlib takes about 0.35 s to import: `import snds` "
    "and a run without plots (plots=False) do not pay it",
}


@dataclass(frozen=True)
class Import:
    """One import of an snds module."""

    source: str  # the importing module
    target: str  # the imported module
    line: int
    top_level: bool  # executed when the importing module is (not inside a function)

    def __str__(self) -> str:
        return f"{MODULES[self.source].relative_to(SRC)}:{self.line}: {self.target}"


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(SRC).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


MODULES: dict[str, Path] = {_module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}


def _resolve(name: str) -> str | None:
    """The snds module that importing ``name`` runs last (a name inside a module: that
    module); None outside the package."""
    while name and name not in MODULES:
        name = name.rpartition(".")[0]
    return name or None


def _is_type_checking(node: ast.If) -> bool:
    test = node.test
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _imports(module: str) -> list[Import]:
    path = MODULES[module]
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found: list[Import] = []

    def visit(node: ast.AST, top_level: bool) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.If) and _is_type_checking(child):
                continue  # never executed: a name for the type checker only
            if isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda):
                visit(child, top_level=False)
                continue
            names: list[str] = []
            if isinstance(child, ast.Import):
                names = [alias.name for alias in child.names]
            elif isinstance(child, ast.ImportFrom):
                base = child.module or ""
                if child.level:
                    anchor = package.split(".")[: len(package.split(".")) - child.level + 1]
                    base = ".".join([*anchor, base] if base else anchor)
                # `from snds.x import y` imports the module snds.x.y if there is one.
                names = [f"{base}.{alias.name}" for alias in child.names]
            for name in names:
                target = _resolve(name)
                if target is not None and target != module:
                    found.append(Import(module, target, child.lineno, top_level))
            visit(child, top_level)

    visit(ast.parse(path.read_text(), str(path)), top_level=True)
    return found


IMPORTS: list[Import] = [imp for module in MODULES for imp in _imports(module)]


def _optional(module: str) -> bool:
    return any(module == root or module.startswith(root + ".") for root in OPTIONAL)


def _allowed(imp: Import) -> bool:
    pair = (imp.source, imp.target)
    return _optional(imp.target) or pair in DELIBERATE


def _cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components: list[list[str]] = []

    def connect(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for nxt in sorted(edges.get(node, ())):
            if nxt not in index:
                connect(nxt)
                low[node] = min(low[node], low[nxt])
            elif nxt in on_stack:
                low[node] = min(low[node], index[nxt])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == node:
                    break
            if len(component) > 1:
                components.append(sorted(component))

    for node in sorted(edges):
        if node not in index:
            connect(node)
    return components


def test_the_graph_sees_the_package() -> None:
    # The scan itself: it finds the modules and a known top-level import.
    assert {"snds", "snds.cli", "snds.cli.train", "snds.policy"} <= set(MODULES)
    assert any(
        i.source == "snds.cli.train" and i.target == "snds.train" and i.top_level for i in IMPORTS
    )


def test_no_cycle_among_top_level_imports() -> None:
    edges: dict[str, set[str]] = {}
    for imp in IMPORTS:
        if imp.top_level:
            edges.setdefault(imp.source, set()).add(imp.target)
    assert _cycles(edges) == []


def test_no_cycle_when_function_level_imports_count_too() -> None:
    # A function-level import inside a cycle is a cycle that is only hidden.
    edges: dict[str, set[str]] = {}
    for imp in IMPORTS:
        if imp.top_level or not _allowed(imp):
            edges.setdefault(imp.source, set()).add(imp.target)
    assert _cycles(edges) == []


def test_our_modules_are_imported_at_the_top_except_the_extras() -> None:
    lazy = sorted({str(imp) for imp in IMPORTS if not imp.top_level and not _allowed(imp)})
    assert not lazy, "function-level imports of snds modules:\n" + "\n".join(lazy)


def test_import_snds_leaves_the_extras_and_matplotlib_out() -> None:
    # GIVEN a fresh interpreter that imports the package and its run API
    code = (
        "import sys, snds, snds.run; "
        "print(','.join(sorted(m for m in ('matplotlib', *OPTIONAL) if m in sys.modules)))"
    )
    found = subprocess.run(
        [sys.executable, "-c", f"OPTIONAL = {OPTIONAL!r}; {code}"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout.strip()
    # THEN neither the plots' matplotlib nor an extra was imported
    assert found == ""


#: Underscore names still imported across modules, as (importing module, name); none left.
UNDERSCORE_IMPORTS_LEFT: set[tuple[str, str]] = set()

#: Modules still without ``__all__``: none left.
WITHOUT_ALL_LEFT: set[str] = set()


def _underscore_imports() -> set[tuple[str, str]]:
    """(importing module, name) of every ``from snds.x import _name`` where snds.x is another
    module (a module's own private names are its business; ``__dunder__`` names are not
    private)."""
    found = set()
    for module, path in MODULES.items():
        package = module if path.name == "__init__.py" else module.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if not isinstance(node, ast.ImportFrom):
                continue
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*anchor, base] if base else anchor)
            if base.split(".")[0] != "snds" or base == module:
                continue
            for alias in node.names:
                if alias.name.startswith("_") and not alias.name.startswith("__"):
                    found.add((module, alias.name))
    return found


def _has_all(path: Path) -> bool:
    for node in ast.parse(path.read_text(), str(path)).body:
        targets = node.targets if isinstance(node, ast.Assign) else [getattr(node, "target", None)]
        if any(isinstance(t, ast.Name) and t.id == "__all__" for t in targets):
            return True
    return False


def test_the_name_scans_see_an_offender() -> None:
    # The scans themselves, on made-up modules: an underscore import and a missing __all__.
    source = "from snds.train import _step\nfrom snds.x import __version__, public\n"
    tree = ast.parse(source)
    names = [a.name for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) for a in n.names]
    private = [n for n in names if n.startswith("_") and not n.startswith("__")]
    assert private == ["_step"]
    assert _has_all(PACKAGE / "errors.py")
    assert not _has_all(Path(__file__).with_name("conftest.py"))


def test_no_underscore_name_is_imported_across_modules() -> None:
    found = _underscore_imports()
    new = sorted(found - UNDERSCORE_IMPORTS_LEFT)
    assert not new, "private names imported from another module: " + ", ".join(
        f"{module} imports {name}" for module, name in new
    )


def test_the_underscore_allowlist_holds_only_current_offenders() -> None:
    # An entry that no longer offends goes, so the list shrinks to nothing.
    assert sorted(UNDERSCORE_IMPORTS_LEFT - _underscore_imports()) == []


def test_every_module_has_all() -> None:
    # (`__main__` files are `python -m` entry points: they run the CLI and define nothing)
    missing = {
        module
        for module, path in MODULES.items()
        if path.name != "__main__.py" and not _has_all(path)
    }
    assert sorted(missing - WITHOUT_ALL_LEFT) == []
    # an entry that has its __all__ now goes from the list
    assert sorted(WITHOUT_ALL_LEFT - missing) == []

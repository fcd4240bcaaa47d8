"""The layers stay layered: checked on the source with ``ast``, so a wrong import fails here.

- ``service.ml`` (the models and the geometry) imports no storage, API or application code;
- a route module imports no ``service.storage`` at run time (it calls the application layer;
  imports under ``if TYPE_CHECKING:`` only name types for annotations);
- nothing in ``service`` imports ``workers`` (the worker entry point sits on top).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SERVICE = ROOT / "service"
APPLICATION = ("service.atlas", "service.jobs", "service.fleet", "service.index", "service.runtime")


def runtime_imports(source: str, package: str) -> set[str]:
    """Modules a module of ``package`` imports outside ``if TYPE_CHECKING:`` blocks (relative
    imports resolved)."""
    tree = ast.parse(source)
    found: set[str] = set()

    def visit(node: ast.AST) -> None:
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            for child in node.orelse:
                visit(child)
            return
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parent = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*parent, base] if base else parent)
            found.add(base)
            found.update(f"{base}.{alias.name}" for alias in node.names)
        for child in ast.iter_child_nodes(node):
            visit(child)

    visit(tree)
    return found


def package_of(path: Path) -> str:
    return ".".join(path.relative_to(ROOT).with_suffix("").parts[:-1])


def forbidden_in(names: set[str], forbidden: tuple[str, ...]) -> bool:
    return any(n == f or n.startswith(f + ".") for n in names for f in forbidden)


def violations(files: list[Path], forbidden: tuple[str, ...]) -> list[str]:
    return sorted(
        f"{path.relative_to(ROOT)} imports {name}"
        for path in files
        for name in runtime_imports(path.read_text(), package_of(path))
        if any(name == f or name.startswith(f + ".") for f in forbidden)
    )


def test_ml_imports_no_storage_api_or_application_code() -> None:
    files = sorted((SERVICE / "ml").rglob("*.py"))
    assert files
    forbidden = ("service.storage", "service.api", "service.config", "workers", *APPLICATION)
    assert violations(files, forbidden) == []


def test_routes_never_import_storage() -> None:
    files = sorted((SERVICE / "api" / "routes").rglob("*.py"))
    assert files
    assert violations(files, ("service.storage",)) == []


def test_service_never_imports_workers() -> None:
    assert violations(sorted(SERVICE.rglob("*.py")), ("workers",)) == []


@pytest.mark.parametrize(
    ("source", "forbidden", "expected"),
    [
        ("from service.storage import repository\n", ("service.storage",), True),
        ("import service.storage.db\n", ("service.storage",), True),
        ("from ...storage import db\n", ("service.storage",), True),
        ("from ..storage import db\n", ("service.storage",), False),
        (
            "if TYPE_CHECKING:\n    from service.storage.models import Job\n",
            ("service.storage",),
            False,
        ),
        ("from service.storage_notes import x\n", ("service.storage",), False),
        ("def f():\n    from workers import queue\n", ("workers",), True),
    ],
)
def test_the_check_sees_what_it_must(
    source: str, forbidden: tuple[str, ...], expected: bool
) -> None:
    names = runtime_imports(source, "service.api.routes")
    assert forbidden_in(names, forbidden) is expected

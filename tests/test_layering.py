"""The layers stay layered: checked on the source with ``ast``, so a wrong import fails here.

- ``service.ml`` (the models and the geometry) imports no storage, API or application code and
  reads no environment variable (settings are passed in);
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


ENVIRONMENT = {"environ", "environb", "getenv", "getenvb", "putenv", "unsetenv"}


def environment_reads(source: str) -> list[str]:
    """Where a module touches the environment through ``os`` (``os.environ``, ``os.getenv``,
    ``from os import environ``), as ``line: code``."""
    found = []
    for node in ast.walk(ast.parse(source)):
        touches = (
            isinstance(node, ast.Attribute)
            and node.attr in ENVIRONMENT
            and isinstance(node.value, ast.Name)
            and node.value.id == "os"
        ) or (
            isinstance(node, ast.ImportFrom)
            and node.module == "os"
            and any(alias.name in ENVIRONMENT for alias in node.names)
        )
        if touches:
            found.append(f"{node.lineno}: {ast.unparse(node)}")
    return found


def test_ml_reads_no_environment_variable() -> None:
    reads = {
        str(path.relative_to(ROOT)): environment_reads(path.read_text())
        for path in sorted((SERVICE / "ml").rglob("*.py"))
    }
    assert {path: found for path, found in reads.items() if found} == {}


@pytest.mark.parametrize(
    ("source", "expected"),
    [
        ("import os\nx = os.environ.get('LOOPNET_OFFLINE')\n", True),
        ("import os\nx = os.getenv('A')\n", True),
        ("from os import environ\n", True),
        ("from os import getenv as g\n", True),
        ("import os\nx = os.path.join('a', 'b')\n", False),
        ("x = settings.environ\n", False),
    ],
)
def test_the_environment_check_sees_what_it_must(source: str, expected: bool) -> None:
    assert bool(environment_reads(source)) is expected


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

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
APPLICATION = ("service.app", "service.jobs", "service.fleet", "service.index", "service.runtime")


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


# The floor plan, bottom to top: a package imports only packages of its own floor or below.
FLOORS: dict[str, int] = {
    # value types and errors, no I/O
    "domain": 0,
    "errors": 0,
    # the models, geometry and process-level plumbing that knows nothing of atlases
    "ml": 1,
    "npz_reader": 1,
    "metrics": 1,
    "concurrency": 1,
    # settings, the database, the vector index, payload formats
    "config": 2,
    "config_sections": 2,
    "config_boundary": 2,
    "storage": 2,
    "index": 2,
    "features_payload": 2,
    # the application's use cases
    "app": 3,
    "jobs": 4,
    "fleet": 4,
    # the process and the harness that drives the use cases
    "runtime": 5,
    "evaluation": 5,
    # the HTTP front and its pages
    "api": 6,
    "console": 6,
    # the command line and the tools on top of everything
    "client": 7,
    "cli": 7,
    "cli_atlas": 7,
    "cli_eval": 7,
    "cli_fleet": 7,
    "config_docs": 7,
}


def package_edges() -> dict[str, set[str]]:
    """Top-level package of ``service`` -> the top-level packages it imports at run time."""
    edges: dict[str, set[str]] = {}
    for path in sorted(SERVICE.rglob("*.py")):
        parts = path.relative_to(SERVICE).with_suffix("").parts
        if parts == ("__init__",):
            continue
        me = parts[0]
        for name in runtime_imports(path.read_text(), package_of(path)):
            target = name.split(".")
            inside = target[0] == "service" and len(target) > 1 and target[1] != me
            if inside and (
                (SERVICE / target[1]).is_dir() or (SERVICE / f"{target[1]}.py").exists()
            ):
                edges.setdefault(me, set()).add(target[1])
    return edges


def cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected groups of more than one package (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        for other in edges.get(node, ()):
            if other not in index:
                visit(other)
                low[node] = min(low[node], low[other])
            elif other in stack:
                low[node] = min(low[node], index[other])
        if low[node] == index[node]:
            group = []
            while True:
                member = stack.pop()
                group.append(member)
                if member == node:
                    break
            if len(group) > 1:
                found.append(sorted(group))

    for node in sorted(edges):
        if node not in index:
            visit(node)
    return found


def test_every_package_has_a_floor() -> None:
    packages = {
        p.stem if p.is_file() else p.name
        for p in SERVICE.iterdir()
        if (p.suffix == ".py" and p.stem != "__init__") or (p / "__init__.py").exists()
    }
    assert packages - FLOORS.keys() == set()


def test_no_package_imports_a_floor_above_it() -> None:
    upward = sorted(
        f"{package} (floor {FLOORS[package]}) imports {other} (floor {FLOORS[other]})"
        for package, others in package_edges().items()
        for other in others
        if FLOORS[other] > FLOORS[package]
    )
    assert upward == []


def test_no_import_cycles_between_packages() -> None:
    assert cycles(package_edges()) == []


def test_the_cycle_check_sees_a_cycle() -> None:
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_api_never_handles_sessions_nor_imports_storage() -> None:
    """The HTTP layer calls use cases (:class:`~service.app.catalog.AtlasService`, the
    runtime's jobs, keys and snapshots); sessions and storage stay beneath them."""
    files = sorted((SERVICE / "api").rglob("*.py"))
    touching = sorted(
        f"{path.relative_to(ROOT)}:{node.lineno}"
        for path in files
        for node in ast.walk(ast.parse(path.read_text()))
        if (isinstance(node, ast.Attribute) and node.attr == "sessions")
        or (isinstance(node, ast.Name) and node.id == "sessions")
    )
    assert touching == []
    assert violations(files, ("service.storage",)) == []

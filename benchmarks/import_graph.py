"""The shape of the service's imports, as tests/test_layering.py reads them from the source:
the package import cycles and the longest chain of run-time imports from a module.

    python benchmarks/import_graph.py [--root .] [--start service.api.app]

Prints the cycles between packages (none is the rule) and the longest chain, module by module.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def module_edges(root: Path) -> dict[str, set[str]]:
    """Module -> the service modules it imports at run time (``if TYPE_CHECKING`` left out)."""
    sys.path.insert(0, str(root / "tests"))
    from test_layering import package_of, runtime_imports

    modules: dict[str, Path] = {}
    for path in (root / "service").rglob("*.py"):
        parts = list(path.relative_to(root).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        modules[".".join(parts)] = path
    edges: dict[str, set[str]] = {}
    for name, path in modules.items():
        package = name if path.name == "__init__.py" else package_of(path)
        found: set[str] = set()
        for imported in runtime_imports(path.read_text(), package):
            while imported and imported not in modules:
                imported = imported.rpartition(".")[0]
            if imported and imported != name:
                found.add(imported)
        edges[name] = found
    return edges


def longest_chain(edges: dict[str, set[str]], start: str) -> list[str]:
    """The longest import chain from ``start`` (a module met again on the way ends it)."""
    best: dict[str, list[str]] = {}

    def visit(module: str, on_path: set[str]) -> list[str]:
        if module in best:
            return best[module]
        on_path.add(module)
        chain = [module]
        for other in sorted(edges.get(module, ())):
            if other in on_path:
                continue
            below = visit(other, on_path)
            if len(below) + 1 > len(chain):
                chain = [module, *below]
        on_path.discard(module)
        best[module] = chain
        return chain

    return visit(start, set())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--root", type=Path, default=Path("."))
    parser.add_argument("--start", default="service.api.app")
    args = parser.parse_args()
    root = args.root.resolve()
    sys.path.insert(0, str(root / "tests"))
    from test_layering import cycles, package_edges

    found = cycles(package_edges())
    print(f"package cycles: {len(found)} {found}")
    chain = longest_chain(module_edges(root), args.start)
    print(f"longest import chain from {args.start}: {len(chain)} modules")
    print(" -> ".join(chain))


if __name__ == "__main__":
    main()

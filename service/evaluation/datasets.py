"""Read a dataset folder in any layout users already have into one :class:`Dataset`.

:func:`detect_layout` picks the layout from the folder's contents (``LAYOUTS``, described in
:mod:`service.evaluation.dataset_layouts`, which reads each one); :func:`load_dataset` reads it.
What a dataset is lives in :mod:`service.evaluation.dataset_model`; its names are re-exported
here, where the harness has always imported them from.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from pathlib import Path

from service.evaluation.dataset_layouts import (
    CSV_NAME,
    LOOPDB_IMAGES,
    VPR_BENCH_GT,
    place_folders,
    read_csv,
    read_loopdb,
    read_places,
    read_traversals,
    read_vpr_bench,
)
from service.evaluation.dataset_model import (
    Dataset,
    DatasetError,
    QueryFrame,
    ReferenceFrame,
    image_folders,
    list_images,
    natural_key,
    require,
)

__all__ = [
    "LAYOUTS",
    "Dataset",
    "DatasetError",
    "QueryFrame",
    "ReferenceFrame",
    "all_images",
    "detect_layout",
    "list_images",
    "load_dataset",
    "natural_key",
]

LAYOUTS = ("traversals", "vpr-bench", "loopdb", "csv", "places")


def detect_layout(root: Path) -> str:
    """The layout of ``root``, judged from the files that define each one."""
    require(root.is_dir(), f"{root} is not a folder")
    if (root / VPR_BENCH_GT).is_file():
        return "vpr-bench"
    if (root / LOOPDB_IMAGES).is_file():
        return "loopdb"
    if (root / CSV_NAME).is_file():
        return "csv"
    folders = image_folders(root)
    if (root / "ref").is_dir() and (root / "query").is_dir():
        nested = place_folders(root / "ref")
        return "places" if nested and not list_images(root / "ref") else "traversals"
    if len(folders) == 2 and len(list_images(folders[0])) == len(list_images(folders[1])):
        return "traversals"
    if folders or place_folders(root):
        return "places"
    raise DatasetError(
        f"{root}: no known dataset layout (expected one of {', '.join(LAYOUTS)}); "
        "see `loopnet eval --help`"
    )


def load_dataset(
    root: Path,
    *,
    layout: str = "auto",
    tolerance: int | None = None,
    distance: float = 25.0,
    reference: str | None = None,
    query: str | None = None,
) -> Dataset:
    """Read ``root`` in ``layout`` (``auto``: :func:`detect_layout`)."""
    root = Path(root)
    chosen = detect_layout(root) if layout == "auto" else layout
    frame_tolerance = 1 if tolerance is None else tolerance
    readers: dict[str, Callable[[], Dataset]] = {
        "traversals": lambda: read_traversals(
            root, tolerance=frame_tolerance, reference=reference, query=query
        ),
        "vpr-bench": lambda: read_vpr_bench(root),
        "loopdb": lambda: read_loopdb(root),
        "csv": lambda: read_csv(root, tolerance=frame_tolerance, distance=distance),
        "places": lambda: read_places(root),
    }
    if chosen not in readers:
        raise DatasetError(f"unknown layout {chosen!r}; choose one of {', '.join(LAYOUTS)}")
    try:
        dataset = readers[chosen]()
    except DatasetError:
        raise
    except (OSError, ValueError, KeyError, IndexError) as exc:  # the folder is another layout
        raise DatasetError(f"{root} does not read as layout {chosen!r}: {exc}") from exc
    require(bool(dataset.references), f"{root}: no reference images")
    require(bool(dataset.queries), f"{root}: no query images")
    return dataset


def all_images(dataset: Dataset) -> Iterable[Path]:
    """Every image the run reads, references first."""
    yield from (r.path for r in dataset.references)
    yield from (q.path for q in dataset.queries)

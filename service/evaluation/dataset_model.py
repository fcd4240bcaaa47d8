"""What a place-recognition dataset is, whatever layout it was read from: its references, its
queries with their ground truth, and the file listing every reader shares."""

from __future__ import annotations

import re
from dataclasses import dataclass, field, replace
from pathlib import Path

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".webp")


class DatasetError(ValueError):
    """The folder does not hold a dataset in the layout asked for (a message for the user)."""


@dataclass(frozen=True)
class ReferenceFrame:
    """A frame of the map.

    Attributes:
        path: the image file.
        place: the dataset's label of the place it shows (or its frame number as text).
        order: its position along the traversal (frame index), used for tolerances and for
            grouping consecutive frames into submaps.
        submap: the dataset's own submap label, where the layout has one (LoopDB, CSV, places).
        position: x, y (, z) in metres, or lat, lon in degrees (see ``geodetic``), if known.
    """

    path: Path
    place: str
    order: int
    submap: str | None = None
    position: tuple[float, ...] | None = None


@dataclass(frozen=True)
class QueryFrame:
    """A frame to localise, with the indices (into ``Dataset.references``) that are right."""

    path: Path
    positives: frozenset[int]
    place: str = ""


@dataclass
class Dataset:
    """References (the map, in traversal order), queries with their ground truth, and the rule.

    Attributes:
        ground_truth: how ``positives`` were decided, in words ("frame within ±2 places").
        tolerance: the frame tolerance, where the rule is one (None otherwise).
        excluded: what the reader left out and why, one line each.
    """

    name: str
    layout: str
    root: Path
    references: list[ReferenceFrame]
    queries: list[QueryFrame]
    ground_truth: str
    tolerance: int | None = None
    excluded: list[str] = field(default_factory=list)

    @property
    def has_native_submaps(self) -> bool:
        return bool(self.references) and all(r.submap is not None for r in self.references)

    def head(self, references: int) -> Dataset:
        """The first ``references`` reference frames and the queries still answerable in them.

        Used for quick slices (tests, smoke runs); positives outside the slice are dropped.
        """
        if references >= len(self.references):
            return self
        queries = [
            replace(q, positives=frozenset(i for i in q.positives if i < references))
            for q in self.queries
        ]
        kept = [q for q in queries if q.positives]
        return replace(
            self,
            references=self.references[:references],
            queries=kept,
            excluded=[
                *self.excluded,
                f"slice: first {references} of {len(self.references)} references and the "
                f"{len(kept)} of {len(self.queries)} queries whose ground truth lies in them",
            ],
        )

    def without(self, dropped: dict[Path, str]) -> Dataset:
        """The dataset without the images in ``dropped`` (path -> why), positives renumbered;
        queries left without a positive are dropped too. Each drop is listed in ``excluded``."""
        if not dropped:
            return self
        kept_refs = [i for i, r in enumerate(self.references) if r.path not in dropped]
        renumber = {old: new for new, old in enumerate(kept_refs)}
        queries = [
            replace(q, positives=frozenset(renumber[i] for i in q.positives if i in renumber))
            for q in self.queries
            if q.path not in dropped
        ]
        answerable = [q for q in queries if q.positives]
        notes = [f"unreadable image {path}: {why}" for path, why in sorted(dropped.items())]
        if len(answerable) < len(queries):
            notes.append(
                f"{len(queries) - len(answerable)} queries whose every positive was unreadable"
            )
        return replace(
            self,
            references=[self.references[i] for i in kept_refs],
            queries=answerable,
            excluded=[*self.excluded, *notes],
        )


def natural_key(name: str) -> list[object]:
    """Sort key that orders ``img2`` before ``img10``."""
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


def list_images(folder: Path) -> list[Path]:
    """Image files directly in ``folder``, in natural name order (frame order)."""
    return sorted(
        (p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES),
        key=lambda p: natural_key(p.name),
    )


def image_folders(root: Path) -> list[Path]:
    """Sub-folders of ``root`` that directly hold images, in natural order."""
    return sorted(
        (d for d in root.iterdir() if d.is_dir() and list_images(d)),
        key=lambda d: natural_key(d.name),
    )


def require(condition: bool, message: str) -> None:
    if not condition:
        raise DatasetError(message)

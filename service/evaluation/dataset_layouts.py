"""The readers of the dataset layouts users already have, each into one :class:`Dataset`.

Layouts (``datasets.LAYOUTS``; ``datasets.detect_layout`` picks one from the folder's contents):

- ``traversals``: two folders of the same route (e.g. ``ref/`` + ``query/``, or ``summer/`` +
  ``winter/``) whose i-th images (natural name order) show the same place. Query i is right on
  references ``i - tolerance .. i + tolerance``. A ``gt.csv`` beside them with a ``degenerate``
  column marks pairs to leave out (Nordland's black or frozen frames).
- ``vpr-bench``: ``query/``, ``ref/`` and ``ground_truth_new.npy``, rows ``[query, [refs]]``
  indexing the images in natural name order (VPR-Bench's convention).
- ``loopdb``: LoopDB's ``datastream_1/data_descriptor.csv`` (the images) and
  ``datastream_2/data_descriptor.csv`` (each shot's submap root, rotation and translation).
  Submaps are the dataset's own; the last shot of each submap is its query, the others are
  references, and a query is right on any reference of its submap.
- ``csv``: a ``dataset.csv`` for users' own data; columns are documented in :func:`read_csv`.
- ``places``: ``<place>/<image>`` folders, or ``<place>/<view>/<image>`` for places seen from
  several views; two images match when they share the place. With ``ref/<place>/`` and
  ``query/<place>/`` the split is given; otherwise the first image of each place (natural
  order) is its reference and the others are queries.
"""

from __future__ import annotations

import csv
import math
import re
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from service.evaluation.dataset_model import (
    IMAGE_SUFFIXES,
    Dataset,
    QueryFrame,
    ReferenceFrame,
    image_folders,
    list_images,
    natural_key,
    require,
)

CSV_NAME = "dataset.csv"
VPR_BENCH_GT = "ground_truth_new.npy"
LOOPDB_IMAGES = Path("datastream_1") / "data_descriptor.csv"
LOOPDB_POSES = Path("datastream_2") / "data_descriptor.csv"


# ----- frame-aligned traversals -----------------------------------------------------------


def _traversal_folders(root: Path, reference: str | None, query: str | None) -> tuple[Path, Path]:
    if reference and query:
        return root / reference, root / query
    if (root / "ref").is_dir() and (root / "query").is_dir():
        return root / "ref", root / "query"
    folders = image_folders(root)
    require(
        len(folders) == 2,
        f"{root}: a traversal layout needs ref/ and query/, or exactly two image folders "
        f"(found {[f.name for f in folders]}); name them with --reference and --query",
    )
    return folders[0], folders[1]


def _degenerate_paths(root: Path) -> set[str]:
    """Image paths (relative to ``root``) on ``gt.csv`` rows flagged ``degenerate``."""
    gt = root / "gt.csv"
    if not gt.is_file():
        return set()
    with gt.open(newline="") as handle:
        rows = list(csv.DictReader(handle))
    if not rows or "degenerate" not in rows[0]:
        return set()
    flagged: set[str] = set()
    for row in rows:
        if row["degenerate"].strip() not in ("", "0", "false", "False"):
            flagged.update(v for v in row.values() if v and "/" in v)
    return flagged


def read_traversals(
    root: Path, *, tolerance: int = 1, reference: str | None = None, query: str | None = None
) -> Dataset:
    """Two frame-aligned traversals; the first folder in natural order is the map by default."""
    ref_dir, query_dir = _traversal_folders(root, reference, query)
    refs, queries = list_images(ref_dir), list_images(query_dir)
    require(
        len(refs) == len(queries) > 0,
        f"{root}: {ref_dir.name}/ has {len(refs)} images and {query_dir.name}/ has "
        f"{len(queries)}; frame-aligned traversals need the same number",
    )
    flagged = _degenerate_paths(root)
    keep = [
        i
        for i in range(len(refs))
        if refs[i].relative_to(root).as_posix() not in flagged
        and queries[i].relative_to(root).as_posix() not in flagged
    ]
    position = {frame: slot for slot, frame in enumerate(keep)}
    references = [ReferenceFrame(refs[i], place=str(i), order=i) for i in keep]
    query_frames = [
        QueryFrame(
            queries[i],
            frozenset(
                position[j] for j in range(i - tolerance, i + tolerance + 1) if j in position
            ),
            place=str(i),
        )
        for i in keep
    ]
    excluded = []
    if len(keep) < len(refs):
        excluded.append(
            f"{len(refs) - len(keep)} frame pairs flagged degenerate in gt.csv (left out of "
            "both the map and the queries)"
        )
    return Dataset(
        name=root.name,
        layout="traversals",
        root=root,
        references=references,
        queries=query_frames,
        ground_truth=(
            f"frame-aligned traversals {ref_dir.name}/ (map) and {query_dir.name}/ (queries): "
            f"query i is right on reference frames i±{tolerance}"
        ),
        tolerance=tolerance,
        excluded=excluded,
    )


# ----- VPR-Bench --------------------------------------------------------------------------


def read_vpr_bench(root: Path) -> Dataset:
    refs, queries = list_images(root / "ref"), list_images(root / "query")
    rows = np.load(root / VPR_BENCH_GT, allow_pickle=True)
    positives: dict[int, frozenset[int]] = {}
    for row in rows:
        query_index, ref_indices = int(row[0]), np.atleast_1d(np.asarray(row[1], dtype=np.int64))
        require(
            0 <= query_index < len(queries) and all(0 <= r < len(refs) for r in ref_indices),
            f"{root / VPR_BENCH_GT}: row {query_index} indexes images that do not exist "
            f"({len(queries)} queries, {len(refs)} references)",
        )
        positives[query_index] = frozenset(int(r) for r in ref_indices)
    return Dataset(
        name=root.name,
        layout="vpr-bench",
        root=root,
        references=[ReferenceFrame(p, place=str(i), order=i) for i, p in enumerate(refs)],
        queries=[
            QueryFrame(p, positives.get(i, frozenset()), place=str(i))
            for i, p in enumerate(queries)
        ],
        ground_truth=f"the references listed for each query in {VPR_BENCH_GT}",
    )


# ----- LoopDB -----------------------------------------------------------------------------


def _find_image(root: Path, stored: str) -> Path:
    """LoopDB stores Windows paths without a suffix (``datastream_1\\samples\\left\\IMG_1``)."""
    base = root / Path(*re.split(r"[\\/]", stored.strip()))
    if base.suffix.lower() in IMAGE_SUFFIXES and base.is_file():
        return base
    for suffix in (*IMAGE_SUFFIXES, *(s.upper() for s in IMAGE_SUFFIXES)):
        candidate = base.with_name(base.name + suffix)
        if candidate.is_file():
            return candidate
    raise ValueError(f"{root}: image {stored!r} listed in {LOOPDB_IMAGES} is missing")


def _float_or_none(values: Sequence[str]) -> tuple[float, ...] | None:
    try:
        return tuple(float(v) for v in values)
    except ValueError:
        return None


def read_loopdb(root: Path) -> Dataset:
    with (root / LOOPDB_IMAGES).open(newline="") as handle:
        shots = [
            (row["timestamp_start"].strip(), row["left_file_path_0"])
            for row in csv.DictReader(handle)
            if (row.get("timestamp_start") or "").strip()
        ]
    root_of: dict[str, str] = {}
    translation: dict[str, tuple[float, ...] | None] = {}
    if (root / LOOPDB_POSES).is_file():
        with (root / LOOPDB_POSES).open(newline="") as handle:
            for row in csv.DictReader(handle):
                shot = (row.get("timestamp_start") or "").strip()
                if shot:
                    root_of[shot] = row["timestamp_root"].strip()
                    translation[shot] = _float_or_none([row["tx"], row["ty"], row["tz"]])
    if not root_of:  # no pose stream: LoopDB's convention of five consecutive shots a scene
        root_of = {shot: shots[i - i % 5][0] for i, (shot, _) in enumerate(shots)}
    by_submap: dict[str, list[tuple[str, Path]]] = {}
    for shot, stored in shots:
        by_submap.setdefault(root_of.get(shot, shot), []).append((shot, _find_image(root, stored)))
    references: list[ReferenceFrame] = []
    held_out: list[tuple[Path, str]] = []
    for submap, members in by_submap.items():
        members.sort(key=lambda m: natural_key(m[0]))
        # the last shot is the submap's query; a single shot cannot be both map and query
        mapped = members[:-1] if len(members) > 1 else members
        for shot, path in mapped:
            references.append(
                ReferenceFrame(path, submap, len(references), submap, translation.get(shot))
            )
        if len(members) > 1:
            held_out.append((members[-1][1], submap))
    members_of: dict[str, set[int]] = {}
    for index, ref in enumerate(references):
        members_of.setdefault(ref.place, set()).add(index)
    return Dataset(
        name=root.name,
        layout="loopdb",
        root=root,
        references=references,
        queries=[QueryFrame(p, frozenset(members_of[s]), place=s) for p, s in held_out],
        ground_truth="same LoopDB submap (timestamp_root); the last shot of each submap is its query",
    )


# ----- generic CSV ------------------------------------------------------------------------


def _haversine_m(a: tuple[float, ...], b: tuple[float, ...]) -> float:
    lat1, lon1, lat2, lon2 = map(math.radians, (a[0], a[1], b[0], b[1]))
    h = (
        math.sin((lat2 - lat1) / 2) ** 2
        + math.cos(lat1) * math.cos(lat2) * math.sin((lon2 - lon1) / 2) ** 2
    )
    return 2 * 6_371_000.0 * math.asin(math.sqrt(h))


def _position(row: dict[str, str]) -> tuple[tuple[float, ...] | None, bool]:
    """(position, geodetic) of a CSV row: x, y[, z] in metres or lat, lon in degrees."""
    if (row.get("lat") or "").strip() and (row.get("lon") or "").strip():
        return (float(row["lat"]), float(row["lon"])), True
    coords = [row.get(c, "").strip() for c in ("x", "y", "z")]
    if coords[0] and coords[1]:
        return tuple(float(c) for c in coords if c), False
    return None, False


def read_csv(root: Path, *, tolerance: int = 1, distance: float = 25.0) -> Dataset:
    """Users' own data: ``dataset.csv`` with one row per image.

    Columns (a header row is required; only ``role`` and ``image`` are mandatory):

    - ``role``: ``reference`` (a map frame) or ``query``;
    - ``image``: the image path, relative to the CSV's folder;
    - ``place``: a place label; ``submap``: the map's submap label (references);
    - ``frame``: the frame number along its traversal (references are ordered by it);
    - ``x``, ``y`` (, ``z``) in metres, or ``lat``, ``lon`` in degrees;
    - ``positives`` (queries): the right references' ``image`` paths, separated by ``;``.

    A query's right references come from the first rule its row allows: its ``positives``;
    references within ``distance`` metres (positions); frames within ``tolerance`` of its
    ``frame``; references with its ``place``.
    """
    with (root / CSV_NAME).open(newline="") as handle:
        rows = [
            {k.strip(): (v or "").strip() for k, v in r.items() if k}
            for r in csv.DictReader(handle)
        ]
    require(bool(rows), f"{root / CSV_NAME} has no rows")
    require(
        {"role", "image"} <= set(rows[0]),
        f"{root / CSV_NAME} needs the columns role and image (has {sorted(rows[0])})",
    )
    ref_rows = [r for r in rows if r["role"] == "reference"]
    query_rows = [r for r in rows if r["role"] == "query"]
    require(
        len(ref_rows) + len(query_rows) == len(rows),
        f"{root / CSV_NAME}: role must be 'reference' or 'query'",
    )
    if all(r.get("frame") for r in ref_rows):
        ref_rows.sort(key=lambda r: int(r["frame"]))
    references = [
        ReferenceFrame(
            root / row["image"],
            place=row.get("place") or str(i),
            order=int(row["frame"]) if row.get("frame") else i,
            submap=row.get("submap") or None,
            position=_position(row)[0],
        )
        for i, row in enumerate(ref_rows)
    ]
    index_of = {r["image"]: i for i, r in enumerate(ref_rows)}
    rules_used: set[str] = set()

    def positives_of(row: dict[str, str]) -> frozenset[int]:
        if row.get("positives"):
            rules_used.add("listed positives")
            names = [n.strip() for n in row["positives"].split(";") if n.strip()]
            missing = [n for n in names if n not in index_of]
            require(not missing, f"{root / CSV_NAME}: positives {missing} are not references")
            return frozenset(index_of[n] for n in names)
        position, query_geodetic = _position(row)
        if position is not None:
            rules_used.add(f"within {distance:g} m")
            measure: Callable[[tuple[float, ...], tuple[float, ...]], float] = (
                _haversine_m if query_geodetic else math.dist
            )
            return frozenset(
                i
                for i, ref in enumerate(references)
                if ref.position is not None and measure(position, ref.position) <= distance
            )
        if row.get("frame"):
            rules_used.add(f"frame within ±{tolerance}")
            frame = int(row["frame"])
            return frozenset(
                i for i, ref in enumerate(references) if abs(ref.order - frame) <= tolerance
            )
        require(
            bool(row.get("place")), f"{root / CSV_NAME}: query {row['image']} has no ground truth"
        )
        rules_used.add("same place")
        return frozenset(i for i, ref in enumerate(references) if ref.place == row["place"])

    queries = [
        QueryFrame(root / r["image"], positives_of(r), place=r.get("place", "")) for r in query_rows
    ]
    paths = [r.path for r in references] + [q.path for q in queries]
    missing_files = [str(p) for p in paths if not p.is_file()]
    require(not missing_files, f"{root / CSV_NAME}: missing images {missing_files[:5]}")
    return Dataset(
        name=root.name,
        layout="csv",
        root=root,
        references=references,
        queries=queries,
        ground_truth=f"{CSV_NAME}: " + ", ".join(sorted(rules_used)),
        tolerance=tolerance if any("frame" in r for r in rules_used) else None,
    )


# ----- place-labelled folders -------------------------------------------------------------


def place_images(folder: Path) -> list[Path]:
    """A place's images: those directly in it, then those of its view sub-folders."""
    views = sorted((d for d in folder.iterdir() if d.is_dir()), key=lambda d: natural_key(d.name))
    return list_images(folder) + [path for view in views for path in list_images(view)]


def place_folders(root: Path) -> list[Path]:
    """Sub-folders of ``root`` holding images directly or in view sub-folders."""
    return sorted(
        (d for d in root.iterdir() if d.is_dir() and place_images(d)),
        key=lambda d: natural_key(d.name),
    )


def _places(folder: Path) -> list[tuple[str, list[Path]]]:
    return [(d.name, place_images(d)) for d in place_folders(folder)]


def read_places(root: Path) -> Dataset:
    if (root / "ref").is_dir() and (root / "query").is_dir():
        mapped = _places(root / "ref")
        asked = _places(root / "query")
        split = "ref/<place>/ and query/<place>/"
    else:
        places = _places(root)
        mapped = [(name, images[:1]) for name, images in places]
        asked = [(name, images[1:]) for name, images in places]
        split = "the first image of each place is its reference, the others are queries"
    require(bool(mapped), f"{root}: no <place>/<image> folders")
    paths = [(name, path) for name, images in mapped for path in images]
    references = [
        ReferenceFrame(path, place=name, order=i, submap=name)
        for i, (name, path) in enumerate(paths)
    ]
    members = {
        name: frozenset(i for i, ref in enumerate(references) if ref.place == name)
        for name, _ in mapped
    }
    return Dataset(
        name=root.name,
        layout="places",
        root=root,
        references=references,
        queries=[
            QueryFrame(path, members.get(name, frozenset()), place=name)
            for name, images in asked
            for path in images
        ],
        ground_truth=f"same place folder ({split})",
    )

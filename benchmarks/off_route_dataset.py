"""A drive that leaves the map: frame-aligned traversals rewritten as a VPR-Bench folder in
which the querying robot drives where no reference was taken, to measure what the sequence
decision does there.

    python benchmarks/off_route_dataset.py ../shared/data/nordland_64x32 /work/tmp/nord_detours \\
        --detours --stretches 10 --length 40
    loopnet eval /work/tmp/nord_detours --layout vpr-bench --tolerance 1 --sequence 10 ...

A short drive works the same way with fewer, shorter detours (stop 46's second proxy):

    python benchmarks/off_route_dataset.py ../shared/data/gardenspoint_cohog200 \
        /work/tmp/cohog_detours --detours --stretches 4 --length 10 --tolerance 2

Two constructions:

- ``--detours`` (the faithful one): the map is the route without its last ``stretches x length``
  frames, one unbroken trajectory as a mapping robot drives it. The querying robot drives the
  mapped route in order, but ``stretches`` times it leaves it for a detour of ``length`` frames
  of the unmapped tail (look-alike scenery of the same route, another season) and then comes
  back where it left. The map's trajectory runs on along the route past each turn-off, as a
  real map's does, so the frames just off the route are judged against the place the robot
  would have reached had it stayed.
- gaps (the default, stop 42's): the map lacks ``stretches`` runs of ``length`` frames inside the
  route and the robot drives the whole route. The map's trajectory then runs across each
  removed stretch without a time gap, which no real map does; kept to reproduce stop 42.

A query with no right reference left has no positive, so any ``loop`` answered for it is false
(the harness counts it so). Images are symbolic links, so nothing is copied. Nothing here is a
service path.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from served_report import loop_frames  # a sibling script (its folder is on the path)

from service.evaluation.dataset_layouts import VPR_BENCH_GT, read_traversals
from service.ml.sequences.distinctiveness import NEWEST_Z_MIN

# what write_detours records beside the folder: each query's place on the drive
ROUTE_FILE = "route.json"
# frames after a turn (off the route, or back onto it) that are read one by one
TURN_FRAMES = 10


def unmapped_stretches(frames: int, stretches: int, length: int) -> np.ndarray:
    """Frame indices left out of the map: ``stretches`` runs of ``length`` frames, evenly
    spread between the route's ends (never its first or last stretch)."""
    starts = np.linspace(0, frames - length, stretches + 2).astype(int)[1:-1]
    return np.unique(np.concatenate([np.arange(s, s + length) for s in starts]))


def _write_folder(out: Path, references: list[Path], queries: list[tuple[Path, list[int]]]) -> None:
    """A VPR-Bench folder: ``ref/`` and ``query/`` as symbolic links in the order given and the
    ground truth (each query's right reference indices; empty: off the map)."""
    (out / "ref").mkdir(parents=True)
    (out / "query").mkdir()
    width = len(str(max(len(references), len(queries))))
    for i, path in enumerate(references):
        (out / "ref" / f"{i:0{width}d}{path.suffix}").symlink_to(path.resolve())
    rows: list[list[object]] = []
    for i, (path, positives) in enumerate(queries):
        (out / "query" / f"{i:0{width}d}{path.suffix}").symlink_to(path.resolve())
        rows.append([i, np.array(sorted(positives), dtype=np.int64)])
    np.save(out / VPR_BENCH_GT, np.array(rows, dtype=object), allow_pickle=True)
    off = sum(not positives for _, positives in queries)
    print(f"{out}: {len(references)} references, {len(queries)} queries, {off} of them off the map")


def write(source: Path, out: Path, stretches: int, length: int, tolerance: int) -> None:
    """The gaps construction: the map lacks ``stretches`` runs inside the route."""
    dataset = read_traversals(source, tolerance=tolerance)
    frames = len(dataset.references)
    left_out = set(unmapped_stretches(frames, stretches, length).tolist())
    kept = [i for i in range(frames) if i not in left_out]
    new_index = {old: new for new, old in enumerate(kept)}
    _write_folder(
        out,
        [dataset.references[old].path for old in kept],
        [
            (query.path, [new_index[p] for p in query.positives if p in new_index])
            for query in dataset.queries
        ],
    )


def detour_route(frames: int, stretches: int, length: int) -> tuple[int, list[int]]:
    """The detours construction's order of query frames: the mapped route ``0..mapped-1`` with
    ``stretches`` detours of ``length`` consecutive frames of the unmapped tail
    (``mapped..frames-1``) spliced in at evenly spaced points; (mapped, that order)."""
    mapped = frames - stretches * length
    if mapped <= length:
        raise SystemExit(f"{frames} frames leave too little route for {stretches} x {length}")
    turns = np.linspace(0, mapped, stretches + 2).astype(int)[1:-1]
    order: list[int] = []
    start = 0
    for k, turn in enumerate(turns):
        order += list(range(start, turn))
        order += list(range(mapped + k * length, mapped + (k + 1) * length))
        start = turn
    return mapped, order + list(range(start, mapped))


def write_detours(source: Path, out: Path, stretches: int, length: int, tolerance: int) -> None:
    """The detours construction: the robot leaves the mapped route for unmapped frames."""
    dataset = read_traversals(source, tolerance=tolerance)
    mapped, order = detour_route(len(dataset.references), stretches, length)
    _write_folder(
        out,
        [dataset.references[i].path for i in range(mapped)],
        [
            (dataset.queries[i].path, [p for p in dataset.queries[i].positives if p < mapped])
            for i in order
        ],
    )
    (out / ROUTE_FILE).write_text(json.dumps({"mapped": mapped, "frames": order}))


def drive_places(mapped: int, frames: list[int]) -> list[str]:
    """Each query's place on a detours drive: ``off k`` (the k-th frame off the route, from 1),
    ``back k`` (the k-th frame back on it, up to :data:`TURN_FRAMES`) or ``route``."""
    places, since, off = [], TURN_FRAMES, False
    for frame in frames:
        now_off = frame >= mapped
        since = since + 1 if now_off == off else 1
        off = now_off
        if off:
            places.append(f"off {since}")
        else:
            places.append(f"back {since}" if since <= TURN_FRAMES else "route")
    return places


def read(report: Path, folder: Path) -> None:
    """Where the loops of each robot row (``observe``) of ``report`` fall on the detours drive
    in ``folder``: right and false loops off the route, just back on it, and along it (each
    false one with its frames' ``aligned_z``), and how much the newest frame's own evidence
    favours the sequence's place off the route and on it."""
    route = json.loads((folder / ROUTE_FILE).read_text())
    places = drive_places(route["mapped"], route["frames"])
    truth = np.load(folder / VPR_BENCH_GT, allow_pickle=True)
    positives = [set(np.atleast_1d(row[1]).tolist()) for row in truth]
    for row in json.loads(report.read_text())["methods"]:
        details = row.get("details") or {}
        if "-served" not in row["name"] or not details.get("per_query_sequence"):
            continue
        sequences = np.array(details["per_query_sequence"], float)
        if np.isnan(sequences[:, 0]).all():
            continue  # anonymous queries: no drive
        loop, frames = loop_frames(details)
        evidence = details.get("per_query_sequence_z") or [[] for _ in loop]
        counts: dict[str, list[int]] = {}
        false: list[str] = []
        for i in np.flatnonzero(loop):
            wrong = int(frames[i]) not in positives[i]
            counts.setdefault(places[i].split()[0], [0, 0])[int(wrong)] += 1
            if wrong:
                false.append(
                    f"query {i} ({places[i]}) -> reference {frames[i]}, sequence margin "
                    f"{sequences[i, 1]:.2f}, passed {bool(sequences[i, 3] == 1)}, "
                    f"aligned_z {[round(z, 1) for z in evidence[i]]}"
                )
        print(f"{row['name']}: {int(loop.sum())} loops of {len(loop)} queries")
        for group, (n_right, n_false) in sorted(counts.items()):
            print(f"  {group}: {n_right} right, {n_false} false")
        for line in false:
            print(f"  false: {line}")
        newest = np.array([z[-1] if z else np.nan for z in evidence])
        off = np.array([place.startswith("off") for place in places])
        for name, where in (("off the map", off), ("on the route", ~off)):
            values = newest[where & ~np.isnan(newest)]
            if len(values):
                print(
                    f"  newest frame's aligned_z {name}: median {np.median(values):.2f}, "
                    f"10 % below {np.quantile(values, 0.1):.2f}, "
                    f"{np.mean(values >= NEWEST_Z_MIN):.0%} at least {NEWEST_Z_MIN:g}"
                )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--read",
        type=Path,
        metavar="REPORT",
        help="read a loopnet eval report.json of the detours folder OUT instead of writing it",
    )
    parser.add_argument("source", type=Path, help="a frame-aligned traversals folder")
    parser.add_argument("out", type=Path, help="the VPR-Bench folder to write (must not exist)")
    parser.add_argument(
        "--detours",
        action="store_true",
        help="the robot leaves the mapped route for unmapped frames (default: gaps in the map)",
    )
    parser.add_argument("--stretches", type=int, default=10)
    parser.add_argument(
        "--length", type=int, default=40, help="frames per unmapped stretch or detour"
    )
    parser.add_argument("--tolerance", type=int, default=1)
    args = parser.parse_args()
    if args.read is not None:
        read(args.read, args.out)
        return
    build = write_detours if args.detours else write
    build(args.source, args.out, args.stretches, args.length, args.tolerance)


if __name__ == "__main__":
    main()

"""A drive that leaves the map: frame-aligned traversals rewritten as a VPR-Bench folder whose
map lacks some stretches, to measure what the sequence decision does when a robot drives where
no reference was taken.

    python benchmarks/off_route_dataset.py ../shared/data/nordland_64x32 /work/tmp/nord_off \\
        --stretches 10 --length 40
    loopnet eval /work/tmp/nord_off --layout vpr-bench --tolerance 1 --sequence 10 ...

The queries keep their route order; a query whose right references were all left out has no
positive, so any ``loop`` answered for it is false (the harness counts it so). The first
frames of each unmapped stretch are the hard ones: the robot's last frames still align along
the mapped route behind it. Images are symbolic links, so nothing is copied. Nothing here is a
service path.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from service.evaluation.dataset_layouts import VPR_BENCH_GT, read_traversals


def unmapped_stretches(frames: int, stretches: int, length: int) -> np.ndarray:
    """Frame indices left out of the map: ``stretches`` runs of ``length`` frames, evenly
    spread between the route's ends (never its first or last stretch)."""
    starts = np.linspace(0, frames - length, stretches + 2).astype(int)[1:-1]
    return np.unique(np.concatenate([np.arange(s, s + length) for s in starts]))


def write(source: Path, out: Path, stretches: int, length: int, tolerance: int) -> None:
    dataset = read_traversals(source, tolerance=tolerance)
    frames = len(dataset.references)
    left_out = set(unmapped_stretches(frames, stretches, length).tolist())
    kept = [i for i in range(frames) if i not in left_out]
    new_index = {old: new for new, old in enumerate(kept)}
    (out / "ref").mkdir(parents=True)
    (out / "query").mkdir()
    width = len(str(frames))
    for new, old in enumerate(kept):
        path = dataset.references[old].path
        (out / "ref" / f"{new:0{width}d}{path.suffix}").symlink_to(path.resolve())
    rows: list[list[object]] = []
    off = 0
    for i, query in enumerate(dataset.queries):
        (out / "query" / f"{i:0{width}d}{query.path.suffix}").symlink_to(query.path.resolve())
        positives = sorted(new_index[p] for p in query.positives if p in new_index)
        rows.append([i, np.array(positives, dtype=np.int64)])
        off += not positives
    np.save(out / VPR_BENCH_GT, np.array(rows, dtype=object), allow_pickle=True)
    print(f"{out}: {len(kept)} references, {len(rows)} queries, {off} of them off the map")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("source", type=Path, help="a frame-aligned traversals folder")
    parser.add_argument("out", type=Path, help="the VPR-Bench folder to write (must not exist)")
    parser.add_argument("--stretches", type=int, default=10)
    parser.add_argument("--length", type=int, default=40, help="frames per unmapped stretch")
    parser.add_argument("--tolerance", type=int, default=1)
    args = parser.parse_args()
    write(args.source, args.out, args.stretches, args.length, args.tolerance)


if __name__ == "__main__":
    main()

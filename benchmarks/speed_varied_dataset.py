"""A revisit at another speed than the map's: frame-aligned traversals rewritten as a VPR-Bench
folder in which the querying robot drives the mapped route at varying speed and stops, to
measure what the sequence decision does when the robot does not move at the map's pace
(issue 25, stop 48; the development sets are frame-aligned, every drive at the map's speed).

    python benchmarks/speed_varied_dataset.py ../shared/data/nordland_64x32 /work/tmp/nord_speeds
    loopnet eval /work/tmp/nord_speeds --layout vpr-bench --tolerance 1 --sequence 10 ...
    python benchmarks/stalled_track.py /work/runs/speeds/report.json

The route is cut into stretches of ``--length`` map frames, driven in turn by the ``--pattern``
(repeating): ``1`` every frame; ``0.5`` every frame twice (half the map's speed: a camera at a
fixed rate sees each place twice; at these image sizes no frame lies between two stored ones);
``2`` every second frame; ``stop`` every frame, then the last one ``--stop`` times more (the
robot stands still). Each query keeps its frame's right references. Images are symbolic links,
so nothing is copied. Nothing here is a service path.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from off_route_dataset import _write_folder  # a sibling script

from service.evaluation.dataset_layouts import read_traversals

ROUTE_FILE = "speeds.json"  # each query's source frame and the stretch's pace


def drive(frames: int, pattern: list[str], length: int, stop: int) -> list[tuple[int, str]]:
    """The query frames in driving order, each with the pace of its stretch."""
    order: list[tuple[int, str]] = []
    for k, start in enumerate(range(0, frames, length)):
        pace = pattern[k % len(pattern)]
        stretch = list(range(start, min(start + length, frames)))
        if pace == "0.5":
            stretch = [i for i in stretch for _ in range(2)]
        elif pace == "2":
            stretch = stretch[::2]
        elif pace == "stop":
            stretch = stretch + [stretch[-1]] * stop
        elif pace != "1":
            raise SystemExit(f"unknown pace {pace!r}: use 1, 0.5, 2 or stop")
        order += [(i, pace) for i in stretch]
    return order


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("source", type=Path, help="frame-aligned traversals (map, queries)")
    parser.add_argument("out", type=Path)
    parser.add_argument("--pattern", default="1,0.5,1,2,1,stop")
    parser.add_argument("--length", type=int, default=40, help="map frames per stretch")
    parser.add_argument("--stop", type=int, default=10, help="frames a stop lasts")
    parser.add_argument("--tolerance", type=int, default=1)
    args = parser.parse_args()
    dataset = read_traversals(args.source, tolerance=args.tolerance)
    order = drive(len(dataset.references), args.pattern.split(","), args.length, args.stop)
    _write_folder(
        args.out,
        [reference.path for reference in dataset.references],
        [(dataset.queries[i].path, list(dataset.queries[i].positives)) for i, _ in order],
    )
    (args.out / ROUTE_FILE).write_text(
        json.dumps({"frames": [i for i, _ in order], "pace": [p for _, p in order]})
    )


if __name__ == "__main__":
    main()

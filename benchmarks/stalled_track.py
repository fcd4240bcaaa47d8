"""Loops whose sequence place stalled while the robot drove on: an offline screen of
``loopnet eval`` reports (issue 25, stop 48).

On nordland_64x32 driven the other way round (winter as the map, summer as the queries:
``--reference winter --query summer``) the service closes 2 false loops at the defaults,
queries 769 and 770, both 4 frames behind the right place. The robot's sequence place stayed
at map frame 765 for queries 766-769 and reached 766 at query 770: the track stalled while the
robot moved, and its margin over the right place (4 frames on, a rival) stayed above the
minimum. The service allows a place to lag behind a robot's recent loops (a robot may slow
down or stop); this measures what a guard "the place advanced at least ``--speeds`` map frames
per frame over the last ``--frames`` frames" would refuse among the loops of each report's
robot row, right and false, before anyone builds it.

    python benchmarks/stalled_track.py REPORT [REPORT ...] --frames 3,4,5 --speeds 0.25,0.5

The place of a query is its sequence's aligned map frame whether or not the sequence passed
(``per_query_sequence``); map frames are compared by index, so references must lie in route
order (one trajectory). A robot standing still also stalls its place: a service guard would
have to exempt stays (:mod:`service.ml.stays`), which offline reports cannot tell. Nothing here
is a service path.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np
from served_report import loop_frames, robot_row  # a sibling script


def stalled(details: dict[str, Any], frames: int, speed: float) -> np.ndarray:
    """The queries answered ``loop`` whose sequence place advanced by at least 0 and less than
    ``speed`` map frames per frame since ``frames`` queries before."""
    loop, _ = loop_frames(details)
    place = np.array(details["per_query_sequence"], float)[:, 0]
    found = []
    for i in np.flatnonzero(loop):
        j = i - frames
        if j < 0 or np.isnan(place[i]) or np.isnan(place[j]):
            continue
        if 0.0 <= (place[i] - place[j]) / frames < speed:
            found.append(i)
    return np.array(found, np.int64)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("reports", nargs="+", type=Path)
    parser.add_argument("--frames", default="3,4,5")
    parser.add_argument("--speeds", default="0.25,0.5")
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    record: dict[str, list[dict[str, Any]]] = {}
    for path in args.reports:
        row = robot_row(json.loads(path.read_text()))
        details = row["details"]
        loop, _ = loop_frames(details)
        right = np.array(details["per_query_right"], bool)
        print(f"== {path} ({row['name']}): {loop.sum()} loops, {(loop & ~right).sum()} false")
        record[str(path)] = []
        for frames in (int(v) for v in args.frames.split(",")):
            for speed in (float(v) for v in args.speeds.split(",")):
                refused = stalled(details, frames, speed)
                false = [int(q) for q in refused if not right[q]]
                print(
                    f"  advanced < {speed:g} frames a frame over {frames}: refuses "
                    f"{len(refused) - len(false)} right, {len(false)} false {false[:10]}"
                )
                record[str(path)].append(
                    {
                        "frames": frames,
                        "speed": speed,
                        "right_refused": len(refused) - len(false),
                        "false_refused": false,
                    }
                )
    if args.out:
        args.out.write_text(json.dumps(record, indent=1) + "\n")


if __name__ == "__main__":
    main()

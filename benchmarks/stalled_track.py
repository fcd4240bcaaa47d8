"""Loops whose sequence place stalled while the robot drove on: an offline screen of
``loopnet eval`` reports (issue 25, stop 48).

On nordland_64x32 driven the other way round (winter as the map, summer as the queries:
``--reference winter --query summer``) the service closes 2 false loops at the defaults,
queries 769 and 770, both 4 frames behind the right place. The robot's sequence place stayed
at map frame 765 for queries 766-769 and reached 766 at query 770: the track stalled while the
robot moved, and its margin over its best rival place (rivals lie more than 3 frames away,
the right place among them) stayed above the minimum. The service allows a place to lag behind a robot's recent loops (a robot may slow
down or stop); this measures what a guard "the place advanced at least ``--speeds`` map frames
per frame over the last ``--frames`` frames" would refuse among the loops of each report's
robot row, right and false, before anyone builds it.

    python benchmarks/stalled_track.py REPORT [REPORT ...] --frames 3,4,5 --speeds 0.25,0.5 \
        --slacks 1,2

A second guard mirrors the service's run-ahead rule (:func:`service.app.sequence_rules.ran_ahead`:
no further past a recent loop than the sequence's fastest speed carries a robot, plus a slack):
refuse a loop that lies less far past one of the robot's loops of its last
:data:`TRACKING_DROPOUT` frames (answered or pending, as the service stores them) than the
sequence's *slowest* speed carries it, less ``--slacks``.

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
from served_report import loop_frames, robot_row, weak_passes  # a sibling script

from service.ml.sequences import SequenceSettings
from service.ml.sequences.distinctiveness import TRACKING_DROPOUT


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


def fell_behind(details: dict[str, Any], slack: float) -> np.ndarray:
    """The queries answered ``loop`` whose frame lies less far past one of the robot's loops of
    its last :data:`TRACKING_DROPOUT` frames than the slowest speed carries it, less ``slack``
    (a loop pending when its sequence passed with the newest ``aligned_z`` below
    :data:`CONFIRM_Z`, held at its sequence's frame)."""
    loop, frames = loop_frames(details)
    places = np.nan_to_num(np.array(details["per_query_sequence"], float)[:, 0], nan=-1)
    held = np.where(loop, frames, np.where(weak_passes(details), places, -1))
    slowest = float(min(SequenceSettings().speeds))
    found = []
    for i in np.flatnonzero(loop):
        for since in range(1, min(TRACKING_DROPOUT, int(i)) + 1):
            j = i - since
            if held[j] >= 0 and frames[i] - held[j] < slowest * since - slack:
                found.append(i)
                break
    return np.array(found, np.int64)


def _tally(refused: np.ndarray, right: np.ndarray) -> dict[str, Any]:
    """How many right loops a guard refuses, and which false ones."""
    false = [int(q) for q in refused if not right[q]]
    return {"right_refused": len(refused) - len(false), "false_refused": false}


def _said(tally: dict[str, Any]) -> str:
    false = tally["false_refused"]
    return f"refuses {tally['right_refused']} right, {len(false)} false {false[:10]}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("reports", nargs="+", type=Path)
    parser.add_argument("--frames", default="3,4,5")
    parser.add_argument("--speeds", default="0.25,0.5")
    parser.add_argument("--slacks", default="1,2", help="the run-ahead mirror's slacks")
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
                tally = _tally(stalled(details, frames, speed), right)
                print(f"  advanced < {speed:g} frames a frame over {frames}: {_said(tally)}")
                record[str(path)].append({"frames": frames, "speed": speed, **tally})
        for slack in (float(v) for v in args.slacks.split(",")):
            tally = _tally(fell_behind(details, slack), right)
            print(
                f"  behind a recent loop by more than the slowest speed, slack {slack:g}: "
                f"{_said(tally)}"
            )
            record[str(path)].append({"slack": slack, **tally})
    if args.out:
        args.out.write_text(json.dumps(record, indent=1) + "\n")


if __name__ == "__main__":
    main()

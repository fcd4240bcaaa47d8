"""What leaving a weak sequence loop to the robot's next frame would cost and refuse, read
offline from ``loopnet eval`` reports made before the rule (stop 46).

    python benchmarks/next_frame_confirmation.py /work/runs/nord/report.json \\
        /work/runs/detours/report.json [--thresholds 1.5,2,2.5,3,3.5,4] [--out FILE.json]
    python benchmarks/next_frame_confirmation.py --anchored REPORTS   # stop 47's rule

The rule (:data:`service.ml.sequences.distinctiveness.CONFIRM_Z`): a loop closed while the
newest frame's own ``aligned_z`` is below the threshold is answered only once the next query's
answer is a loop of the same place (its loop frame within the consistency's step, 3 frames, of
the first). For each report's robot row (``-served+seq``) and threshold, per half of the queries
(route order: choose on the first, read the second as held out): the right loops lost and the
false loops kept of all false. Exact for a report made without the rule and without
adaptation (the rule changes no provisional decision, only when one is answered); with
adaptation, the pairs a job learns from change too, so a run of the service gives the final
figures. Rightness is the report's (any layout). Nothing here is a service path.

``--anchored`` reads reports made *with* stop 46's rule (a pending loop confirmed by the next
frame's loop, answered or pending) and gives what stop 47's rule costs and refuses: a pending
loop is confirmed only by a later loop answered at once, through an unbroken run of pending
loops of the same place. A loop counts as pending when its sequence passed with the newest
``aligned_z`` below :data:`CONFIRM_Z` (a consistent single-frame loop that also passed that way
was answered at once, which overstates the loss), and is confirmed only by a loop within the
robot's frames that the service reads back (:func:`reach`), as the service bounds the run
(:func:`service.app.sequences.pending_run`). Without that bound the screen kept 3 Nordland
loops that the service lost (queries 3518-3520, the oldest of a run of 13 pending loops; stop
48); with it, stop 46's Nordland report gives the served count exactly (2,482).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np
from served_report import (  # a sibling script (its folder is on the path)
    loop_frames,
    newest_z,
    robot_row,
    weak_passes,
)

from service.config_sections import SequenceSettings
from service.ml.sequences import ConsistencySettings

SAME_PLACE = ConsistencySettings().max_step  # how far apart two loops of one place may lie


def confirmed(details: dict[str, Any], threshold: float) -> tuple[np.ndarray, np.ndarray]:
    """Per query: whether it was a loop before the rule, and whether it still is with it (its
    newest frame reaches ``threshold``, or the next query's loop names the same place)."""
    loop, frames = loop_frames(details)
    newest = newest_z(details)
    following = np.append(loop[1:], False)
    after = np.append(frames[1:], -1)
    same_place = following & (np.abs(after - frames) <= SAME_PLACE)
    return loop, loop & ((newest >= threshold) | same_place)


def anchored(details: dict[str, Any], reach: int) -> tuple[np.ndarray, np.ndarray]:
    """Per query of a report made with stop 46's rule: whether it was a loop, and whether it
    still is when only a loop answered at once, at most ``reach`` frames later, confirms a
    pending one (walking back from the end: a confirmed pending loop's next loop was the same
    place, answered or pending)."""
    loop = np.array([s == "loop" for s in details["per_query_status"]])
    pending = weak_passes(details)
    kept = loop & ~pending
    anchor = np.full(len(loop), -1)  # the loop answered at once that confirms a pending one
    for i in range(len(loop) - 2, -1, -1):
        if loop[i] and pending[i]:
            anchor[i] = i + 1 if not pending[i + 1] else anchor[i + 1] if kept[i + 1] else -1
            kept[i] = 0 < anchor[i] - i <= reach
    return loop, kept


def reach(row: dict[str, Any]) -> int:
    """How many frames after a pending loop one answered at once may confirm it: the robot's
    previous frames the service reads back (:meth:`service.app.sequences.SequenceScorer`: the
    longest of L, from the row's name ``+seqL``, the consistency's k and the trajectory
    contrast's frames + 1, less the newest frame), at the default settings: 10 at L = 10."""
    length = int(row["name"].rsplit("+seq", 1)[1])
    contrast = SequenceSettings().trajectory_contrast_frames
    return max(length, ConsistencySettings().required, contrast + 1) - 1


def screen(row: dict[str, Any], threshold: float | None) -> list[dict[str, Any]]:
    """Per half of the queries: loops before, right loops lost, false loops before and kept
    (``threshold`` None: :func:`anchored`)."""
    details = row["details"]
    loop, kept = (
        confirmed(details, threshold) if threshold is not None else anchored(details, reach(row))
    )
    right = np.array(details["per_query_right"], bool)
    half = len(loop) // 2
    out = []
    for name, part in (("first half", slice(0, half)), ("second half", slice(half, None))):
        before, after, good = loop[part], kept[part], right[part]
        out.append(
            {
                "half": name,
                "loops": int(before.sum()),
                "right_lost": int((before & ~after & good).sum()),
                "false": int((before & ~good).sum()),
                "false_kept": int((after & ~good).sum()),
            }
        )
    return out


def label(threshold: float | None) -> str:
    return "anchored" if threshold is None else f"{threshold:g}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("reports", nargs="+", type=Path)
    parser.add_argument("--thresholds", default="1.5,2,2.5,3,3.5,4")
    parser.add_argument("--out", type=Path, help="write the figures as JSON")
    parser.add_argument(
        "--anchored", action="store_true", help="stop 47's rule, on reports made with stop 46's"
    )
    args = parser.parse_args()
    thresholds = [None] if args.anchored else [float(t) for t in args.thresholds.split(",")]
    record: dict[str, dict[str, list[dict[str, Any]]]] = {}
    for path in args.reports:
        row = robot_row(json.loads(path.read_text()))
        record[str(path)] = {label(t): screen(row, t) for t in thresholds}
    print("threshold | " + " | ".join(str(p) for p in args.reports))
    print("  each half: right loops lost of loops, false kept of false")
    for t in thresholds:
        cells = []
        for path in args.reports:
            halves = record[str(path)][label(t)]
            cells.append(
                " / ".join(
                    f"-{h['right_lost']} of {h['loops']}, {h['false_kept']} of {h['false']}"
                    for h in halves
                )
            )
        print(f"{label(t)} | " + " | ".join(cells))
    if args.out:
        args.out.write_text(json.dumps(record, indent=1) + "\n")


if __name__ == "__main__":
    main()

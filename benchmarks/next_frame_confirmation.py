"""What leaving a weak sequence loop to the robot's next frame would cost and refuse, read
offline from ``loopnet eval`` reports made before the rule (stop 46).

    python benchmarks/next_frame_confirmation.py /work/runs/nord/report.json \\
        /work/runs/detours/report.json [--thresholds 1.5,2,2.5,3,3.5,4] [--out FILE.json]

The rule (:data:`service.ml.sequences.distinctiveness.CONFIRM_Z`): a loop closed while the
newest frame's own ``aligned_z`` is below the threshold is answered only once the next query's
answer is a loop of the same place (its loop frame within the consistency's step, 3 frames, of
the first). For each report's robot row (``-served+seq``) and threshold, per half of the queries
(route order: choose on the first, read the second as held out): the right loops lost and the
false loops kept of all false. Exact for a report made without the rule and without
adaptation (the rule changes no provisional decision, only when one is answered); with
adaptation, the pairs a job learns from change too, so a run of the service gives the final
figures. Rightness is the report's (any layout). Nothing here is a service path.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np
from served_report import loop_frames, robot_row  # a sibling script (its folder is on the path)

from service.ml.sequences import ConsistencySettings

SAME_PLACE = ConsistencySettings().max_step  # how far apart two loops of one place may lie


def confirmed(details: dict[str, Any], threshold: float) -> tuple[np.ndarray, np.ndarray]:
    """Per query: whether it was a loop before the rule, and whether it still is with it (its
    newest frame reaches ``threshold``, or the next query's loop names the same place)."""
    loop, frames = loop_frames(details)
    newest = np.array([z[-1] if z else -np.inf for z in details["per_query_sequence_z"]])
    following = np.append(loop[1:], False)
    after = np.append(frames[1:], -1)
    same_place = following & (np.abs(after - frames) <= SAME_PLACE)
    return loop, loop & ((newest >= threshold) | same_place)


def screen(details: dict[str, Any], threshold: float) -> list[dict[str, Any]]:
    """Per half of the queries: loops before, right loops lost, false loops before and kept."""
    loop, kept = confirmed(details, threshold)
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("reports", nargs="+", type=Path)
    parser.add_argument("--thresholds", default="1.5,2,2.5,3,3.5,4")
    parser.add_argument("--out", type=Path, help="write the figures as JSON")
    args = parser.parse_args()
    thresholds = [float(t) for t in args.thresholds.split(",")]
    record: dict[str, dict[str, list[dict[str, Any]]]] = {}
    for path in args.reports:
        details = robot_row(json.loads(path.read_text()))["details"]
        record[str(path)] = {f"{t:g}": screen(details, t) for t in thresholds}
    print("threshold | " + " | ".join(str(p) for p in args.reports))
    print("  each half: right loops lost of loops, false kept of false")
    for t in thresholds:
        cells = []
        for path in args.reports:
            halves = record[str(path)][f"{t:g}"]
            cells.append(
                " / ".join(
                    f"-{h['right_lost']} of {h['loops']}, {h['false_kept']} of {h['false']}"
                    for h in halves
                )
            )
        print(f"{t:g} | " + " | ".join(cells))
    if args.out:
        args.out.write_text(json.dumps(record, indent=1) + "\n")


if __name__ == "__main__":
    main()

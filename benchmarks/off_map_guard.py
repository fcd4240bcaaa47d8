"""What the off-the-map test would refuse, read offline from ``loopnet eval`` reports.

    python benchmarks/off_map_guard.py /work/runs/nord/report.json /work/runs/detours/report.json \\
        [--grid] [--out benchmarks/results/issue25/stop45_off_map.json]

For every loop a robot's served row closed by a passed sequence, whether
:func:`service.ml.sequences.off_map.left_the_map` (a CUSUM over the newest frames' ``aligned_z``)
would refuse it: right and false, as the report scored the answer (any layout), and the false
loops it keeps. ``--grid`` screens other constants (reference z, slack, frames) the same way:
that is how the service's were chosen. Offline: a refused loop would also stop the tracking
that follows it, which is not counted, so a run of the service gives the final figures. Reports
from stop 43 on carry ``per_query_sequence_z``; frames that aligned with nothing read as 0.

Nothing here is a service path: it is the record of what the rule buys before building it.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from served_report import robot_row, sequence_loops  # a sibling script

from service.ml.sequences import off_map

GRID = [
    (z, slack, frames)
    for z in (1.0, 1.5, 2.0)
    for slack in (0.5, 1.0, 1.5, 2.0)
    for frames in (3, 4)
]


def screen(details: dict[str, Any], z: float, slack: float, frames: int) -> dict[str, Any]:
    """Right and false loops the test with these constants refuses, and the false ones kept."""
    closed, right = sequence_loops(details)
    evidence = details["per_query_sequence_z"]
    refused = {
        int(i)
        for i in closed
        if off_map.left_the_map(evidence[i], reference_z=z, slack=slack, frames=frames) is not None
    }
    false = [int(i) for i in closed if not right[i]]
    return {
        "z": z,
        "slack": slack,
        "frames": frames,
        "loops": len(closed),
        "false": len(false),
        "refused_right": sum(1 for i in refused if right[i]),
        "refused_false": sum(1 for i in refused if not right[i]),
        "false_kept": [i for i in false if i not in refused],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("reports", nargs="+", type=Path)
    parser.add_argument("--grid", action="store_true", help="also screen other constants")
    parser.add_argument("--out", type=Path, help="write the figures as JSON")
    args = parser.parse_args()
    service_constants = (off_map.OFF_MAP_Z, off_map.OFF_MAP_SLACK, off_map.OFF_MAP_FRAMES)
    settings = [service_constants] + (
        [g for g in GRID if g != service_constants] if args.grid else []
    )
    record: dict[str, list[dict[str, Any]]] = {}
    for path in args.reports:
        details = robot_row(json.loads(path.read_text()))["details"]
        record[str(path)] = [screen(details, *s) for s in settings]
    print("z slack frames | " + " | ".join(str(p) for p in args.reports))
    print("  each: refused right, refused false of all false (false kept)")
    for n, s in enumerate(settings):
        cells = []
        for path in args.reports:
            r = record[str(path)][n]
            kept = f" {r['false_kept']}" if n == 0 else ""
            cells.append(f"{r['refused_right']}, {r['refused_false']} of {r['false']}{kept}")
        label = " (the service's)" if n == 0 else ""
        print(f"{s[0]} {s[1]} {s[2]}{label} | " + " | ".join(cells))
    if args.out:
        args.out.write_text(json.dumps(record, indent=1) + "\n")


if __name__ == "__main__":
    main()

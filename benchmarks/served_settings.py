"""How a decision setting was chosen: the served rows of ``loopnet eval`` runs that differ in
one setting, compared per half of the queries (route order). Choose on the FIRST half of a
development set and read the second half as held out.

    LOOPNET_RIVAL_GAP_FRAMES=5 loopnet eval ../shared/data/gardenspoint_cohog200 \\
        --tolerance 2 --long-side 256 --extractors disk ... --out RUN5
    python benchmarks/served_settings.py gap2=RUN2/report.json gap5=RUN5/report.json \\
        --out benchmarks/results/issue25/rival_gap.json

Every served row of each report (anonymous ``POST /query`` and, with ``--sequence``, the
robot's ``observe``) gives per half: R@1 of the served top-1, R@100%P of the sweep over the
decision's probability (recomputed unrounded from the parts the service reported, as the
harness sweeps it), the loops answered at the defaults and how many were false. Unlike an
offline re-decision, every figure here is what the service answered with that setting: the
frames it verified, its re-rank and its decision. Nothing here is a service path.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from service.evaluation.metrics import precision_recall
from service.ml.decision import probability


def swept(parts: list[float], names: list[str]) -> float:
    """The decision's probability from its reported parts (NaN: absent); 0 without any."""
    present = {n: v for n, v in zip(names, parts, strict=True) if not math.isnan(v)}
    return probability(present) if present else 0.0


def half_figures(row: dict[str, Any], sl: slice) -> dict[str, float | int]:
    details = row["details"]
    right = np.array(details["per_query_right"], bool)[sl]
    names = list(details["parts"])
    p = np.array([swept(parts, names) for parts in details["per_query_parts"]])[sl]
    loops = np.array([s == "loop" for s in details["per_query_status"]])[sl]
    curve = precision_recall(p, right, len(right))
    return {
        "queries": int(len(right)),
        "r_at_1": round(float(right.mean()), 3),
        "r_at_100p": round(curve.recall_at_full_precision, 3),
        "loops": int(loops.sum()),
        "false_loops": int((loops & ~right).sum()),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", help="LABEL=path/to/report.json, one per setting")
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    result: dict[str, Any] = {}
    for run in args.runs:
        label, _, path = run.partition("=")
        if not path:
            raise SystemExit(f"{run!r}: give LABEL=path/to/report.json")
        report = json.loads(Path(path).read_text())
        rows = [m for m in report["methods"] if m["kind"] == "served"]
        if not rows:
            raise SystemExit(f"{path}: no served row (run loopnet eval without --no-served)")
        result[label] = {}
        for row in rows:
            half = len(row["details"]["per_query_right"]) // 2
            result[label][row["name"]] = {
                which: half_figures(row, sl)
                for which, sl in (
                    ("first half", slice(0, half)),
                    ("second half", slice(half, None)),
                    ("all", slice(None)),
                )
            }
            figures = result[label][row["name"]]
            print(
                label,
                row["name"],
                *(
                    f"{which}: R@1 {f['r_at_1']:.3f} R@100%P {f['r_at_100p']:.3f} "
                    f"loops {f['loops']} ({f['false_loops']} false)"
                    for which, f in figures.items()
                ),
                sep=" | ",
            )
    if args.out:
        args.out.write_text(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()

"""How the trajectory-contrast window was chosen: the served observe row (``+seqL``) of
``loopnet eval`` reports run with different ``LOOPNET_TRAJECTORY_CONTRAST_FRAMES``, split into
the FIRST and SECOND half of the queries (route order).

    LOOPNET_TRAJECTORY_CONTRAST_FRAMES=5 loopnet eval ... --sequence 10 --out OUT5
    python benchmarks/contrast_halves.py 0=OUT0/report.json 5=OUT5/report.json 10=...

Printed per report: R@1 and R@100%P (over the decision's logit) of each half, and the false
loops at the service's defaults. The window is chosen on the first halves; the second halves
say whether the choice holds. Nothing here is a service path: it is the record of a choice.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from service.ml.decision import logit


def observe_row(report: dict[str, Any]) -> dict[str, Any]:
    rows = [m for m in report["methods"] if "-served+seq" in m["name"]]
    if not rows:
        raise SystemExit("no served observe row in the report (run loopnet eval --sequence L)")
    return rows[0]


def logits(details: dict[str, Any]) -> np.ndarray:
    """Each answer's decision logit from its recorded parts (-inf without a decision)."""
    names = details["parts"]
    out = []
    for row in details["per_query_parts"]:
        present = {n: float(v) for n, v in zip(names, row, strict=True) if not math.isnan(v)}
        out.append(logit(present) if present else -np.inf)
    return np.array(out)


def recall_at_full_precision(scores: np.ndarray, right: np.ndarray) -> float:
    """Right answers above the best-scored wrong one, over all queries."""
    order = np.argsort(-scores, kind="stable")
    ranked = right[order]
    first_wrong = int(np.argmax(~ranked)) if (~ranked).any() else len(ranked)
    return float(ranked[:first_wrong].sum() / max(len(ranked), 1))


def halves(details: dict[str, Any]) -> dict[str, Any]:
    right = np.asarray(details["per_query_right"], bool)
    scores = logits(details)
    status = np.asarray(details["per_query_status"])
    middle = len(right) // 2
    out: dict[str, Any] = {}
    for name, part in (("first", slice(0, middle)), ("second", slice(middle, len(right)))):
        out[name] = {
            "recall@1": round(float(right[part].mean()), 3),
            "R@100%P": round(recall_at_full_precision(scores[part], right[part]), 3),
            "false_loops": int(np.sum((status[part] == "loop") & ~right[part])),
        }
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("reports", nargs="+", help="WINDOW=report.json")
    parser.add_argument("--out", type=Path, help="also write the figures as JSON")
    args = parser.parse_args()
    figures = {}
    for item in args.reports:
        window, _, path = item.partition("=")
        row = observe_row(json.loads(Path(path).read_text()))
        figures[window] = {"row": row["name"], **halves(row["details"])}
        first, second = figures[window]["first"], figures[window]["second"]
        print(
            f"window {window:>3}  first half R@1 {first['recall@1']:.3f} R@100%P "
            f"{first['R@100%P']:.3f} false loops {first['false_loops']}  |  second half R@1 "
            f"{second['recall@1']:.3f} R@100%P {second['R@100%P']:.3f} false loops "
            f"{second['false_loops']}"
        )
    if args.out:
        args.out.write_text(json.dumps(figures, indent=1))


if __name__ == "__main__":
    main()

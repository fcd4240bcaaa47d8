"""Choose the minimum-inliers default of each matcher on a development split of a harness run.

Reads the per-query data that ``loopnet eval --verify ...`` writes into report.json (the
re-ranked best match's inliers, similarity and whether it is right), takes the queries of
``--dev`` as the development split, picks the smallest inlier count that accepts no wrong
match there (recall at 100% precision), and reports precision and recall at that count on the
held-out queries. Nothing is tuned on the held-out part.

    python benchmarks/choose_verification_thresholds.py \\
        benchmarks/results/gardenspoint_cohog200/verification/report.json --dev 0:100
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def choose(inliers: np.ndarray, correct: np.ndarray) -> int:
    """Smallest threshold with no false positive among accepted queries (max recall)."""
    wrong = inliers[~correct]
    return int(wrong.max()) + 1 if len(wrong) else 1


def at(threshold: int, inliers: np.ndarray, correct: np.ndarray, answerable: int) -> str:
    accepted = inliers >= threshold
    tp = int((accepted & correct).sum())
    precision = tp / accepted.sum() if accepted.any() else float("nan")
    return f"precision {precision:.3f}, recall {tp / max(answerable, 1):.3f} ({accepted.sum()} accepted)"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("report", type=Path)
    parser.add_argument("--dev", default="0:100", help="query index range start:stop")
    args = parser.parse_args()
    report = json.loads(args.report.read_text())
    start, stop = (int(v) for v in args.dev.split(":"))
    for method in report["methods"]:
        data = method["details"].get("per_query")
        if not data:
            continue
        inliers = np.array(data["best_inliers"])
        correct = np.array(data["best_correct"], bool)
        dev = np.zeros(len(inliers), bool)
        dev[start:stop] = True
        threshold = choose(inliers[dev], correct[dev])
        print(f"{method['label']}")
        print(f"  chosen on queries {start}:{stop}: min_inliers = {threshold}")
        print(f"  dev:      {at(threshold, inliers[dev], correct[dev], int(dev.sum()))}")
        held = ~dev
        print(f"  held-out: {at(threshold, inliers[held], correct[held], int(held.sum()))}")


if __name__ == "__main__":
    main()

"""How the re-rank's zoom tolerance was chosen: the served answers of a ``loopnet eval`` run made
with the zoom off (``LOOPNET_VERIFY_SCALE_TOLERANCE=0``) re-ranked offline for each tolerance,
their decision recomputed as the service computes it, figures per half of the queries (route
order). Choose on the FIRST half of a development set, read the second half as held out.

    LOOPNET_VERIFY_SCALE_TOLERANCE=0 loopnet eval ../shared/data/gardenspoint_cohog200 \\
        --tolerance 2 --long-side 256 --extractors disk ... --out RUN
    python benchmarks/scale_tolerance.py RUN/report.json ../shared/data/gardenspoint_cohog200 \\
        --tolerance 2 --tolerances 0,1,0.7,0.5,0.35,0.25

Anonymous queries only (the report's ``loopnet-<extractor>-served`` row): the decision's parts
are the inliers, the inlier ratio, the rival (references are one robot's frames in route
order, so a rival is a reference more than ``--rival-gap`` away: 2, the service's when the
tolerance was chosen, so the result files reproduce) and the calibrated score. The
re-rank, the evidence and the decision are the service's own functions (``rerank``,
``answer_evidence``, ``decide_loop``). Only the candidates the
service verified are re-ordered; a query whose top 5 held no right frame stays wrong.
Nothing here is a service path: it is the record of a choice.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
from served_halves import served_row  # beside this script: the same report's served row

from service.app.decision import answer_evidence
from service.app.results import Candidate
from service.evaluation.datasets import load_dataset
from service.evaluation.metrics import precision_recall
from service.ml.decision import decide_loop, probability
from service.ml.verification import rerank

REFERENCE, SIMILARITY, SCORE, INLIERS, RATIO, ZOOM = range(6)
MAP = "map"  # the one robot and submap every reference belongs to


def number(value: float) -> float | None:
    return None if math.isnan(value) else value


def answer(
    rows: list[list[float]], tolerance: float, frames: int, min_inliers: int, rival_gap: int
) -> tuple[int, float, bool]:
    """The re-ranked best reference (-1: none), its loop probability (0: none) and whether
    the decision calls it a loop. The candidates are one robot's frames in route order (a
    frame's id is its reference index), so the service's rival rule applies as it is."""
    if not rows:
        return -1, 0.0, False
    candidates = [
        Candidate(
            int(r[REFERENCE]),
            MAP,
            MAP,
            r[SIMILARITY],
            None if math.isnan(r[INLIERS]) else int(r[INLIERS]),
            number(r[SCORE]),
            number(r[RATIO]),
            scale=number(r[ZOOM]),
        )
        for r in rows
    ]
    order = rerank(
        [c.similarity for c in candidates],
        [c.inliers for c in candidates],
        [c.scale for c in candidates],
        scale_tolerance=tolerance,
    )
    ordered = [candidates[i] for i in order]
    evidence = answer_evidence(ordered, frames, None, tolerance, rival_gap)
    decision = decide_loop(evidence, min_inliers=min_inliers)
    best = ordered[0].frame_id
    if decision.loop_probability is None:
        return best, 0.0, False
    # unrounded, over every answer (served_sweep.swept_probability with closable_only=False)
    return best, probability(decision.parts), decision.passed


def figures(
    best: np.ndarray, probability: np.ndarray, loops: np.ndarray, positives: list[frozenset[int]]
) -> dict[str, float]:
    right = np.array([int(b) in p for b, p in zip(best, positives, strict=True)])
    answerable = sum(1 for p in positives if p)
    curve = precision_recall(probability, right, answerable)
    return {
        "r_at_1": round(float(right.sum() / max(answerable, 1)), 3),
        "r_at_100p": round(curve.recall_at_full_precision, 3),
        "loops": int(loops.sum()),
        "false_loops": int((loops & ~right).sum()),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("report", type=Path)
    parser.add_argument("dataset", type=Path)
    parser.add_argument("--tolerance", type=int, default=1, help="the run's frame tolerance")
    parser.add_argument("--tolerances", default="0,1,0.7,0.5,0.35,0.25")
    parser.add_argument("--rival-gap", type=int, default=2, help="frames; 2 as at the choice")
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    row = served_row(json.loads(args.report.read_text()))
    candidates = row["details"]["per_query_candidates"]
    if candidates and candidates[0] and len(candidates[0][0]) <= ZOOM:
        raise SystemExit("the report's candidates have no zoom column: re-run loopnet eval")
    min_inliers = int(row["details"]["verification"]["min_inliers"])
    dataset = load_dataset(args.dataset, tolerance=args.tolerance)
    positives = [q.positives for q in dataset.queries]
    frames = len(dataset.references)
    half = len(positives) // 2
    result: dict[str, Any] = {}
    for tolerance in (float(t) for t in args.tolerances.split(",")):
        answers = [
            answer(rows, tolerance, frames, min_inliers, args.rival_gap) for rows in candidates
        ]
        best = np.array([a[0] for a in answers])
        probability = np.array([a[1] for a in answers])
        loops = np.array([a[2] for a in answers], bool)
        result[str(tolerance)] = {
            which: figures(best[sl], probability[sl], loops[sl], positives[sl])
            for which, sl in (("first half", slice(0, half)), ("second half", slice(half, None)))
        }
        print(tolerance, json.dumps(result[str(tolerance)]))
    if args.out:
        args.out.write_text(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()

"""Would a place's geometric support lift a verification-bound served row? An offline screen
of ``loopnet eval`` reports (issue 25, stop 48).

The anonymous served row of gardenspoint_cohog200 is bound by verification: with MNN only
0.685 of its queries are right with a match verified above the atlas's fitted minimum. A true
revisit often verifies weakly against *several* neighbouring atlas frames (the two sides of the
path at 99x56 px: 8-20 inliers each), where a look-alike elsewhere verifies against none (the impostors'
median is 0 inliers). The covisibility check of keyframe SLAM reads that: here, a match is
closable when the inliers of every verified candidate of the best's place (frames within
``--gap`` of it along the route) add up to ``--minimums``, and the probability reads their sum
where it beats the best's own inliers. Near misses (the right place, a frame 3-5 off) gain as
much, which is what this measures.

    python benchmarks/place_support.py RUN/report.json --minimums 30,40

Per served anonymous row and minimum (the atlas's fitted one first): the closable ceiling
(right and closable / queries), the closable wrong answers, and R@100%P of the sweep over the
probability of the closable answers, as the harness sweeps it. The best match stays the
service's (its rightness is the report's); references must lie in route order (one
trajectory), so that frames within the gap are one place. Nothing here is a service path.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
from served_report import served_rows  # a sibling script

from service.evaluation.metrics import precision_recall
from service.evaluation.served_pass import PARTS
from service.ml.decision import DEFAULT_RIVAL_GAP, Evidence, decide_loop

PICKS = ("service", "similarity", "centre")


def place_decisions(
    details: dict[str, Any], minimum: int, gap: int, frames: int, pick: str = "service"
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per query: the probability of its best match read with its place's summed inliers (-1
    when not closable), whether it is closable at ``minimum``, and the frame answered: the
    service's best (``pick`` "service"), the place's most similar candidate ("similarity") or
    the place's inlier-weighted centre ("centre"); -1 without any candidate."""
    parts = np.array(details["per_query_parts"], float)
    probabilities = np.full(len(parts), -1.0)
    closable = np.zeros(len(parts), bool)
    answered = np.full(len(parts), -1, np.int64)
    for q, candidates in enumerate(details["per_query_candidates"]):
        if candidates:
            answered[q] = int(candidates[0][0])  # the service's best, unless a pick moves it
        verified = [(int(c[0]), float(c[1]), int(c[3])) for c in candidates if not math.isnan(c[3])]
        if not verified:
            continue
        best, _, own = verified[0]
        if int(candidates[0][0]) != best:
            continue  # the best was not verified: nothing to sum
        place = [v for v in verified if abs(v[0] - best) <= gap]
        support = sum(n for _, _, n in place)
        answered[q] = _picked(place, best, support, pick)
        row = dict(zip(PARTS, parts[q], strict=False))
        rival = None
        # the part is log((1 + own) / (1 + rival's)), clipped as served: a rival far below the
        # match reads as the clip's, which the probability clips again
        if not math.isnan(row["rival"]):
            rival = math.expm1(math.log1p(own) - row["rival"])
        score = None if math.isnan(row["score"]) else float(row["score"])
        evidence = Evidence(
            inliers=max(own, support),
            inlier_ratio=float(row["inlier_ratio"]),
            rival_inliers=rival,
            score_excess=score,
            frames=frames,
        )
        decision = decide_loop(evidence, min_inliers=minimum)
        closable[q] = decision.closable
        if decision.closable:
            probabilities[q] = float(decision.loop_probability or 0.0)
    return probabilities, closable, answered


def _picked(place: list[tuple[int, float, int]], best: int, support: int, pick: str) -> int:
    if pick == "similarity":
        return max(place, key=lambda v: v[1])[0]
    if pick == "centre" and support:
        return round(sum(frame * n for frame, _, n in place) / support)
    return best


def recall_at_full_precision(probabilities: np.ndarray, right: np.ndarray) -> float:
    """R@100%P of the sweep over the closable answers (probability >= 0), as the harness sweeps
    a served row (:func:`service.evaluation.metrics.precision_recall`)."""
    closable = probabilities >= 0
    curve = precision_recall(probabilities[closable], right[closable], len(right))
    return curve.recall_at_full_precision


def screen(
    report: dict[str, Any], minimums: list[int], gap: int, pick: str = "service"
) -> list[dict[str, Any]]:
    out = []
    frames = int(report["dataset"].get("references", 0) or 0)
    for row in served_rows(report):
        if "+seq" in row["name"]:
            continue  # a robot's row is bound by its sequence, not by one frame's geometry
        details = row["details"]
        fitted = details["verification"]["fitted_min_inliers"]["min_inliers"]
        for minimum in [fitted, *minimums]:
            probabilities, closable, answered = place_decisions(details, minimum, gap, frames, pick)
            right = np.array(details["per_query_right"], bool)
            if pick != "service":  # frame-aligned ground truth: query i right on i +- tolerance
                tolerance = int(report["dataset"]["tolerance"])
                right = np.abs(answered - np.arange(len(answered))) <= tolerance
            wrong = np.flatnonzero(closable & ~right)
            out.append(
                {
                    "row": row["name"],
                    "pick": pick,
                    "minimum": minimum,
                    "fitted": minimum == fitted,
                    "recall_at_1": round(float(right.mean()), 3),
                    "ceiling": round(float((closable & right).mean()), 3),
                    "closable_wrong": [int(q) for q in wrong],
                    "recall_at_100_precision": round(
                        recall_at_full_precision(probabilities, right), 3
                    ),
                    "served_recall_at_100_precision": row["recall_at_100_precision"],
                }
            )
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("reports", nargs="+", type=Path)
    parser.add_argument("--minimums", default="30,40")
    parser.add_argument(
        "--gap", type=int, default=DEFAULT_RIVAL_GAP, help="frames of one place (the rival gap)"
    )
    parser.add_argument(
        "--pick",
        choices=PICKS,
        default="service",
        help="the frame answered: the service's best, or the place's most similar candidate or "
        "inlier-weighted centre (those need frame-aligned ground truth)",
    )
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    minimums = [int(v) for v in args.minimums.split(",") if v]
    results = {}
    for path in args.reports:
        lines = screen(json.loads(path.read_text()), minimums, args.gap, args.pick)
        results[str(path)] = lines
        print(f"== {path}")
        for line in lines:
            fitted = " (fitted)" if line["fitted"] else ""
            print(
                f"{line['row']} ({line['pick']}'s frame, R@1 {line['recall_at_1']}): place "
                f"inliers >= {line['minimum']}{fitted}: ceiling "
                f"{line['ceiling']}, R@100%P {line['recall_at_100_precision']} (served "
                f"{line['served_recall_at_100_precision']}), closable wrong "
                f"{line['closable_wrong']}"
            )
    if args.out:
        args.out.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()

"""How the loop decision's coefficients were chosen: a logistic model over the decision's
parts, fitted on the FIRST half of a development set's queries (route order) and reported on
the SECOND half, from the served rows of ``loopnet eval`` reports.

    python benchmarks/served_halves.py /work/cache/decision/cohog/report.json \\
        /work/cache/decision/nord/report.json --out benchmarks/results/served_halves.json

Each report's ``loopnet-<extractor>-served`` row holds, per query, the decision's parts as
the service computed them (``details.per_query_parts``) and whether the served top-1 is right.
The fit pools the first halves of every report given (labels: right top-1); absent parts are
filled with their centre (they add nothing, as in the service). Printed per report and half:
R@100%P of the service's current coefficients and of the refit, and the operating point of
the refit at the largest probability threshold that keeps zero false loops on the first half.
Nothing here is a service path: it is the record of a choice.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

from service.evaluation.metrics import precision_recall
from service.ml.decision import CENTRES, COEFFICIENTS, INTERCEPT

PARTS = ("inliers", "inlier_ratio", "rival", "score", "sequence")


def served_row(report: dict[str, Any]) -> dict[str, Any]:
    rows = [m for m in report["methods"] if m["name"].endswith("-served")]
    if not rows:
        raise SystemExit("no served row in the report (run loopnet eval without --no-served)")
    return rows[0]


def design(parts: np.ndarray, names: tuple[str, ...]) -> np.ndarray:
    """Centred parts (absent: 0) of the named columns."""
    columns = []
    for name in names:
        values = parts[:, PARTS.index(name)] - CENTRES[name]
        columns.append(np.where(np.isnan(values), 0.0, values))
    return np.stack(columns, axis=1)


def fit_logistic(x: np.ndarray, y: np.ndarray, l2: float = 1.0, steps: int = 50) -> np.ndarray:
    """Intercept + weights by Newton's method with a small ridge (no scikit-learn here)."""
    a = np.c_[np.ones(len(x)), x]
    w = np.zeros(a.shape[1])
    ridge = l2 * np.eye(a.shape[1])
    ridge[0, 0] = 0.0
    for _ in range(steps):
        p = 1.0 / (1.0 + np.exp(-np.clip(a @ w, -30, 30)))
        grad = a.T @ (p - y) + ridge @ w
        hess = (a * (p * (1 - p))[:, None]).T @ a + ridge
        w -= np.linalg.solve(hess, grad)
    return w


def current(x: np.ndarray, names: tuple[str, ...]) -> np.ndarray:
    w = np.array([COEFFICIENTS[n] for n in names])
    return 1.0 / (1.0 + np.exp(-(INTERCEPT + x @ w)))


def evaluate(p: np.ndarray, right: np.ndarray, threshold: float | None) -> dict[str, float]:
    curve = precision_recall(p, right.astype(bool), int(len(right)))
    out = {"r_at_100p": curve.recall_at_full_precision, "auc_pr": curve.auc}
    if threshold is not None:
        loops = p >= threshold
        out["precision"] = float((loops & right).sum() / max(loops.sum(), 1))
        out["recall"] = float((loops & right).sum() / len(right))
        out["false_loops"] = int((loops & ~right).sum())
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("reports", type=Path, nargs="+")
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    names = PARTS
    halves = []
    for path in args.reports:
        row = served_row(json.loads(path.read_text()))
        parts = np.array(row["details"]["per_query_parts"], np.float64)
        right = np.array(row["details"]["per_query_right"], bool)
        half = len(right) // 2
        halves.append((path, parts, right, half))
    x_fit = np.concatenate([design(p[:h], names) for _, p, _, h in halves])
    y_fit = np.concatenate([r[:h] for _, _, r, h in halves]).astype(np.float64)
    w = fit_logistic(x_fit, y_fit)
    refit = 1.0 / (1.0 + np.exp(-(np.c_[np.ones(len(x_fit)), x_fit] @ w)))
    wrong = refit[y_fit < 0.5]
    threshold = float(np.nextafter(wrong.max(), 1.0)) if len(wrong) else 0.5
    result: dict[str, Any] = {
        "fitted": {"intercept": float(w[0]), **dict(zip(names, map(float, w[1:]), strict=True))},
        "zero_false_loop_threshold_on_first_halves": threshold,
        "reports": {},
    }
    for path, parts, right, half in halves:
        x = design(parts, names)
        p_refit = 1.0 / (1.0 + np.exp(-(np.c_[np.ones(len(x)), x] @ w)))
        p_now = current(x, names)
        result["reports"][str(path)] = {
            which: {
                "current": evaluate(p_now[sl], right[sl], 0.98),
                "refit": evaluate(p_refit[sl], right[sl], threshold),
            }
            for which, sl in (("first half", slice(0, half)), ("second half", slice(half, None)))
        }
    print(json.dumps(result, indent=2))
    if args.out:
        args.out.write_text(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()

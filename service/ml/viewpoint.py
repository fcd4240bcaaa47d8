"""Where a candidate was taken relative to the query, from the inliers alone: their zoom.

Frames a few metres apart along one view share many inliers (the frame further back often
more: it sees more of the scene), so inliers alone pick a frame taken near the query, not the
one taken where it was. The inliers' spread tells them apart: the same spot shows them at the
same size, a frame further back smaller, one further ahead larger. Verification measures the
zoom of every candidate (:func:`viewpoint_scale`) and the re-rank weighs the inliers by it
(:func:`support`). Light on purpose (numpy only): the settings read its default.
"""

from __future__ import annotations

import math

import numpy as np

# How much the re-rank trusts the inliers' zoom (:func:`support`): chosen on the first half of
# gardenspoint_cohog200's queries (DISK at 256 px, MNN; benchmarks/scale_tolerance.py, figures
# in benchmarks/RESULTS.md), where 0.1-0.35 gave the best R@1 and R@100%P of the served
# decision (within one query); 0.35 is the plateau's gentlest end.
DEFAULT_SCALE_TOLERANCE = 0.35
# Fewest inliers whose spread says anything about the viewpoint (RANSAC's own minimum).
MIN_SCALE_POINTS = 8


def viewpoint_scale(
    query_points: np.ndarray, candidate_points: np.ndarray, query_unit: float, candidate_unit: float
) -> float | None:
    """How much larger the inliers appear in the candidate than in the query: the ratio of
    their spreads (root mean square distance from their centroid), each divided by its
    camera's unit (focal length or image long side: ``verification.view_units``). About 1 for
    two frames taken from one spot; below 1 when the candidate was taken further back along
    the view (the scene looks smaller), above 1 further ahead. None with fewer than 8 inliers
    (as for RANSAC, too few to mean anything)."""
    if len(query_points) < MIN_SCALE_POINTS:
        return None
    a = query_points.astype(np.float64) / query_unit
    b = candidate_points.astype(np.float64) / candidate_unit
    spread_a = float(((a - a.mean(axis=0)) ** 2).sum())
    spread_b = float(((b - b.mean(axis=0)) ** 2).sum())
    if spread_a <= 0.0 or spread_b <= 0.0:
        return None
    return math.sqrt(spread_b / spread_a)


def support(inliers: int | None, scale: float | None, tolerance: float) -> float:
    """A verified candidate's evidence of being the query's place: its inliers, discounted by
    e per ``tolerance`` of ``|ln scale|`` (ahead and behind alike) when ``tolerance`` > 0."""
    count = float(inliers or 0)
    if tolerance <= 0.0 or scale is None or scale <= 0.0:
        return count
    return count * math.exp(-abs(math.log(scale)) / tolerance)

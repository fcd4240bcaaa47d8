"""The inliers' zoom between a query and a candidate, and the re-rank that weighs it: of frames
a few metres apart along one view, the one taken where the query was comes first."""

from __future__ import annotations

import math

import numpy as np
import pytest

from service.ml.geometry import Intrinsics
from service.ml.verification import View, rerank, view_units
from service.ml.viewpoint import support, viewpoint_scale


def test_scale_of_a_hand_computed_zoom() -> None:
    """Four points at (+-1, +-1) around (10, 10) in a 100-px query; the candidate (200 px
    long side) shows them at (+-3, +-3) around (50, 40): spreads 2*sqrt(2)/100 and
    6*sqrt(2)/200, a zoom of 1.5."""
    square = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]] * 2, np.float64)
    query = square + [10.0, 10.0]
    candidate = 3.0 * square + [50.0, 40.0]
    assert viewpoint_scale(query, candidate, 100.0, 200.0) == pytest.approx(1.5)
    # a translation alone is no zoom
    assert viewpoint_scale(query, query + 7.0, 100.0, 100.0) == pytest.approx(1.0)


def test_scale_needs_eight_spread_inliers() -> None:
    points = np.random.default_rng(0).uniform(0, 50, (7, 2))
    assert viewpoint_scale(points, points, 64.0, 64.0) is None
    same = np.full((9, 2), 3.0)
    assert viewpoint_scale(same, same, 64.0, 64.0) is None


def test_units_are_focal_lengths_only_when_both_frames_have_them() -> None:
    local = None  # the units read only the sizes and the intrinsics
    plain = View(local, (640, 360))  # type: ignore[arg-type]
    calibrated = View(local, (960, 540), Intrinsics(500.0, 520.0, 480.0, 270.0))  # type: ignore[arg-type]
    assert view_units(calibrated, calibrated) == (510.0, 510.0)
    assert view_units(plain, calibrated) == (640.0, 960.0)  # never a focal length and a side
    assert view_units(calibrated, plain) == (960.0, 640.0)


def test_support_discounts_an_e_fold_per_tolerance() -> None:
    assert support(40, 1.0, 0.5) == 40.0
    assert support(40, math.exp(-0.5), 0.5) == pytest.approx(40 / math.e)
    assert support(40, math.exp(0.5), 0.5) == pytest.approx(40 / math.e)  # ahead as behind
    assert support(40, 0.5, 0.0) == 40.0  # off: inliers alone
    assert support(40, None, 0.5) == 40.0  # too few inliers to say
    assert support(None, 1.0, 0.5) == 0.0


def test_rerank_prefers_the_frame_taken_where_the_query_was() -> None:
    """The README flow's night 3 (gardenspoint_first10): day 0, three frames back, shares 47
    inliers at zoom 0.70; day 3 shares 35 at zoom 0.90. By inliers alone day 0 wins."""
    similarities = [0.91, 0.90, 0.89]
    inliers: list[int | None] = [47, 35, None]
    scales = [0.70, 0.90, None]
    assert rerank(similarities, inliers) == [0, 1, 2]
    assert rerank(similarities, inliers, scales, scale_tolerance=0.0) == [0, 1, 2]
    assert rerank(similarities, inliers, scales, scale_tolerance=0.5) == [1, 0, 2]

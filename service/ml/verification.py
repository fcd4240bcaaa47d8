"""Geometric verification of retrieval candidates: match local features, fit two-view geometry
with RANSAC, count inliers, re-rank, and decide.

One code path for the service (query and observe) and the evaluation harness: both hand a
:class:`View` of the query and of each candidate (keypoints in decoded-image pixels, as the
feature store keeps them) to :meth:`Verifier.verify`, then order and decide with
:func:`rerank` and :func:`decide`.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from service.ml.features import LocalFeatures
from service.ml.geometry import Intrinsics
from service.ml.matching import Matcher, Matches, build_matcher
from service.ml.two_view import (
    RansacConfig,
    TwoViewGeometry,
    camera_matrix,
    estimate_two_view_many,
    rotation_to_quaternion,
)
from service.ml.viewpoint import DEFAULT_SCALE_TOLERANCE, support, viewpoint_scale

# Minimum RANSAC inliers for a verified candidate, per matcher: LightGlue returns several times
# more (and more reliable) matches than MNN + ratio, so its bar is higher. Chosen for 100%
# precision on the development split, queries 0-99 of gardenspoint_cohog200 (DISK at 256 px,
# benchmarks/choose_verification_thresholds.py; the figures are in benchmarks/RESULTS.md).
DEFAULT_MIN_INLIERS = {"mnn": 44, "lightglue": 137}


def default_min_inliers(matcher: str) -> int:
    return DEFAULT_MIN_INLIERS[matcher]


@dataclass(frozen=True)
class VerificationConfig:
    """How candidates are verified.

    Attributes:
        matcher: "mnn" or "lightglue" (already resolved for the atlas's extractor).
        top: how many of the best retrieval candidates are verified (0: no verification).
        min_inliers: RANSAC inliers at or above which a candidate is verified.
        ratio: Lowe's ratio of the MNN matcher.
        ransac: RANSAC settings.
        scale_tolerance: how much the re-rank trusts the inliers' zoom (:func:`support`);
            0: candidates ordered by their inliers alone.
    """

    matcher: str = "mnn"
    top: int = 5
    min_inliers: int = 20
    ratio: float = 0.9
    ransac: RansacConfig = RansacConfig()
    scale_tolerance: float = DEFAULT_SCALE_TOLERANCE


@dataclass(frozen=True)
class View:
    """One frame as verification sees it."""

    local: LocalFeatures
    image_size: tuple[int, int]
    intrinsics: Intrinsics | None = None


@dataclass(frozen=True)
class RelativePose:
    """``X_candidate = R X_query + t``: rotation as a unit quaternion (w, x, y, z), translation as
    a unit direction (two views fix it only up to scale)."""

    rotation: tuple[float, float, float, float]
    translation: tuple[float, float, float]


@dataclass(frozen=True)
class Verification:
    """The outcome for one candidate.

    Attributes:
        matches: tentative matches given to RANSAC.
        inliers: RANSAC inliers (0 when there was no consensus).
        inlier_ratio: inliers / tentative matches (0 without matches).
        verified: inliers >= the configured minimum.
        model: "essential", "fundamental" or "none".
        relative_pose: with an essential matrix (both frames have intrinsics), else None.
        ms: milliseconds spent (matching + RANSAC).
        scale: the inliers' zoom from the query to the candidate (:func:`viewpoint_scale`);
            None with fewer than 8 inliers.
        inlier_pairs: ``inliers x 2`` int64 (index in the query's keypoints, index in the
            candidate's), only when :meth:`Verifier.verify` was asked to keep them.
    """

    matches: int
    inliers: int
    inlier_ratio: float
    verified: bool
    model: str
    relative_pose: RelativePose | None
    ms: float
    scale: float | None = None
    inlier_pairs: np.ndarray | None = field(default=None, repr=False, compare=False)


class Verifier:
    """Matches and RANSAC for query-candidate pairs under one :class:`VerificationConfig`."""

    def __init__(self, config: VerificationConfig, matcher: Matcher | None = None) -> None:
        self.config = config
        self.matcher = matcher or build_matcher(config.matcher, config.ratio)

    def verify(self, query: View, candidate: View, *, keep_inliers: bool = False) -> Verification:
        """Match, fit and count; ``keep_inliers`` also returns which matches were inliers
        (for drawing them), which the search path never asks for."""
        return self.verify_many(query, [candidate], keep_inliers=keep_inliers)[0]

    def verify_many(
        self, query: View, candidates: Sequence[View], *, keep_inliers: bool = False
    ) -> list[Verification]:
        """:meth:`verify` of each candidate, batched: MNN matches all of them from one matrix
        product and the batched RANSAC fits their fundamental matrices together. ``ms`` is
        each candidate's share of the whole."""
        start = time.perf_counter()
        found = self.matcher.match_many(
            query.local, query.image_size, [(c.local, c.image_size) for c in candidates]
        )
        k_query = _camera(query.intrinsics)
        geometries = estimate_two_view_many(
            [
                (
                    query.local.keypoints[matches.pairs[:, 0]],
                    c.local.keypoints[matches.pairs[:, 1]],
                    k_query,
                    _camera(c.intrinsics),
                )
                for matches, c in zip(found, candidates, strict=True)
            ],
            self.config.ransac,
        )
        ms = (time.perf_counter() - start) * 1000.0 / max(1, len(candidates))
        return [
            self._outcome(matches, geometry, ms, keep_inliers, query, c)
            for matches, geometry, c in zip(found, geometries, candidates, strict=True)
        ]

    def _outcome(
        self,
        matches: Matches,
        geometry: TwoViewGeometry,
        ms: float,
        keep_inliers: bool,
        query: View,
        candidate: View,
    ) -> Verification:
        pose = None
        if geometry.rotation is not None and geometry.translation is not None:
            tx, ty, tz = (float(v) for v in geometry.translation)
            pose = RelativePose(rotation_to_quaternion(geometry.rotation), (tx, ty, tz))
        inliers = geometry.inliers
        pairs = matches.pairs[geometry.inlier_mask]
        scale = viewpoint_scale(
            query.local.keypoints[pairs[:, 0]],
            candidate.local.keypoints[pairs[:, 1]],
            *view_units(query, candidate),
        )
        return Verification(
            matches=matches.count,
            inliers=inliers,
            inlier_ratio=inliers / matches.count if matches.count else 0.0,
            verified=inliers >= self.config.min_inliers,
            model=geometry.model,
            relative_pose=pose,
            ms=ms,
            scale=scale,
            inlier_pairs=pairs if keep_inliers else None,
        )


def _camera(intrinsics: Intrinsics | None) -> np.ndarray | None:
    if intrinsics is None:
        return None
    return camera_matrix(intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy)


def view_units(query: View, candidate: View) -> tuple[float, float]:
    """The lengths that make two frames' pixels comparable: their focal lengths when both have
    intrinsics, else their images' long sides (cameras of equal field of view; a focal length
    on one side only would mix the two)."""
    if query.intrinsics is not None and candidate.intrinsics is not None:
        return _focal(query.intrinsics), _focal(candidate.intrinsics)
    return float(max(query.image_size)), float(max(candidate.image_size))


def _focal(intrinsics: Intrinsics) -> float:
    return float(intrinsics.fx + intrinsics.fy) / 2.0


def rerank(
    similarities: Sequence[float],
    inliers: Sequence[int | None],
    scales: Sequence[float | None] | None = None,
    *,
    scale_tolerance: float = 0.0,
) -> list[int]:
    """The order of candidates after verification: verified-then-unverified by
    :func:`support` (most first, ties by similarity); candidates that were not verified
    (None) keep their retrieval order after every verified one."""
    zooms = list(scales) if scales is not None else [None] * len(inliers)
    checked = [i for i, n in enumerate(inliers) if n is not None]
    unchecked = [i for i, n in enumerate(inliers) if n is None]
    checked.sort(
        key=lambda i: (-support(inliers[i], zooms[i], scale_tolerance), -similarities[i], i)
    )
    return checked + unchecked


def decide(
    similarity: float | None,
    verification: Verification | None,
    *,
    threshold: float,
    verify: bool,
) -> bool:
    """Loop closure: the best similarity passes its threshold and, when verification is on,
    the best candidate passes verification too."""
    if similarity is None or similarity < threshold:
        return False
    if not verify:
        return True
    return verification is not None and verification.verified

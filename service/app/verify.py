"""Geometric verification of a query's best candidates against their stored keypoints."""

from __future__ import annotations

from dataclasses import replace

from service.app.results import Candidate
from service.concurrency import InferenceGate
from service.config import Settings
from service.ml.features import LocalFeatures
from service.ml.geometry import Intrinsics
from service.ml.matching import resolve_matcher_name
from service.ml.two_view import RansacConfig
from service.ml.verification import (
    Verification,
    VerificationConfig,
    Verifier,
    View,
    default_min_inliers,
    rerank,
)
from service.storage.models import Frame


def verification_config(settings: Settings, local_extractor: str) -> VerificationConfig:
    """The verification the settings ask for, with the extractor's default matcher."""
    matcher = resolve_matcher_name(settings.matcher, local_extractor)
    return VerificationConfig(
        matcher=matcher,
        top=settings.verify_top,
        min_inliers=settings.verify_min_inliers or default_min_inliers(matcher),
        ratio=settings.verify_ratio,
        ransac=RansacConfig(
            threshold_px=settings.ransac_threshold_px, backend=settings.ransac_backend
        ),
        scale_tolerance=settings.verify_scale_tolerance,
    )


class CandidateVerification:
    """Verifies candidates in one of the inference gate's slots (matching and RANSAC are
    inference work too: torch threads)."""

    def __init__(self, config: VerificationConfig, inference: InferenceGate) -> None:
        self.config = config
        self.inference = inference
        self._verifier: Verifier | None = None  # built on first use (LightGlue loads weights)

    @property
    def enabled(self) -> bool:
        return self.config.top > 0

    @property
    def verifier(self) -> Verifier:
        if self._verifier is None:
            self._verifier = Verifier(self.config)
        return self._verifier

    def verify(
        self, query: View, frames: list[Frame], stored: dict[int, LocalFeatures]
    ) -> dict[int, Verification]:
        """Verify the query against stored frames (``stored``: their keypoints by frame id;
        a frame missing there was deleted meanwhile and is skipped)."""
        verifier = self.verifier
        present = [frame for frame in frames if frame.id in stored]
        with self.inference.slot():
            found = verifier.verify_many(
                query, [frame_view(frame, stored[frame.id]) for frame in present]
            )
        return {frame.id: v for frame, v in zip(present, found, strict=True)}

    def check(
        self,
        query: View,
        checked: list[Candidate],
        frames: dict[int, Frame],
        stored: dict[int, LocalFeatures],
        min_inliers: int,
    ) -> dict[int, Verification]:
        """Verify ``checked`` (their frames and stored keypoints by frame id) against the
        query, a match verified from ``min_inliers`` on, and write what verification found into
        each candidate; the verifications by frame id."""
        verifications = {
            frame_id: replace(v, verified=v.inliers >= min_inliers)
            for frame_id, v in self.verify(
                query, [frames[c.frame_id] for c in checked], stored
            ).items()
        }
        for candidate in checked:
            verified = verifications.get(candidate.frame_id)
            if verified is not None:
                candidate.inliers = verified.inliers
                candidate.inlier_ratio = round(verified.inlier_ratio, 4)
                candidate.verified = verified.verified
                candidate.relative_pose = verified.relative_pose
                candidate.scale = round(verified.scale, 4) if verified.scale is not None else None
        return verifications

    def reranked(self, candidates: list[Candidate]) -> list[Candidate]:
        """``candidates`` in the order verification gives them (:func:`rerank`: verified ones
        first by their inliers, discounted by a zoom beyond the scale tolerance, ties by
        similarity; the others after, in retrieval order)."""
        order = rerank(
            [c.similarity for c in candidates],
            [c.inliers for c in candidates],
            [c.scale for c in candidates],
            scale_tolerance=self.config.scale_tolerance,
        )
        return [candidates[i] for i in order]

    def verify_pair(self, query: View, candidate: View) -> Verification:
        """One pair, keeping which matches were inliers (to draw them)."""
        verifier = self.verifier
        with self.inference.slot():
            return verifier.verify(query, candidate, keep_inliers=True)


def frame_view(frame: Frame, local: LocalFeatures) -> View:
    """A stored frame as verification sees it: its keypoints, decoded size and intrinsics."""
    intrinsics = (
        Intrinsics(frame.fx, frame.fy, frame.cx, frame.cy)  # type: ignore[arg-type]
        if frame.fx is not None
        else None
    )
    return View(local, (frame.width, frame.height), intrinsics)

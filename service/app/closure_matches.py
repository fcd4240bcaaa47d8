"""The verified matches of one loop closure, redrawn from both frames' stored keypoints.

Only an observation stores the image that closed the loop (as a frame); a query keeps nothing
but a thumbnail, so its matches cannot be recomputed. The matches are recomputed by the
service's verifier (its matcher and RANSAC settings), on the keypoints and half-precision
descriptors the feature store keeps, so their count may differ slightly from the inliers
recorded when the loop closed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from sqlalchemy.orm import Session, sessionmaker

from service.app.browse import closure_row
from service.app.ingest import FrameIngest
from service.app.verify import CandidateVerification, frame_view
from service.errors import NotFound
from service.ml.verification import RelativePose
from service.storage import repository as repo
from service.storage.feature_store import load_local_features
from service.storage.models import Frame


@dataclass(frozen=True)
class FrameSize:
    frame_id: int
    width: int
    height: int


@dataclass(frozen=True)
class ClosureMatches:
    """Inlier correspondences of a loop closure's query frame and matched frame.

    Attributes:
        pairs: ``[xq, yq, xm, ym]`` per inlier: the query frame's keypoint and the matched
            frame's, each in its frame's decoded-image pixels; at most the requested limit.
    """

    closure_id: int
    query_frame: FrameSize
    frame: FrameSize
    matcher: str
    matches: int
    inliers: int
    model: str
    relative_pose: RelativePose | None
    pairs: list[list[float]]


def closure_matches(
    sessions: sessionmaker[Session],
    ingest: FrameIngest,
    verification: CandidateVerification,
    atlas: str,
    closure_id: int,
    limit: int,
) -> ClosureMatches:
    """Re-verify a closure's two stored frames and return the inliers (NotFound when the
    closure came from a query, or its observed frame was deleted)."""
    with sessions() as session:
        found = ingest.checked_atlas(session, atlas)
        row = closure_row(session, found, closure_id)
        if row.query_frame_id is None:
            raise NotFound(_why_no_frame(found.name, closure_id, row.source))
        query_frame = repo.get_frame(session, atlas=found, frame_id=row.query_frame_id)
        frame = repo.get_frame(session, atlas=found, frame_id=row.frame_id)
        stored = load_local_features(session, [query_frame.id, frame.id])
    for needed in (query_frame, frame):
        if needed.id not in stored:
            raise NotFound(f"frame {needed.id} has no stored features")
    query_local, local = stored[query_frame.id], stored[frame.id]
    result = verification.verify_pair(
        frame_view(query_frame, query_local), frame_view(frame, local)
    )
    inlier_pairs = result.inlier_pairs
    assert inlier_pairs is not None
    inlier_pairs = inlier_pairs[:limit]
    points = np.concatenate(
        [query_local.keypoints[inlier_pairs[:, 0]], local.keypoints[inlier_pairs[:, 1]]], axis=1
    )
    return ClosureMatches(
        closure_id=closure_id,
        query_frame=_size(query_frame),
        frame=_size(frame),
        matcher=verification.config.matcher,
        matches=result.matches,
        inliers=result.inliers,
        model=result.model,
        relative_pose=result.relative_pose,
        pairs=np.round(points, 1).tolist(),
    )


def _why_no_frame(atlas: str, closure_id: int, source: str) -> str:
    if source == "query":
        return (
            f"loop closure {closure_id} came from a query, which stores no frame: matches are "
            f"only kept for observed frames (POST /v1/atlases/{atlas}/observe)"
        )
    return f"the observed frame of loop closure {closure_id} is no longer stored"


def _size(frame: Frame) -> FrameSize:
    return FrameSize(frame.id, frame.width, frame.height)

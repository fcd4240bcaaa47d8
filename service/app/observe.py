"""Observations (online SLAM): query with a robot's new keyframe, then insert it, in one call;
from an image or from already extracted features (a replay, an on-board extractor)."""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

from service.app.filters import QueryFilter
from service.app.ingest import FrameFields, FrameIngest
from service.app.results import QueryResult
from service.app.robot_evidence import RobotContext
from service.errors import InvalidInput
from service.ml.features import FrameFeatures
from service.ml.geometry import Intrinsics
from service.storage.models import Frame

if TYPE_CHECKING:
    from sqlalchemy.orm import Session, sessionmaker

    from service.storage.models import Atlas


class Observations:
    """The observe calls of :class:`~service.app.query.AtlasQueries` (which brings the
    search, the checks and the ingest)."""

    sessions: sessionmaker[Session]
    ingest: FrameIngest

    def check_k(self, k: int) -> None:
        raise NotImplementedError

    def robot_context(
        self, query_filter: QueryFilter, timestamp: float | None, sequence_length: int | None
    ) -> RobotContext | None:
        raise NotImplementedError

    def _check_targets(
        self, session: Session, atlas_name: str, query_filter: QueryFilter, submap: str | None
    ) -> Atlas:
        raise NotImplementedError

    def _search(
        self,
        atlas_name: str,
        features: FrameFeatures,
        k: int,
        query_filter: QueryFilter,
        intrinsics: Intrinsics | None,
        robot: RobotContext | None = None,
    ) -> QueryResult:
        raise NotImplementedError

    def observe(
        self,
        *,
        atlas_name: str,
        fields: FrameFields,
        image_bytes: bytes,
        query_filter: QueryFilter,
        k: int = 5,
        sequence_length: int | None = None,
    ) -> tuple[QueryResult, Frame]:
        """Online SLAM: query with a robot's new keyframe, then insert it, in one call.

        Everything is validated before the CNNs run; the query happens before the insert, so
        the new frame is never its own match; the insert is one transaction, so a failure
        writes nothing.
        """
        total_start = time.perf_counter()
        robot = self._check_observation(atlas_name, fields, k, query_filter, sequence_length)
        features, decode_ms, _ = self.ingest.extract(image_bytes)
        result, frame = self._observe(atlas_name, fields, features, query_filter, k, robot)
        return with_extraction_timings(result, features, decode_ms, total_start), frame

    def observe_features(
        self,
        *,
        atlas_name: str,
        fields: FrameFields,
        features: FrameFeatures,
        query_filter: QueryFilter,
        k: int = 5,
        sequence_length: int | None = None,
    ) -> tuple[QueryResult, Frame]:
        """:meth:`observe` with already extracted features (a replay, an on-board extractor)."""
        robot = self._check_observation(atlas_name, fields, k, query_filter, sequence_length)
        return self._observe(atlas_name, fields, features, query_filter, k, robot)

    def _check_observation(
        self,
        atlas_name: str,
        fields: FrameFields,
        k: int,
        query_filter: QueryFilter,
        sequence_length: int | None,
    ) -> RobotContext:
        """Everything an observation names, checked before any CNN runs."""
        fields.validate()
        self.check_k(k)
        if query_filter.robot_id != fields.robot_id:
            raise InvalidInput("an observation's filter must be for the observing robot")
        robot = self.robot_context(query_filter, fields.timestamp, sequence_length)
        with self.sessions() as session:
            self._check_targets(session, atlas_name, query_filter, fields.submap_name)
        assert robot is not None  # the filter names the observing robot
        return robot

    def _observe(
        self,
        atlas_name: str,
        fields: FrameFields,
        features: FrameFeatures,
        query_filter: QueryFilter,
        k: int,
        robot: RobotContext,
    ) -> tuple[QueryResult, Frame]:
        """Query, then insert in one transaction: the frame never matches itself, and a
        failure writes nothing."""
        result = self._search(atlas_name, features, k, query_filter, fields.intrinsics, robot)
        frame = self.ingest.store(
            atlas_name=atlas_name,
            fields=fields,
            features=features,
            proposals=result.proposals,
            loop_frame_id=result.proposed_loop_frame_id,  # answered or pending: either is tracked
            loop_pending=result.pending_loop_frame_id is not None,
        )
        return result, frame


def with_extraction_timings(
    result: QueryResult, features: FrameFeatures, decode_ms: float, total_start: float
) -> QueryResult:
    result.timings_ms = {
        "decode": round(decode_ms, 3),
        **{name: round(ms, 3) for name, ms in features.timings_ms.items()},
        **result.timings_ms,
        "total": round((time.perf_counter() - total_start) * 1000.0, 3),
    }
    result.query_thumbnail = features.thumbnail
    return result

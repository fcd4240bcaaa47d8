"""The application's facade over atlases: the catalog (atlases, submaps) and the entry points
the API, the CLI and the evaluation harness call for ingest and queries.

It owns the feature pipeline (CNNs), the database session factory, the inference gate and the
loaded state of every atlas; the work itself lives in :mod:`service.app.state`,
:mod:`service.app.ingest` and :mod:`service.app.query`.
"""

from __future__ import annotations

from typing import Any

from sqlalchemy.orm import Session, sessionmaker

from service.app import change_feed, reads
from service.app import model_versions as models_store
from service.app.browse import Browse
from service.app.closure_matches import ClosureMatches, closure_matches
from service.app.filters import QueryFilter, make_filter
from service.app.ingest import FrameFields, FrameIngest
from service.app.loop_closures import record_if_inter_robot
from service.app.names import validate_name
from service.app.pairs import RevisitPairs
from service.app.query import AtlasQueries
from service.app.reads import Reads
from service.app.results import QueryResult
from service.app.revisit_pairs import record_verified
from service.app.state import AtlasStates, LoadedAtlas
from service.app.verify import CandidateVerification, verification_config
from service.concurrency import InferenceGate, default_workers
from service.config import Settings
from service.index.pgvector_store import drop_atlas_tables
from service.index.store import PGVECTOR
from service.ml.features import FrameFeatures
from service.ml.geometry import Intrinsics
from service.ml.pipeline import FeaturePipeline
from service.storage import repository as repo
from service.storage.db import transaction
from service.storage.models import Atlas, Frame, ModelVersion, Submap


class AtlasService:
    """Atlases, submaps, frames and queries over one database and one data directory."""

    def __init__(
        self, settings: Settings, sessions: sessionmaker[Session], pipeline: FeaturePipeline
    ) -> None:
        self.settings = settings
        self.sessions = sessions
        self.pipeline = pipeline
        # Decode + CNNs behind a bounded gate: beyond its slots and queue, Overloaded (503).
        self.inference = InferenceGate(
            settings.inference_workers or default_workers(settings.torch_threads),
            settings.inference_queue,
            settings.inference_wait_seconds,
        )
        self.verification_config = verification_config(settings, pipeline.preset.local.name)
        self.states = AtlasStates(settings, sessions)
        self.frames = FrameIngest(settings, sessions, pipeline, self.states, self.inference)
        self.verification = CandidateVerification(self.verification_config, self.inference)
        self.queries = AtlasQueries(settings, sessions, self.states, self.frames, self.verification)
        self.reads = Reads(sessions)
        self.browse = Browse(sessions)
        self.pairs = RevisitPairs(sessions)
        # what the follower thread, the tests and the CLI reach through the facade
        self._loaded = self.states.loaded_states
        self.broken = self.states.broken
        self.loaded = self.states.loaded
        self.follow = self.states.follow
        self.flush = self.states.flush
        self.load_all = self.states.load_all
        self.save_index = self.states.save_index
        self.extract = self.frames.extract
        self.ingest_frame = self.frames.ingest_frame
        self.ingest_features = self.frames.ingest_features
        self.delete_frame = self.frames.delete_frame
        self.delete_submap = self.frames.delete_submap

    # ----- atlases -----------------------------------------------------------------------

    def catch_up(self) -> None:
        """Apply the change feed now, as each process's follower thread does every period
        (for the harness and tools that run without the thread)."""
        with self.sessions() as session:
            revisions = change_feed.revisions(session)
        self.follow(revisions)

    def create_atlas(self, name: str, description: str = "") -> Atlas:
        validate_name("atlas", name)
        heads_config = self.pipeline.heads_config()
        with transaction(self.sessions) as session:
            atlas = repo.create_atlas(
                session,
                name=name,
                description=description,
                feature_signature=self.pipeline.signature.to_json(),
            )
            repo.create_model_version(
                session,
                atlas_id=atlas.id,
                config=models_store.initial_version_config(heads_config),
                metrics={},
                weights_path=None,
                activate=True,
            )
        return atlas

    def create_submap(self, atlas_name: str, name: str) -> Submap:
        validate_name("submap", name)
        with transaction(self.sessions) as session:
            return repo.create_submap(
                session, atlas=repo.get_atlas(session, name=atlas_name), name=name
            )

    def delete_atlas(self, name: str) -> None:
        with transaction(self.sessions) as session:
            atlas = repo.get_atlas(session, name=name)
            atlas_id = atlas.id
            session.delete(atlas)
            if self.states.store_kind == PGVECTOR:  # its vector tables go in the same commit
                drop_atlas_tables(session, atlas_id)
        self.states.forget(atlas_id)
        models_store.remove_atlas_files(self.settings.index_dir, self.settings.models_dir, atlas_id)

    def unavailable_atlases(self) -> dict[str, str]:
        """Atlas name -> why it cannot be loaded (served with 503 while the others serve)."""
        return self.reads.unavailable_atlases(self.states.broken.reasons())

    def activate_version(self, atlas_name: str, version: int) -> ModelVersion:
        """Make a model version the active one; every process, this one included, swaps it in
        within LOOPNET_SYNC_SECONDS plus the time to load it (see :mod:`change_feed`)."""
        with transaction(self.sessions) as session:
            found = repo.get_atlas(session, name=atlas_name)
            return change_feed.activate_version(session, atlas_id=found.id, version=version)

    def served_indexes(self) -> list[reads.ServedIndex]:
        """What this process serves: each loaded atlas's index size and change-feed lag."""
        return self.reads.served_indexes(self.states.serving())

    def closure_matches(self, atlas_name: str, closure_id: int, limit: int) -> ClosureMatches:
        """A loop closure's verified matches, recomputed from both frames' stored keypoints."""
        return closure_matches(
            self.sessions, self.frames, self.verification, atlas_name, closure_id, limit
        )

    def rebuild_index(self, atlas_name: str) -> int:
        """Re-embed every frame of an atlas from stored features into a fresh index file."""
        with self.sessions() as session:
            atlas_id = repo.get_atlas(session, name=atlas_name).id
        return self.states.rebuild_index(atlas_id)

    # ----- queries -----------------------------------------------------------------------

    def query_filter(self, **fields: Any) -> QueryFilter:
        """A validated filter (see :func:`service.app.filters.make_filter`)."""
        return make_filter(self.settings, **fields)

    def query(
        self,
        *,
        atlas_name: str,
        image_bytes: bytes,
        k: int = 5,
        robot_id: str | None = None,
        query_filter: QueryFilter | None = None,
        intrinsics: Intrinsics | None = None,
        sequence_length: int | None = None,
    ) -> QueryResult:
        """The frames of the atlas most similar to an image, verified, and the loop-closure
        decision. ``robot_id`` is the robot asking (its recent frames never match; a loop onto
        another robot's frame is recorded)."""
        result = self.queries.query(
            atlas_name=atlas_name,
            image_bytes=image_bytes,
            k=k,
            query_filter=query_filter or self.query_filter(robot_id=robot_id),
            intrinsics=intrinsics,
            sequence_length=sequence_length,
        )
        record_if_inter_robot(self.sessions, robot_id=robot_id, result=result, source="query")
        return result

    def query_features(
        self,
        *,
        atlas_name: str,
        features: FrameFeatures,
        k: int = 5,
        robot_id: str | None = None,
        query_filter: QueryFilter | None = None,
        intrinsics: Intrinsics | None = None,
        sequence_length: int | None = None,
        timestamp: float | None = None,
    ) -> QueryResult:
        """Search with already extracted features (by :meth:`extract`) and verify (a loop
        onto another robot's frame is recorded, as by :meth:`query`)."""
        result = self.queries.query_features(
            atlas_name=atlas_name,
            features=features,
            k=k,
            query_filter=query_filter or self.query_filter(robot_id=robot_id, timestamp=timestamp),
            intrinsics=intrinsics,
            sequence_length=sequence_length,
            timestamp=timestamp,
        )
        record_if_inter_robot(self.sessions, robot_id=robot_id, result=result, source="query")
        return result

    def observe(
        self,
        *,
        atlas_name: str,
        fields: FrameFields,
        image_bytes: bytes,
        k: int = 5,
        query_filter: QueryFilter | None = None,
        sequence_length: int | None = None,
    ) -> tuple[QueryResult, Frame]:
        """:meth:`AtlasQueries.observe` with the observing robot's default filter; a loop onto
        another robot's frame is recorded."""
        result, frame = self.queries.observe(
            atlas_name=atlas_name,
            fields=fields,
            image_bytes=image_bytes,
            query_filter=query_filter or self._robot_filter(fields),
            k=k,
            sequence_length=sequence_length,
        )
        self._record_observation(fields, result, frame)
        return result, frame

    def observe_features(
        self,
        *,
        atlas_name: str,
        fields: FrameFields,
        features: FrameFeatures,
        k: int = 5,
        query_filter: QueryFilter | None = None,
        sequence_length: int | None = None,
    ) -> tuple[QueryResult, Frame]:
        """:meth:`AtlasQueries.observe_features` with the observing robot's default filter; a
        loop onto another robot's frame is recorded."""
        result, frame = self.queries.observe_features(
            atlas_name=atlas_name,
            fields=fields,
            features=features,
            query_filter=query_filter or self._robot_filter(fields),
            k=k,
            sequence_length=sequence_length,
        )
        self._record_observation(fields, result, frame)
        return result, frame

    def _record_observation(self, fields: FrameFields, result: QueryResult, frame: Frame) -> None:
        """An observation's loop onto another robot's frame, and its verified closure as a
        revisit pair (which may queue an automatic adaptation)."""
        record_if_inter_robot(
            self.sessions,
            robot_id=fields.robot_id,
            result=result,
            source="observe",
            query_frame_id=frame.id,
        )
        record_verified(
            self.sessions,
            self.settings,
            result=result,
            frame_id=frame.id,
            enqueue=self.frames.enqueue,
        )

    def _robot_filter(self, fields: FrameFields) -> QueryFilter:
        return self.query_filter(robot_id=fields.robot_id, timestamp=fields.timestamp)


__all__ = ["AtlasService", "LoadedAtlas"]

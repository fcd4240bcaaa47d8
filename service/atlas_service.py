"""The domain service behind the API and CLI: atlases, ingest and query.

It owns the feature pipeline (CNNs), the database session factory and one loaded state per
atlas (active heads + FAISS index). Writes follow one order so that a rejected request leaves
nothing behind: validate and decode, run the CNNs, embed, then commit the rows in one
transaction, and only then add the vector to the in-memory index.
"""

from __future__ import annotations

import logging
import shutil
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from sqlalchemy.orm import Session, sessionmaker

from service import change_feed, models_store
from service.concurrency import InferenceGate, default_workers
from service.config import Settings
from service.errors import Conflict, InvalidInput, NotFound
from service.geometry import Intrinsics, Pose
from service.index import AtlasIndex
from service.index_builder import add_stored_frames
from service.ml.features import FrameFeatures
from service.ml.heads import LoopNetHeads
from service.ml.images import decode_image
from service.ml.matching import resolve_matcher_name
from service.ml.pipeline import FeaturePipeline, embed_vectors
from service.ml.two_view import RansacConfig
from service.names import validate_name
from service.query_filters import QueryFilter, resolve
from service.storage import repository as repo
from service.storage.db import transaction
from service.storage.feature_store import load_local_features
from service.storage.models import Atlas, Frame, ModelVersion, Submap
from service.verification import (
    RelativePose,
    Verification,
    VerificationConfig,
    Verifier,
    View,
    decide,
    default_min_inliers,
    rerank,
)

log = logging.getLogger(__name__)

# Frames searched per query beyond k, so the margin finds the best other place even when the
# top k all lie in the match's submap.
MARGIN_POOL = 32


@dataclass
class LoadedAtlas:
    """What queries of one atlas need in memory: its active heads and its index."""

    atlas_id: int
    model_version: int
    heads: LoopNetHeads
    index: AtlasIndex
    dirty: bool = False
    checked_at: float = field(default_factory=time.monotonic)
    revision: int = 0  # the atlas revision the index reflects (see service/change_feed.py)


@dataclass
class Candidate:
    frame_id: int
    submap: str
    robot_id: str
    similarity: float
    inliers: int | None = None
    inlier_ratio: float | None = None
    verified: bool = False
    relative_pose: RelativePose | None = None


@dataclass
class VerificationSummary:
    """How the candidates of an answer were verified."""

    enabled: bool
    matcher: str | None = None
    verified_candidates: int = 0
    min_inliers: int | None = None


@dataclass
class SubmapGuess:
    available: bool
    submap: str | None = None
    probability: float | None = None
    reason: str | None = None


@dataclass
class QueryResult:
    atlas: str
    model_version: int
    match: Candidate | None
    candidates: list[Candidate]
    loop_closure: bool
    threshold: float
    predicted_submap: SubmapGuess
    keypoints: int
    timings_ms: dict[str, float] = field(default_factory=dict)
    margin: float | None = None
    verification: VerificationSummary = field(
        default_factory=lambda: VerificationSummary(enabled=False)
    )


class AtlasService:
    """Atlases, submaps, frames and queries over one database and one data directory."""

    def __init__(
        self, settings: Settings, sessions: sessionmaker[Session], pipeline: FeaturePipeline
    ) -> None:
        self.settings = settings
        self.sessions = sessions
        self.pipeline = pipeline
        self._loaded: dict[int, LoadedAtlas] = {}
        self._loaded_lock = threading.Lock()
        # Per atlas: held while its state is swapped and while a new frame enters its index,
        # so a frame committed around a swap always ends up in the index that is served.
        self._atlas_locks: dict[int, threading.RLock] = {}
        # Decode + CNNs behind a bounded gate: beyond its slots and queue, Overloaded (503).
        self.inference = InferenceGate(
            settings.inference_workers or default_workers(settings.torch_threads),
            settings.inference_queue,
            settings.inference_wait_seconds,
        )
        matcher = resolve_matcher_name(settings.matcher, pipeline.preset.local.name)
        self.verification_config = VerificationConfig(
            matcher=matcher,
            top=settings.verify_top,
            min_inliers=settings.verify_min_inliers or default_min_inliers(matcher),
            ratio=settings.verify_ratio,
            ransac=RansacConfig(threshold_px=settings.ransac_threshold_px),
        )
        self._verifier: Verifier | None = None  # built on first use (LightGlue loads weights)

    # ----- atlases -----------------------------------------------------------------------

    def create_atlas(self, name: str, description: str = "") -> Atlas:
        validate_name("atlas", name)
        heads_config = self.pipeline.heads_config()
        with transaction(self.sessions) as session:
            atlas = repo.create_atlas(
                session,
                name=name,
                description=description,
                feature_signature=self.pipeline.signature,
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
        with self._loaded_lock:
            self._loaded.pop(atlas_id, None)
        for path in self.settings.index_dir.glob(f"atlas-{atlas_id}-*.faiss"):
            path.unlink(missing_ok=True)
        shutil.rmtree(self.settings.models_dir / f"atlas-{atlas_id}", ignore_errors=True)

    def atlas_summary(self, session: Session, atlas: Atlas) -> dict[str, Any]:
        version = repo.active_model_version(session, atlas_id=atlas.id)
        return {
            "name": atlas.name,
            "description": atlas.description,
            "created_at": atlas.created_at,
            "submaps": repo.count_submaps(session, atlas_id=atlas.id),
            "frames": repo.count_frames(session, atlas_id=atlas.id),
            "active_model_version": version.version,
            "classifier_trained": bool(version.config.get("trained")),
            "feature_signature": atlas.feature_signature,
        }

    # ----- loaded state ------------------------------------------------------------------

    def load_all(self) -> None:
        """Load heads and reconcile the index of every atlas (at start-up)."""
        with self.sessions() as session:
            atlas_ids = [a.id for a in repo.list_atlases(session)]
        for atlas_id in atlas_ids:
            self.loaded(atlas_id)

    def _atlas_lock(self, atlas_id: int) -> threading.RLock:
        with self._loaded_lock:
            return self._atlas_locks.setdefault(atlas_id, threading.RLock())

    def loaded(self, atlas_id: int) -> LoadedAtlas:
        """The in-memory state of an atlas: loaded on first use, and swapped for the new one
        when another process (a retraining worker, an operator's rollback) has activated another
        model version. Queries in flight keep the state they started with."""
        with self._loaded_lock:
            state = self._loaded.get(atlas_id)
        if state is not None and not self._active_version_changed(state):
            return state
        with self._atlas_lock(atlas_id):
            with self._loaded_lock:
                current = self._loaded.get(atlas_id)
            if current is not None and current is not state:
                return current  # another thread swapped meanwhile
            new = self._load(atlas_id)
            if state is not None:
                log.info(
                    "atlas %d: now serving model version %d (was %d)",
                    atlas_id,
                    new.model_version,
                    state.model_version,
                )
                if state.dirty:
                    self.save_index(state)  # keep the old version's file current for rollback
            with self._loaded_lock:
                self._loaded[atlas_id] = new
            return new

    def refresh(self, atlas_id: int) -> LoadedAtlas:
        """Serve the database's active version now, without waiting for the next poll."""
        with self._loaded_lock:
            state = self._loaded.get(atlas_id)
        if state is not None:
            state.checked_at = float("-inf")
        return self.loaded(atlas_id)

    def _active_version_changed(self, state: LoadedAtlas) -> bool:
        """Whether the database's active version differs (checked at most once per poll period)."""
        now = time.monotonic()
        if now - state.checked_at < self.settings.model_poll_seconds:
            return False
        state.checked_at = now
        with self.sessions() as session:
            try:
                active = repo.active_model_version(session, atlas_id=state.atlas_id)
            except NotFound:
                return False  # the atlas is being deleted
        return active.version != state.model_version

    def _index_path(self, atlas_id: int, version: int) -> Path:
        return models_store.index_file(self.settings.index_dir, atlas_id, version)

    def _load(self, atlas_id: int) -> LoadedAtlas:
        with self.sessions() as session:
            version: ModelVersion = repo.active_model_version(session, atlas_id=atlas_id)
            heads = models_store.load_heads(version, self.settings.models_dir)
            # the revision first: frames read after it can only be newer, never missing
            revision = change_feed.atlas_revision(session, atlas_id=atlas_id)
            robot_of = repo.frame_ids_and_robots(session, atlas_id=atlas_id)
            path = self._index_path(atlas_id, version.version)
            index = None
            if path.is_file():
                try:
                    index = AtlasIndex.load(path, heads.config.fused_dim)
                except Exception as exc:  # a corrupt cache is rebuilt, never trusted
                    log.warning("index %s unreadable (%s); rebuilding from the database", path, exc)
            if index is None:
                index = AtlasIndex(heads.config.fused_dim)
            state = LoadedAtlas(atlas_id, version.version, heads, index, revision=revision)
            self._reconcile(session, state, robot_of)
        return state

    def _reconcile(self, session: Session, state: LoadedAtlas, robot_of: dict[int, str]) -> None:
        """Make the index hold exactly the database's frames: drop extras, embed missing ones."""
        in_index = set(state.index.ids().tolist())
        in_db = set(robot_of)
        extra = np.array(sorted(in_index - in_db), np.int64)
        missing = sorted(in_db - in_index)
        state.index.remove(extra)
        state.index.set_robots({i: robot_of[i] for i in in_db & in_index})
        add_stored_frames(session, state.atlas_id, state.heads, state.index, frame_ids=missing)
        if len(extra) or missing:
            log.info(
                "atlas %d: index caught up with the database (+%d, -%d frames)",
                state.atlas_id,
                len(missing),
                len(extra),
            )
            state.dirty = True

    def rebuild_index(self, atlas_name: str) -> int:
        """Re-embed every frame of an atlas from stored features into a fresh index file."""
        with self.sessions() as session:
            atlas_id = repo.get_atlas(session, name=atlas_name).id
        with self._atlas_lock(atlas_id):
            with self._loaded_lock:
                self._loaded.pop(atlas_id, None)
            with self.sessions() as session:
                version = repo.active_model_version(session, atlas_id=atlas_id)
            self._index_path(atlas_id, version.version).unlink(missing_ok=True)
            state = self.loaded(atlas_id)
            self.save_index(state)
            return state.index.size

    def save_index(self, state: LoadedAtlas) -> None:
        state.index.save(self._index_path(state.atlas_id, state.model_version))
        state.dirty = False

    def flush(self) -> None:
        """Write every changed index to disk (at shutdown; a crash is caught up at start)."""
        with self._loaded_lock:
            states = list(self._loaded.values())
        for state in states:
            if state.dirty:
                self.save_index(state)

    # ----- frames ------------------------------------------------------------------------

    def _check_signature(self, atlas: Atlas) -> None:
        if atlas.feature_signature != self.pipeline.signature:
            raise Conflict(
                f"atlas '{atlas.name}' holds features {atlas.feature_signature}, but this service "
                f"extracts {self.pipeline.signature}; run the service with the atlas's preset"
            )

    def extract(self, image_bytes: bytes) -> tuple[FrameFeatures, float]:
        """Decode and run the CNNs in one of the gate's slots; returns the features and the
        decode time in ms. Raises Overloaded when every slot is busy and the queue is full."""
        with self.inference.slot():
            start = time.perf_counter()
            rgb = decode_image(image_bytes, self.settings.image_limits)
            decode_ms = (time.perf_counter() - start) * 1000.0
            features = self.pipeline.extract(rgb)
        return features, decode_ms

    def ingest_frame(
        self,
        *,
        atlas_name: str,
        submap_name: str,
        robot_id: str,
        image_bytes: bytes,
        timestamp: float | None = None,
        pose: Pose | None = None,
        intrinsics: Intrinsics | None = None,
    ) -> Frame:
        """Store a frame, its features and its embedding; nothing is written if any step fails."""
        self._validate_frame_fields(robot_id, timestamp)
        with self.sessions() as session:
            atlas = repo.get_atlas(session, name=atlas_name)
            self._check_signature(atlas)
            repo.get_submap(session, atlas=atlas, name=submap_name)
        features, _ = self.extract(image_bytes)
        return self.ingest_features(
            atlas_name=atlas_name,
            submap_name=submap_name,
            robot_id=robot_id,
            features=features,
            timestamp=timestamp,
            pose=pose,
            intrinsics=intrinsics,
        )

    def ingest_features(
        self,
        *,
        atlas_name: str,
        submap_name: str,
        robot_id: str,
        features: FrameFeatures,
        timestamp: float | None = None,
        pose: Pose | None = None,
        intrinsics: Intrinsics | None = None,
    ) -> Frame:
        """Store a frame whose features are already extracted (by :meth:`extract`).

        The rows are committed in one transaction; the embedding is then computed with the
        atlas's *current* heads and added to its index, so a model swap in between cannot leave
        the frame embedded by the wrong version.
        """
        self._validate_frame_fields(robot_id, timestamp)
        with transaction(self.sessions) as session:
            atlas = repo.get_atlas(session, name=atlas_name)
            self._check_signature(atlas)
            submap = repo.get_submap(session, atlas=atlas, name=submap_name)
            frame = repo.add_frame(
                session,
                atlas=atlas,
                submap=submap,
                robot_id=robot_id,
                timestamp=timestamp,
                pose=pose,
                intrinsics=intrinsics,
                features=features,
            )
            revision = change_feed.record(
                session, atlas_id=atlas.id, op=change_feed.ADD, frame_ids=[frame.id]
            )
        with self._atlas_lock(frame.atlas_id):
            state = self.loaded(frame.atlas_id)
            if state.revision < revision:  # else the change feed has handled it already
                embedding = self._embed(state.heads, features)
                state.index.add(np.array([frame.id]), embedding[None], [robot_id])
                state.dirty = True
        return frame

    def delete_frame(self, atlas_name: str, frame_id: int) -> None:
        """Delete one frame (rows, features); every process drops it from its index."""
        with transaction(self.sessions) as session:
            atlas = repo.get_atlas(session, name=atlas_name)
            session.delete(repo.get_frame(session, atlas=atlas, frame_id=frame_id))
            atlas_id = atlas.id
            revision = change_feed.record(
                session, atlas_id=atlas_id, op=change_feed.REMOVE, frame_ids=[frame_id]
            )
        self._drop_from_index(atlas_id, [frame_id], revision)

    def delete_submap(self, atlas_name: str, submap_name: str) -> int:
        """Delete a submap with its frames; returns how many frames went."""
        with transaction(self.sessions) as session:
            atlas = repo.get_atlas(session, name=atlas_name)
            submap = repo.get_submap(session, atlas=atlas, name=submap_name)
            frame_ids = repo.frame_ids_of_submap(session, submap_id=submap.id)
            session.delete(submap)  # the database cascades to its frames and their features
            atlas_id, revision = atlas.id, None
            if frame_ids:
                revision = change_feed.record(
                    session, atlas_id=atlas_id, op=change_feed.REMOVE, frame_ids=frame_ids
                )
        if revision is not None:
            self._drop_from_index(atlas_id, frame_ids, revision)
        return len(frame_ids)

    def _drop_from_index(self, atlas_id: int, frame_ids: list[int], revision: int) -> None:
        with self._atlas_lock(atlas_id):
            with self._loaded_lock:
                state = self._loaded.get(atlas_id)
            if state is not None and state.revision < revision:
                state.index.remove(np.array(frame_ids, np.int64))
                state.dirty = True

    def follow(self, revisions: dict[int, int]) -> None:
        """Catch the loaded atlases up with the database (``revisions``: atlas id -> current).

        Called by the :class:`~service.change_feed.ChangeFollower` thread: applies the frames
        other processes added or removed, and forgets atlases deleted elsewhere.
        """
        with self._loaded_lock:
            loaded_ids = list(self._loaded)
        for atlas_id in loaded_ids:
            if atlas_id not in revisions:
                with self._loaded_lock:
                    self._loaded.pop(atlas_id, None)
                log.info("atlas %d was deleted; dropped from memory", atlas_id)
                continue
            with self._atlas_lock(atlas_id):
                with self._loaded_lock:
                    state = self._loaded.get(atlas_id)
                if state is None or state.revision >= revisions[atlas_id]:
                    continue
                upto = revisions[atlas_id]
                with self.sessions() as session:
                    changes = change_feed.changes_between(
                        session, atlas_id=atlas_id, after=state.revision, upto=upto
                    )
                    if changes.complete:
                        state.index.remove(np.array(changes.removed, np.int64))
                        add_stored_frames(
                            session, atlas_id, state.heads, state.index, frame_ids=changes.added
                        )
                    else:  # the log was pruned past our cursor: compare everything
                        upto = change_feed.atlas_revision(session, atlas_id=atlas_id)
                        robot_of = repo.frame_ids_and_robots(session, atlas_id=atlas_id)
                        self._reconcile(session, state, robot_of)
                state.revision, state.dirty = upto, True

    @staticmethod
    def _validate_frame_fields(robot_id: str, timestamp: float | None) -> None:
        validate_name("robot", robot_id)
        if timestamp is not None and not np.isfinite(timestamp):
            raise InvalidInput("timestamp must be a finite number of seconds")

    @staticmethod
    def _embed(heads: LoopNetHeads, features: FrameFeatures) -> np.ndarray:
        return embed_vectors(heads, features.local_vector[None], features.global_vector[None])[0]

    # ----- queries -----------------------------------------------------------------------

    def query_filter(
        self,
        *,
        robot_id: str | None = None,
        robots: str = "all",
        submap: str | None = None,
        since: float | None = None,
        until: float | None = None,
        timestamp: float | None = None,
        exclude_recent_frames: int | None = None,
        exclude_recent_seconds: float | None = None,
    ) -> QueryFilter:
        """A validated :class:`QueryFilter`, with the settings' recent-frame exclusion unless
        the request overrides it."""
        if robot_id is not None:
            validate_name("robot", robot_id)
        if submap is not None:
            validate_name("submap", submap)
        query_filter = QueryFilter(
            robot_id=robot_id,
            robots=robots,
            submap=submap,
            since=since,
            until=until,
            timestamp=timestamp,
            exclude_recent_frames=(
                self.settings.exclude_recent_frames
                if exclude_recent_frames is None
                else exclude_recent_frames
            ),
            exclude_recent_seconds=(
                self.settings.exclude_recent_seconds
                if exclude_recent_seconds is None
                else exclude_recent_seconds
            ),
        )
        query_filter.validate()
        return query_filter

    def query(
        self,
        *,
        atlas_name: str,
        image_bytes: bytes,
        k: int = 5,
        robot_id: str | None = None,
        query_filter: QueryFilter | None = None,
        intrinsics: Intrinsics | None = None,
    ) -> QueryResult:
        """The frames of the atlas most similar to an image, verified, and the loop-closure
        decision. ``robot_id`` is the robot asking (its recent frames never match)."""
        total_start = time.perf_counter()
        query_filter = query_filter or self.query_filter(robot_id=robot_id)
        self._validate_query_fields(k)
        with self.sessions() as session:
            self._check_signature(repo.get_atlas(session, name=atlas_name))
        features, decode_ms = self.extract(image_bytes)
        result = self.query_features(
            atlas_name=atlas_name,
            features=features,
            k=k,
            query_filter=query_filter,
            intrinsics=intrinsics,
        )
        return self._with_extraction_timings(result, features, decode_ms, total_start)

    @staticmethod
    def _with_extraction_timings(
        result: QueryResult, features: FrameFeatures, decode_ms: float, total_start: float
    ) -> QueryResult:
        result.timings_ms = {
            "decode": round(decode_ms, 3),
            **{name: round(ms, 3) for name, ms in features.timings_ms.items()},
            **result.timings_ms,
            "total": round((time.perf_counter() - total_start) * 1000.0, 3),
        }
        return result

    def observe(
        self,
        *,
        atlas_name: str,
        submap_name: str,
        robot_id: str,
        image_bytes: bytes,
        timestamp: float | None = None,
        pose: Pose | None = None,
        intrinsics: Intrinsics | None = None,
        k: int = 5,
        query_filter: QueryFilter | None = None,
    ) -> tuple[QueryResult, Frame]:
        """Online SLAM: query with a robot's new keyframe, then insert it, in one call.

        Everything is validated before the CNNs run; the query happens before the insert, so
        the new frame is never its own match; the insert is one transaction, so a failure
        writes nothing.
        """
        total_start = time.perf_counter()
        self._validate_frame_fields(robot_id, timestamp)
        self._validate_query_fields(k)
        query_filter = query_filter or self.query_filter(robot_id=robot_id, timestamp=timestamp)
        if query_filter.robot_id != robot_id:
            raise InvalidInput("an observation's filter must be for the observing robot")
        with self.sessions() as session:
            atlas = repo.get_atlas(session, name=atlas_name)
            self._check_signature(atlas)
            repo.get_submap(session, atlas=atlas, name=submap_name)
        features, decode_ms = self.extract(image_bytes)
        result = self.query_features(
            atlas_name=atlas_name,
            features=features,
            k=k,
            query_filter=query_filter,
            intrinsics=intrinsics,
        )
        frame = self.ingest_features(
            atlas_name=atlas_name,
            submap_name=submap_name,
            robot_id=robot_id,
            features=features,
            timestamp=timestamp,
            pose=pose,
            intrinsics=intrinsics,
        )
        return self._with_extraction_timings(result, features, decode_ms, total_start), frame

    def query_features(
        self,
        *,
        atlas_name: str,
        features: FrameFeatures,
        k: int = 5,
        robot_id: str | None = None,
        query_filter: QueryFilter | None = None,
        intrinsics: Intrinsics | None = None,
    ) -> QueryResult:
        """Search with already extracted features (by :meth:`extract`), verify the best
        candidates; timings cover the heads, the search and the verification."""
        self._validate_query_fields(k)
        query_filter = query_filter or self.query_filter(robot_id=robot_id)
        with self.sessions() as session:
            atlas = repo.get_atlas(session, name=atlas_name)
            self._check_signature(atlas)
            atlas_id = atlas.id
            selection = resolve(session, atlas, query_filter)
        state = self.loaded(atlas_id)
        timings: dict[str, float] = {}

        start = time.perf_counter()
        embedding = self._embed(state.heads, features)
        prediction = state.heads.predict_submap(
            torch.from_numpy(features.local_vector[None]),
            torch.from_numpy(features.global_vector[None]),
        )
        timings["heads"] = (time.perf_counter() - start) * 1000.0

        config = self.verification_config
        start = time.perf_counter()
        pool = max(k, config.top, MARGIN_POOL)
        hits = state.index.search(
            embedding, pool, include=selection.include, exclude=selection.exclude
        )
        timings["search"] = (time.perf_counter() - start) * 1000.0

        with self.sessions() as session:
            names = repo.submap_names(session, atlas_id=atlas_id)
            frames = repo.frames_by_id(session, frame_ids=[h.frame_id for h in hits])
        candidates = [
            Candidate(h.frame_id, names[f.submap_id], f.robot_id, h.similarity)
            for h in hits
            if (f := frames.get(h.frame_id)) is not None
        ]
        verifications: dict[int, Verification] = {}
        if config.top > 0 and candidates:
            start = time.perf_counter()
            checked = candidates[: config.top]
            verifications = self._verify(
                View(features.local, features.image_size, intrinsics),
                [(c.frame_id, frames[c.frame_id]) for c in checked],
            )
            for candidate in checked:
                found = verifications.get(candidate.frame_id)
                if found is not None:
                    candidate.inliers = found.inliers
                    candidate.inlier_ratio = round(found.inlier_ratio, 4)
                    candidate.verified = found.verified
                    candidate.relative_pose = found.relative_pose
            order = rerank([c.similarity for c in candidates], [c.inliers for c in candidates])
            candidates = [candidates[i] for i in order]
            timings["verification"] = (time.perf_counter() - start) * 1000.0
        if prediction is None:
            guess = SubmapGuess(
                available=False,
                reason=(
                    f"model version {state.model_version} of atlas '{atlas_name}' has no trained "
                    "classification head; run a retrain job to get submap predictions"
                ),
            )
        else:
            guess = SubmapGuess(True, names.get(prediction.submap_id), prediction.probability)
        threshold = self.settings.loop_closure_threshold
        match = candidates[0] if candidates else None
        loop_closure = decide(
            match.similarity if match else None,
            verifications.get(match.frame_id) if match else None,
            threshold=threshold,
            verify=config.top > 0,
        )
        return QueryResult(
            atlas=atlas_name,
            model_version=state.model_version,
            match=match,
            candidates=candidates[:k],
            loop_closure=loop_closure,
            threshold=threshold,
            predicted_submap=guess,
            keypoints=features.local.count,
            timings_ms={name: round(ms, 3) for name, ms in timings.items()},
            margin=place_margin(candidates),
            verification=VerificationSummary(
                enabled=config.top > 0,
                matcher=config.matcher if config.top > 0 else None,
                verified_candidates=len(verifications),
                min_inliers=config.min_inliers if config.top > 0 else None,
            ),
        )

    @property
    def verifier(self) -> Verifier:
        if self._verifier is None:
            self._verifier = Verifier(self.verification_config)
        return self._verifier

    def _verify(self, query: View, frames: list[tuple[int, Frame]]) -> dict[int, Verification]:
        """Verify the query against stored frames, reading their keypoints from the store."""
        with self.sessions() as session:
            stored = load_local_features(session, [frame_id for frame_id, _ in frames])
        verifier = self.verifier
        found = {}
        with self.inference.slot():  # matching and RANSAC are inference work too (torch threads)
            for frame_id, frame in frames:
                local = stored.get(frame_id)
                if local is None:
                    continue  # deleted meanwhile
                intrinsics = (
                    Intrinsics(frame.fx, frame.fy, frame.cx, frame.cy)  # type: ignore[arg-type]
                    if frame.fx is not None
                    else None
                )
                view = View(local, (frame.width, frame.height), intrinsics)
                found[frame_id] = verifier.verify(query, view)
        return found

    def _validate_query_fields(self, k: int) -> None:
        if not 1 <= k <= self.settings.max_k:
            raise InvalidInput(f"k must be between 1 and {self.settings.max_k}, got {k}")


def place_margin(candidates: list[Candidate]) -> float | None:
    """Similarity of the match minus that of the best candidate from another place, a place
    being a submap: small or negative means a look-alike elsewhere competes with the match.
    None when every searched frame lies in the match's submap."""
    if not candidates:
        return None
    best = candidates[0]
    others = [c.similarity for c in candidates[1:] if c.submap != best.submap]
    return round(best.similarity - max(others), 6) if others else None

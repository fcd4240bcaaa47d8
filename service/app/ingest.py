"""Adding frames to an atlas and deleting them.

Writes follow one order so that a rejected request leaves nothing behind: validate (names,
atlas, feature signature, submap) before any CNN runs, decode and run the CNNs, then commit the
rows in one transaction, and only then add the embedding to the in-memory index.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from sqlalchemy.orm import Session, sessionmaker

from service.app import change_feed
from service.app.milestones import calibration_due
from service.app.names import validate_name
from service.app.state import AtlasStates
from service.concurrency import InferenceGate
from service.config import Settings
from service.errors import Conflict, InvalidInput
from service.index.store import PGVECTOR
from service.metrics import observe_stages
from service.ml.decode_memory import DecodeBudget
from service.ml.features import FrameFeatures
from service.ml.geometry import Intrinsics, Pose
from service.ml.images import decode_frame, in_upload_pixels
from service.ml.pipeline import FeaturePipeline
from service.ml.thumbnails import make_thumbnail
from service.storage import repository as repo
from service.storage.db import transaction
from service.storage.models import Atlas, Frame

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FrameFields:
    """What a robot says of a frame it sends: the submap it joins, who took it, when, from
    where and with which camera. One value for ingest and observe alike."""

    submap_name: str
    robot_id: str
    timestamp: float | None = None
    pose: Pose | None = None
    intrinsics: Intrinsics | None = None

    def validate(self) -> None:
        """The robot's name and a finite timestamp (the submap is checked against the atlas)."""
        validate_name("robot", self.robot_id)
        if self.timestamp is not None and not np.isfinite(self.timestamp):
            raise InvalidInput("timestamp must be a finite number of seconds")


class FrameIngest:
    """Extraction behind the inference gate, and the frame writes of every atlas."""

    def __init__(
        self,
        settings: Settings,
        sessions: sessionmaker[Session],
        pipeline: FeaturePipeline,
        states: AtlasStates,
        inference: InferenceGate,
    ) -> None:
        self.settings = settings
        self.sessions = sessions
        self.pipeline = pipeline
        self.states = states
        self.inference = inference
        # every decode of the process holds its peak memory from this budget
        self.decode_budget = DecodeBudget(
            settings.decode_memory_bytes, settings.inference_wait_seconds
        )
        # hands a job id to the queue (set by the process that has one); without it, or when
        # the queue is down, a milestone's job waits queued for a worker's sweep
        self.enqueue: Callable[[int], None] | None = None

    def checked_atlas(self, session: Session, atlas_name: str) -> Atlas:
        """The atlas by name (NotFound), refused (Conflict) when its features are not ours."""
        atlas = repo.get_atlas(session, name=atlas_name)
        if not self.pipeline.signature.matches(atlas.feature_signature):
            raise Conflict(
                f"atlas '{atlas.name}' holds features {atlas.feature_signature}, but this service "
                f"extracts {self.pipeline.signature.to_json()}; run the service with the atlas's "
                "preset"
            )
        return atlas

    def extract(
        self, image_bytes: bytes, *, thumbnail: bool = True
    ) -> tuple[FrameFeatures, float, np.ndarray]:
        """Decode and run the CNNs in one of the gate's slots; returns the features (with their
        thumbnail unless ``thumbnail`` is False: a query makes one only if a loop closes), the
        decode time in ms and the decoded frame (shrunk when the upload is much larger than the
        networks use; the features are in the upload's pixels all the same). Raises Overloaded
        when every slot is busy and the queue is full, or the decode memory budget stays full."""
        with self.inference.slot():
            start = time.perf_counter()
            frame = decode_frame(
                image_bytes,
                self.settings.image_limits,
                working_side=self.pipeline.working_side,
                budget=self.decode_budget,
            )
            decode_ms = (time.perf_counter() - start) * 1000.0
            features = in_upload_pixels(self.pipeline.extract(frame.rgb), frame)
            if thumbnail:
                features.thumbnail = make_thumbnail(frame.rgb)
        observe_stages({"decode": decode_ms, **features.timings_ms})
        return features, decode_ms, frame.rgb

    def ingest_frame(self, *, atlas_name: str, fields: FrameFields, image_bytes: bytes) -> Frame:
        """Store a frame, its features and its embedding; nothing is written if any step fails."""
        fields.validate()
        with self.sessions() as session:
            atlas = self.checked_atlas(session, atlas_name)
            repo.get_submap(session, atlas=atlas, name=fields.submap_name)
        features, _, _ = self.extract(image_bytes)
        return self.store(atlas_name=atlas_name, fields=fields, features=features)

    def ingest_features(
        self, *, atlas_name: str, fields: FrameFields, features: FrameFeatures
    ) -> Frame:
        """Store a frame whose features are already extracted (validated here)."""
        fields.validate()
        return self.store(atlas_name=atlas_name, fields=fields, features=features)

    def store(
        self,
        *,
        atlas_name: str,
        fields: FrameFields,
        features: FrameFeatures,
        proposals: list[int] | None = None,
        loop_frame_id: int | None = None,
        loop_pending: bool = False,
    ) -> Frame:
        """Commit a validated frame's rows in one transaction; the embedding is then computed
        with the atlas's *current* heads and added to its index, so a model swap in between
        cannot leave the frame embedded by the wrong version. ``proposals``: what the frame's
        own search found (an observation's), kept for sequence scoring; ``loop_frame_id``: the
        frame that observation closed a loop with (``loop_pending``: or left to a later frame to
        confirm)."""
        if self.states.store_kind == PGVECTOR:  # load the atlas (and its table) beforehand
            with self.sessions() as session:
                self.states.loaded(self.checked_atlas(session, atlas_name).id)
        with transaction(self.sessions) as session:
            atlas = self.checked_atlas(session, atlas_name)
            submap = repo.get_submap(session, atlas=atlas, name=fields.submap_name)
            frame = repo.add_frame(
                session,
                atlas=atlas,
                submap=submap,
                robot_id=fields.robot_id,
                timestamp=fields.timestamp,
                pose=fields.pose,
                intrinsics=fields.intrinsics,
                features=features,
                proposals=proposals,
                loop_frame_id=loop_frame_id,
                loop_pending=loop_pending,
            )
            in_table = self.states.store_kind == PGVECTOR
            revision = change_feed.record(  # pgvector: the feed only orders (no frame rows)
                session,
                atlas_id=atlas.id,
                op=change_feed.ADD,
                frame_ids=[] if in_table else [frame.id],
            )
            if in_table:  # the vector commits with its frame: every replica finds it then
                written = self.states.write_vector(
                    session, atlas.id, frame.id, features, fields.robot_id
                )
            calibration = calibration_due(session, self.settings, atlas.id)
            job_id = calibration.id if calibration is not None else None
        if job_id is not None:
            self._enqueue_calibration(job_id)
        if in_table:
            if not written:  # a version activated meanwhile: embed under it now
                self.states.catch_up(frame.atlas_id)
            return frame
        with self.states.lock(frame.atlas_id):
            state = self.states.loaded(frame.atlas_id)
            if state.revision < revision:  # else the change feed has handled it already
                embedding = state.model.embed(features)
                state.index.add(np.array([frame.id]), embedding[None], [fields.robot_id])
                state.dirty = True
        return frame

    def _enqueue_calibration(self, job_id: int) -> None:
        if self.enqueue is None:
            return
        try:
            self.enqueue(job_id)
        except Exception as exc:  # the frame is stored; the sweep will enqueue the job
            log.warning(
                "calibration job %d not queued now (%s); a worker will find it", job_id, exc
            )

    def delete_frame(self, atlas_name: str, frame_id: int) -> None:
        """Delete one frame (rows, features); every process drops it from its index."""
        with transaction(self.sessions) as session:
            atlas = repo.get_atlas(session, name=atlas_name)
            session.delete(repo.get_frame(session, atlas=atlas, frame_id=frame_id))
            atlas_id = atlas.id
            revision = change_feed.record(
                session, atlas_id=atlas_id, op=change_feed.REMOVE, frame_ids=[frame_id]
            )
        self.states.drop_from_index(atlas_id, [frame_id], revision)

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
            self.states.drop_from_index(atlas_id, frame_ids, revision)
        return len(frame_ids)

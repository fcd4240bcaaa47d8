"""The loaded state of each atlas (active heads + FAISS index): loaded on first use, reconciled
with the database, and kept following the change feed: frames any process adds or removes, and
model versions activated anywhere (swapped in by the follower thread, never by a request)."""

from __future__ import annotations

import contextlib
import logging
import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from sqlalchemy.orm import Session, sessionmaker

from service.app import change_feed
from service.app import model_versions as models_store
from service.app.broken_atlases import BrokenAtlases
from service.config import Settings
from service.errors import AtlasUnavailable, NotFound
from service.index import AtlasIndex
from service.index.builder import add_stored_frames
from service.index.pgvector_store import PgVectorStore
from service.index.store import PGVECTOR, VectorStore, resolve_kind
from service.ml.active_model import ActiveModel
from service.ml.calibration import Calibration
from service.ml.features import FrameFeatures
from service.ml.heads import LoopNetHeads
from service.storage import repository as repo
from service.storage.models import ModelVersion

log = logging.getLogger(__name__)


@dataclass
class LoadedAtlas:
    """What queries of one atlas need in memory: its active heads (over its calibration, when
    the version has one) and its index."""

    atlas_id: int
    model_version: int
    heads: LoopNetHeads
    index: VectorStore
    dirty: bool = False
    revision: int = 0  # the atlas revision the index reflects (see service/app/change_feed.py)
    calibration: Calibration | None = None
    min_inliers: tuple[str, int] | None = None  # (matcher, minimum) fitted by the calibration

    @property
    def model(self) -> ActiveModel:
        return ActiveModel(self.heads, self.calibration)


class AtlasStates:
    """One :class:`LoadedAtlas` per atlas, with the locks that keep swaps and inserts ordered."""

    def __init__(self, settings: Settings, sessions: sessionmaker[Session]) -> None:
        self.settings = settings
        self.sessions = sessions
        self.loaded_states: dict[int, LoadedAtlas] = {}
        self._loaded_lock = threading.Lock()
        # Per atlas: held while its state is swapped and while a new frame enters its index,
        # so a frame committed around a swap always ends up in the index that is served.
        self._atlas_locks: dict[int, threading.RLock] = {}
        # Atlases that failed to load: they answer 503 while the others serve.
        self.broken = BrokenAtlases(max(settings.model_poll_seconds, 1.0), settings.data_dir)
        # faiss (in-process indexes) or pgvector (tables in the database: no copy to follow)
        self.store_kind = resolve_kind(settings.vector_store, sessions.kw["bind"])

    def load_all(self) -> None:
        """Load heads and reconcile the index of every atlas (at start-up); an atlas that
        cannot be loaded is left out and reported (see :class:`BrokenAtlases`)."""
        with self.sessions() as session:
            atlas_ids = [a.id for a in repo.list_atlases(session)]
        for atlas_id in atlas_ids:
            with contextlib.suppress(AtlasUnavailable):  # reported by self.broken
                self.loaded(atlas_id)

    def lock(self, atlas_id: int) -> threading.RLock:
        with self._loaded_lock:
            return self._atlas_locks.setdefault(atlas_id, threading.RLock())

    def current(self, atlas_id: int) -> LoadedAtlas | None:
        """The state in memory now, if any (never loads)."""
        with self._loaded_lock:
            return self.loaded_states.get(atlas_id)

    def serving(self) -> list[LoadedAtlas]:
        """The states this process serves now (a snapshot; never loads)."""
        with self._loaded_lock:
            return list(self.loaded_states.values())

    def forget(self, atlas_id: int) -> None:
        with self._loaded_lock:
            self.loaded_states.pop(atlas_id, None)

    def loaded(self, atlas_id: int) -> LoadedAtlas:
        """The in-memory state of an atlas, loaded on first use. Another model version
        activated later is swapped in by :meth:`follow`, never here."""
        state = self.current(atlas_id)
        if state is not None:
            return state
        with self.lock(atlas_id):
            current = self.current(atlas_id)
            if current is not None:
                return current  # another thread loaded it meanwhile
            new = self.broken.load(atlas_id, lambda: self._load(atlas_id))
            with self._loaded_lock:
                self.loaded_states[atlas_id] = new
            return new

    def _swap(self, old: LoadedAtlas) -> None:
        """Serve the database's active version instead of ``old`` (the caller holds the atlas
        lock). Queries in flight keep the state they started with. If it cannot be loaded, the
        atlas answers 503 with the reason, as a broken atlas does at start."""
        atlas_id = old.atlas_id
        if old.dirty:
            self.save_index(old)  # keep the old version's file current for a rollback
        try:
            new = self.broken.load(atlas_id, lambda: self._load(atlas_id))
        except (AtlasUnavailable, NotFound):
            self.forget(atlas_id)
            return
        log.info(
            "atlas %d: now serving model version %d (was %d)",
            atlas_id,
            new.model_version,
            old.model_version,
        )
        with self._loaded_lock:
            self.loaded_states[atlas_id] = new

    @staticmethod
    def _serves_active(session: Session, state: LoadedAtlas) -> bool:
        """Whether ``state`` has the database's active version (an activation pruned from the
        log is caught here)."""
        try:
            active = repo.active_model_version(session, atlas_id=state.atlas_id)
        except NotFound:
            return True  # the atlas is being deleted
        return active.version == state.model_version

    def index_path(self, atlas_id: int, version: int) -> Path:
        return models_store.index_file(self.settings.index_dir, atlas_id, version)

    def _load(self, atlas_id: int) -> LoadedAtlas:
        with self.sessions() as session:
            version: ModelVersion = repo.active_model_version(session, atlas_id=atlas_id)
            heads = models_store.load_heads(version, self.settings.models_dir)
            calibration = models_store.load_calibration(version, self.settings.models_dir)
            fitted = (models_store.VersionConfig.of(version).calibration or {}).get("min_inliers")
            # the revision first: frames read after it can only be newer, never missing
            revision = change_feed.atlas_revision(session, atlas_id=atlas_id)
            robot_of = repo.frame_ids_and_robots(session, atlas_id=atlas_id)
            path = self.index_path(atlas_id, version.version)
            index: VectorStore | None = None
            if self.store_kind == PGVECTOR:
                index = self.table(atlas_id, version.version, heads.config.fused_dim)
            elif path.is_file():
                try:
                    index = AtlasIndex.load(path, heads.config.fused_dim)
                except Exception as exc:  # a corrupt cache is rebuilt, never trusted
                    log.warning("index %s unreadable (%s); rebuilding from the database", path, exc)
            if index is None:
                index = AtlasIndex(heads.config.fused_dim)
            state = LoadedAtlas(
                atlas_id,
                version.version,
                heads,
                index,
                revision=revision,
                calibration=calibration,
                min_inliers=(fitted["matcher"], fitted["min_inliers"]) if fitted else None,
            )
            self._reconcile(session, state, robot_of)
        return state

    def table(self, atlas_id: int, version: int, dim: int) -> PgVectorStore:
        """The pgvector table of an atlas's model version (created if missing)."""
        store = PgVectorStore(self.sessions, atlas_id, version, dim)
        store.create()
        return store

    def _reconcile(self, session: Session, state: LoadedAtlas, robot_of: dict[int, str]) -> None:
        """Make the index hold exactly the database's frames: drop extras, embed missing ones.
        (A pgvector table cannot hold extras: its rows go with their frames.)"""
        if isinstance(state.index, PgVectorStore):
            missing = state.index.missing_frames(session)
            add_stored_frames(session, state.atlas_id, state.model, state.index, frame_ids=missing)
            if missing:
                log.info(
                    "atlas %d: %d frames embedded into its table", state.atlas_id, len(missing)
                )
            return
        in_index = set(state.index.ids().tolist())
        in_db = set(robot_of)
        extra = np.array(sorted(in_index - in_db), np.int64)
        missing = sorted(in_db - in_index)
        state.index.remove(extra)
        state.index.set_robots({i: robot_of[i] for i in in_db & in_index})
        add_stored_frames(session, state.atlas_id, state.model, state.index, frame_ids=missing)
        if len(extra) or missing:
            log.info(
                "atlas %d: index caught up with the database (+%d, -%d frames)",
                state.atlas_id,
                len(missing),
                len(extra),
            )
            state.dirty = True

    def rebuild_index(self, atlas_id: int) -> int:
        """Re-embed every frame of an atlas from stored features into a fresh index file."""
        with self.lock(atlas_id):
            self.forget(atlas_id)
            with self.sessions() as session:
                version = repo.active_model_version(session, atlas_id=atlas_id)
            self.index_path(atlas_id, version.version).unlink(missing_ok=True)
            if self.store_kind == PGVECTOR:
                PgVectorStore(self.sessions, atlas_id, version.version, 1).drop()
            state = self.loaded(atlas_id)
            self.save_index(state)
            return state.index.size

    def save_index(self, state: LoadedAtlas) -> None:
        if isinstance(state.index, AtlasIndex):  # a table needs no file
            state.index.save(self.index_path(state.atlas_id, state.model_version))
        state.dirty = False

    def write_vector(
        self, session: Session, atlas_id: int, frame_id: int, features: FrameFeatures, robot: str
    ) -> bool:
        """pgvector: embed a frame and insert its vector in the caller's transaction (which
        holds the atlas row's lock: no activation can commit meanwhile). False, writing
        nothing, when this process serves another version than the active one; the frame is
        then embedded when the active version is swapped in (:meth:`catch_up`), and when the
        atlas is not loaded (loading creates tables, which would wait for this transaction)."""
        state = self.current(atlas_id)
        if state is None or not isinstance(state.index, PgVectorStore):
            return False
        active = repo.active_model_version(session, atlas_id=atlas_id)
        if active.version != state.model_version:
            return False
        embedding = state.model.embed(features)
        state.index.add(np.array([frame_id]), embedding[None], [robot], session=session)
        return True

    def catch_up(self, atlas_id: int) -> None:
        """Follow the database now for one atlas (a frame written around an activation)."""
        if self.current(atlas_id) is None:
            self.loaded(atlas_id)  # loading embeds the frames its table lacks
            return
        with self.sessions() as session:
            revision = change_feed.atlas_revision(session, atlas_id=atlas_id)
        self.follow({atlas_id: revision}, only=atlas_id)

    def flush(self) -> None:
        """Write every changed index to disk (at shutdown; a crash is caught up at start)."""
        with self._loaded_lock:
            states = list(self.loaded_states.values())
        for state in states:
            if state.dirty:
                self.save_index(state)

    def drop_from_index(self, atlas_id: int, frame_ids: list[int], revision: int) -> None:
        if self.store_kind == PGVECTOR:  # the rows went with their frames, in that transaction
            state = self.current(atlas_id)
            if state is not None and isinstance(state.index, PgVectorStore):
                state.index.journal_removal(np.array(frame_ids, np.int64))  # caches follow
            return
        with self.lock(atlas_id):
            state = self.current(atlas_id)
            if state is not None and state.revision < revision:
                state.index.remove(np.array(frame_ids, np.int64))
                state.dirty = True

    def follow(self, revisions: dict[int, int], *, only: int | None = None) -> None:
        """Catch the loaded atlases up with the database (``revisions``: atlas id -> current).

        Called by the :class:`~service.app.change_feed.ChangeFollower` thread: applies the
        frames other processes added or removed, swaps in a newly activated model version, and
        forgets atlases deleted elsewhere. With pgvector only the activations matter: the
        frames are in the shared tables already. ``only``: that atlas alone.
        """
        with self._loaded_lock:
            loaded_ids = [i for i in self.loaded_states if only is None or i == only]
        for atlas_id in loaded_ids:
            if atlas_id not in revisions:
                self.forget(atlas_id)
                log.info("atlas %d was deleted; dropped from memory", atlas_id)
                continue
            with self.lock(atlas_id):
                state = self.current(atlas_id)
                if state is None or state.revision >= revisions[atlas_id]:
                    continue
                upto = revisions[atlas_id]
                with self.sessions() as session:
                    if isinstance(state.index, PgVectorStore):
                        if not self._serves_active(session, state):
                            self._swap(state)
                        else:
                            state.revision = upto
                        continue
                    changes = change_feed.changes_between(
                        session, atlas_id=atlas_id, after=state.revision, upto=upto
                    )
                    if changes.activated is not None or (
                        not changes.complete and not self._serves_active(session, state)
                    ):
                        self._swap(state)  # loads the frames and revision with the new heads
                        continue
                    if changes.complete:
                        state.index.remove(np.array(changes.removed, np.int64))
                        add_stored_frames(
                            session, atlas_id, state.model, state.index, frame_ids=changes.added
                        )
                    else:  # the log was pruned past our cursor: compare everything
                        upto = change_feed.atlas_revision(session, atlas_id=atlas_id)
                        robot_of = repo.frame_ids_and_robots(session, atlas_id=atlas_id)
                        self._reconcile(session, state, robot_of)
                state.revision, state.dirty = upto, True

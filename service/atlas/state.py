"""The loaded state of each atlas (active heads + FAISS index): loaded on first use, reconciled
with the database, swapped when another model version becomes active, and kept following the
change feed of frames other processes add or remove."""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from sqlalchemy.orm import Session, sessionmaker

from service.atlas import change_feed
from service.atlas import model_versions as models_store
from service.atlas.broken_atlases import BrokenAtlases
from service.config import Settings
from service.errors import AtlasUnavailable, NotFound
from service.index import AtlasIndex
from service.index.builder import add_stored_frames
from service.ml.heads import LoopNetHeads
from service.storage import repository as repo
from service.storage.models import ModelVersion

log = logging.getLogger(__name__)


@dataclass
class LoadedAtlas:
    """What queries of one atlas need in memory: its active heads and its index."""

    atlas_id: int
    model_version: int
    heads: LoopNetHeads
    index: AtlasIndex
    dirty: bool = False
    checked_at: float = field(default_factory=time.monotonic)
    revision: int = 0  # the atlas revision the index reflects (see service/atlas/change_feed.py)


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

    def loaded(self, atlas_id: int, session: Session | None = None) -> LoadedAtlas:
        """The in-memory state of an atlas: loaded on first use, and swapped for the new one
        when another process (a retraining worker, an operator's rollback) has activated another
        model version. Queries in flight keep the state they started with. ``session``: the
        caller's open session, used for the active-version check instead of a new one."""
        state = self.current(atlas_id)
        if state is not None and not self._active_version_changed(state, session):
            return state
        with self.lock(atlas_id):
            current = self.current(atlas_id)
            if current is not None and current is not state:
                return current  # another thread swapped meanwhile
            new = self.broken.load(atlas_id, lambda: self._load(atlas_id))
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
                self.loaded_states[atlas_id] = new
            return new

    def refresh(self, atlas_id: int) -> LoadedAtlas:
        """Serve the database's active version now, without waiting for the next poll."""
        state = self.current(atlas_id)
        if state is not None:
            state.checked_at = float("-inf")
        return self.loaded(atlas_id)

    def _active_version_changed(self, state: LoadedAtlas, session: Session | None) -> bool:
        """Whether the database's active version differs (checked at most once per poll period)."""
        now = time.monotonic()
        if now - state.checked_at < self.settings.model_poll_seconds:
            return False
        state.checked_at = now
        if session is None:
            with self.sessions() as own:
                return self._active_version_changed_in(own, state)
        return self._active_version_changed_in(session, state)

    @staticmethod
    def _active_version_changed_in(session: Session, state: LoadedAtlas) -> bool:
        try:
            active = repo.active_model_version(session, atlas_id=state.atlas_id)
        except NotFound:
            return False  # the atlas is being deleted
        return active.version != state.model_version

    def index_path(self, atlas_id: int, version: int) -> Path:
        return models_store.index_file(self.settings.index_dir, atlas_id, version)

    def _load(self, atlas_id: int) -> LoadedAtlas:
        with self.sessions() as session:
            version: ModelVersion = repo.active_model_version(session, atlas_id=atlas_id)
            heads = models_store.load_heads(version, self.settings.models_dir)
            # the revision first: frames read after it can only be newer, never missing
            revision = change_feed.atlas_revision(session, atlas_id=atlas_id)
            robot_of = repo.frame_ids_and_robots(session, atlas_id=atlas_id)
            path = self.index_path(atlas_id, version.version)
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

    def rebuild_index(self, atlas_id: int) -> int:
        """Re-embed every frame of an atlas from stored features into a fresh index file."""
        with self.lock(atlas_id):
            self.forget(atlas_id)
            with self.sessions() as session:
                version = repo.active_model_version(session, atlas_id=atlas_id)
            self.index_path(atlas_id, version.version).unlink(missing_ok=True)
            state = self.loaded(atlas_id)
            self.save_index(state)
            return state.index.size

    def save_index(self, state: LoadedAtlas) -> None:
        state.index.save(self.index_path(state.atlas_id, state.model_version))
        state.dirty = False

    def flush(self) -> None:
        """Write every changed index to disk (at shutdown; a crash is caught up at start)."""
        with self._loaded_lock:
            states = list(self.loaded_states.values())
        for state in states:
            if state.dirty:
                self.save_index(state)

    def drop_from_index(self, atlas_id: int, frame_ids: list[int], revision: int) -> None:
        with self.lock(atlas_id):
            state = self.current(atlas_id)
            if state is not None and state.revision < revision:
                state.index.remove(np.array(frame_ids, np.int64))
                state.dirty = True

    def follow(self, revisions: dict[int, int]) -> None:
        """Catch the loaded atlases up with the database (``revisions``: atlas id -> current).

        Called by the :class:`~service.atlas.change_feed.ChangeFollower` thread: applies the
        frames other processes added or removed, and forgets atlases deleted elsewhere.
        """
        with self._loaded_lock:
            loaded_ids = list(self.loaded_states)
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

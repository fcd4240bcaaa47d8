"""How every API process keeps its in-memory indexes in step with the shared database.

Each transaction that adds or removes frames logs them in ``atlas_changes`` and, as its last
statement, bumps ``atlases.revision``. That UPDATE takes the atlas row's lock until commit, so
an atlas's revisions are handed out in commit order: once revision ``r`` is visible, every
revision before it is too. (Frame ids are not: PostgreSQL hands out sequence values before
commit, so "catch up from the largest frame id seen" could miss a frame that commits late.)

A :class:`ChangeFollower` thread in each process reads the atlases' revisions every
``LOOPNET_SYNC_SECONDS`` and, for each loaded atlas that moved, applies the logged changes since
the revision its index reflects. A frame committed through any process is therefore searchable
in every other within ``LOOPNET_SYNC_SECONDS`` plus the time to embed it from stored features
(matrix products, no CNN). Deleted atlases are dropped.

Activating a model version (the API, a retraining job, ``loopnet atlas activate``) is logged the
same way, in the transaction that flips ``is_active``: each process's follower loads the newly
active heads and index in its own thread and swaps them in, so request threads never load a
model and an atlas nobody queries swaps too. Log rows older than
``LOOPNET_CHANGE_RETENTION_SECONDS`` are pruned; a process that fell further behind (or whose
cursor predates the oldest row) reconciles the whole index against the database instead.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from datetime import timedelta

from sqlalchemy import delete, select, update
from sqlalchemy.orm import Session, sessionmaker

from service.storage import repository as repo
from service.storage.db import transaction
from service.storage.models import Atlas, AtlasChange, ModelVersion, utcnow

log = logging.getLogger(__name__)

ADD, REMOVE, ACTIVATE = "add", "remove", "activate"


def record(session: Session, *, atlas_id: int, op: str, frame_ids: Iterable[int]) -> int:
    """Log frames added or removed in the caller's transaction; returns the new revision.

    Call it last before the commit: the atlas row stays locked from here until then.
    """
    assert op in (ADD, REMOVE), op
    ids = [int(i) for i in frame_ids]
    revision = _next_revision(session, atlas_id)
    session.add_all(
        AtlasChange(atlas_id=atlas_id, revision=revision, op=op, frame_id=i) for i in ids
    )
    session.flush()
    return revision


def record_activation(session: Session, *, atlas_id: int, version: int) -> int:
    """Log that the caller's transaction made ``version`` the active one; returns the new
    revision. Call it last before the commit, like :func:`record`."""
    revision = _next_revision(session, atlas_id)
    session.add(
        AtlasChange(atlas_id=atlas_id, revision=revision, op=ACTIVATE, model_version=version)
    )
    session.flush()
    return revision


def activate_version(session: Session, *, atlas_id: int, version: int) -> ModelVersion:
    """Make ``version`` the atlas's active one and log it: every process's follower swaps it
    in once the caller's transaction commits."""
    chosen = repo.activate_model_version(session, atlas_id=atlas_id, version=version)
    record_activation(session, atlas_id=atlas_id, version=version)
    return chosen


def _next_revision(session: Session, atlas_id: int) -> int:
    session.flush()
    return int(
        session.execute(
            update(Atlas)
            .where(Atlas.id == atlas_id)
            .values(revision=Atlas.revision + 1)
            .returning(Atlas.revision)
        ).scalar_one()
    )


def revisions(session: Session) -> dict[int, int]:
    """Every atlas's current revision, by atlas id."""
    return {int(i): int(r) for i, r in session.execute(select(Atlas.id, Atlas.revision))}


def atlas_revision(session: Session, *, atlas_id: int) -> int:
    return int(session.scalar(select(Atlas.revision).where(Atlas.id == atlas_id)) or 0)


@dataclass
class Changes:
    """The net effect of an atlas's log between two revisions."""

    complete: bool  # False: the log no longer reaches back that far; reconcile everything
    added: list[int] = field(default_factory=list)
    removed: list[int] = field(default_factory=list)
    activated: int | None = None  # the last model version activated meanwhile, if any


def changes_between(session: Session, *, atlas_id: int, after: int, upto: int) -> Changes:
    """Frames added and removed by revisions ``after + 1 .. upto`` (a removal wins), and the
    last version activated by them."""
    rows = session.execute(
        select(
            AtlasChange.revision, AtlasChange.op, AtlasChange.frame_id, AtlasChange.model_version
        )
        .where(
            AtlasChange.atlas_id == atlas_id,
            AtlasChange.revision > after,
            AtlasChange.revision <= upto,
        )
        .order_by(AtlasChange.revision, AtlasChange.id)
    ).all()
    if {int(r.revision) for r in rows} != set(range(after + 1, upto + 1)):
        return Changes(complete=False)
    removed = {int(r.frame_id) for r in rows if r.op == REMOVE}
    added = [int(r.frame_id) for r in rows if r.op == ADD and int(r.frame_id) not in removed]
    activations = [int(r.model_version) for r in rows if r.op == ACTIVATE]
    return Changes(
        complete=True,
        added=added,
        removed=sorted(removed),
        activated=activations[-1] if activations else None,
    )


def prune(session: Session, *, older_than_seconds: float) -> int:
    """Drop log rows older than the retention; returns how many went."""
    cutoff = utcnow() - timedelta(seconds=older_than_seconds)
    result = session.execute(delete(AtlasChange).where(AtlasChange.created_at < cutoff))
    return int(getattr(result, "rowcount", 0) or 0)


class ChangeFollower:
    """A daemon thread: every ``interval`` seconds, bring this process's indexes up to date.

    ``catch_up(revisions)`` is the service's step (see ``AtlasService.follow``); it receives
    every atlas's current revision.
    """

    PRUNE_EVERY = 60.0

    def __init__(
        self,
        sessions: sessionmaker[Session],
        catch_up: Callable[[dict[int, int]], None],
        *,
        interval: float,
        retention_seconds: float,
    ) -> None:
        self._sessions = sessions
        self._catch_up = catch_up
        self.interval = max(interval, 0.05)
        self.retention_seconds = retention_seconds
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="loopnet-sync", daemon=True)
        self._since_prune = 0.0
        self.last_sync: float | None = None

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=30)

    def step(self) -> None:
        with self._sessions() as session:
            current = revisions(session)
        self._catch_up(current)
        self.last_sync = time.time()  # seen by /metrics as the change feed's lag

    def _run(self) -> None:
        while not self._stop.wait(self.interval):
            try:
                self.step()
                self._since_prune += self.interval
                if self._since_prune >= self.PRUNE_EVERY:
                    self._since_prune = 0.0
                    with transaction(self._sessions) as session:
                        prune(session, older_than_seconds=self.retention_seconds)
            except Exception:  # the database may be briefly unreachable: try again next tick
                log.exception("catching up with the database failed; retrying")

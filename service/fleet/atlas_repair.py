"""Checking and repairing atlases on the database and data directory directly, with the
service stopped: find the atlases that cannot be loaded, delete one, or activate another of
its model versions. No CNN is loaded, so a broken deployment is repaired in seconds.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from service.app import change_feed
from service.app import model_versions as models_store
from service.config import Settings
from service.errors import InvalidInput
from service.fleet.snapshot_restore import ABANDONED_AFTER, RESTORING_PREFIX
from service.index import AtlasIndex
from service.storage import repository as repo
from service.storage.db import transaction
from service.storage.models import Atlas, utcnow

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class AtlasCheck:
    name: str
    model_version: int | None
    problem: str | None  # None: loads


def check_atlases(
    settings: Settings, sessions: sessionmaker[Session], names: list[str] | None = None
) -> list[AtlasCheck]:
    """Whether each atlas's active heads and index file load (a missing index is fine: the
    service rebuilds it from stored features)."""
    out = []
    with sessions() as session:
        atlases = [repo.get_atlas(session, name=n) for n in names] if names else None
        for atlas in atlases or repo.list_atlases(session):
            version: int | None = None
            try:
                active = repo.active_model_version(session, atlas_id=atlas.id)
                version = active.version
                heads = models_store.load_heads(active, settings.models_dir)
                index = models_store.index_file(settings.index_dir, atlas.id, active.version)
                if index.is_file():
                    AtlasIndex.load(index, heads.config.fused_dim)
                problem = None
            except Exception as exc:
                problem = f"{type(exc).__name__}: {exc}"
            out.append(AtlasCheck(atlas.name, version, problem))
    return out


def unfinished_restores(sessions: sessionmaker[Session]) -> list[str]:
    """Hidden atlases of snapshot restores that never finished (a process killed midway);
    ``delete_atlas`` removes them by the name listed."""
    with sessions() as session:
        query = select(Atlas.name).where(Atlas.name.startswith(RESTORING_PREFIX))
        return list(session.scalars(query))


def clean_unfinished_restores(settings: Settings, sessions: sessionmaker[Session]) -> list[str]:
    """At start-up: delete the hidden atlases of restores silent for ``ABANDONED_AFTER`` (their
    process was killed: a running restore marks its atlas alive at every write) and log the
    others (another process may be restoring now; ``loopnet atlas delete NAME`` removes one).
    Returns the names deleted."""
    with sessions() as session:
        hidden = session.execute(
            select(Atlas.name, Atlas.created_at).where(Atlas.name.startswith(RESTORING_PREFIX))
        ).all()
    deleted = []
    for name, alive_at in hidden:
        silent = utcnow() - alive_at
        if silent < ABANDONED_AFTER:
            log.warning(
                "snapshot restore %s was active %s ago: another process may be restoring it; "
                "if not, `loopnet atlas delete %s` removes it (as does a start %s later)",
                name,
                silent,
                name,
                ABANDONED_AFTER,
            )
            continue
        delete_atlas(settings, sessions, name)
        log.warning("deleted %s, left by a snapshot restore that was killed", name)
        deleted.append(name)
    return deleted


def delete_atlas(settings: Settings, sessions: sessionmaker[Session], name: str) -> None:
    """Delete an atlas's rows (they cascade) and its files."""
    with transaction(sessions) as session:
        atlas = repo.get_atlas(session, name=name)
        atlas_id = atlas.id
        session.delete(atlas)
    models_store.remove_atlas_files(settings.index_dir, settings.models_dir, atlas_id)


def activate_version(
    settings: Settings, sessions: sessionmaker[Session], name: str, version: int
) -> None:
    """Make ``version`` the atlas's active one, once its heads are known to load (its index
    is rebuilt from stored features when the service next loads the atlas, if missing). A
    running service swaps it in through the change feed."""
    with transaction(sessions) as session:
        atlas = repo.get_atlas(session, name=name)
        chosen = repo.activate_model_version(session, atlas_id=atlas.id, version=version)
        try:
            models_store.load_heads(chosen, settings.models_dir)
        except Exception as exc:  # nothing is committed
            raise InvalidInput(
                f"model version {version} of atlas '{name}' cannot be loaded either: "
                f"{type(exc).__name__}: {exc}"
            ) from exc
        change_feed.record_activation(session, atlas_id=atlas.id, version=version)

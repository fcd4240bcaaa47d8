"""Checking and repairing atlases on the database and data directory directly, with the
service stopped: find the atlases that cannot be loaded, delete one, or activate another of
its model versions. No CNN is loaded, so a broken deployment is repaired in seconds.
"""

from __future__ import annotations

from dataclasses import dataclass

from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from service.atlas import model_versions as models_store
from service.config import Settings
from service.errors import InvalidInput
from service.fleet.snapshot_restore import RESTORING_PREFIX
from service.index import AtlasIndex
from service.storage import repository as repo
from service.storage.db import transaction
from service.storage.models import Atlas


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
    is rebuilt from stored features when the service next loads the atlas, if missing)."""
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

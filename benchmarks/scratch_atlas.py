"""A throwaway SQLite atlas with one submap, for benchmarks that time database work."""

from __future__ import annotations

import tempfile
from collections.abc import Iterator
from contextlib import contextmanager

from sqlalchemy.orm import Session, sessionmaker

from service.storage import repository as repo
from service.storage.db import make_engine, make_session_factory, transaction, upgrade_database
from service.storage.models import Atlas, Submap


@contextmanager
def scratch_atlas() -> Iterator[tuple[sessionmaker[Session], Atlas, Submap]]:
    """(session factory, atlas, submap) in a migrated database deleted on exit."""
    with tempfile.TemporaryDirectory() as tmp:
        url = f"sqlite:///{tmp}/bench.sqlite3"
        upgrade_database(url)
        engine = make_engine(url)
        sessions = make_session_factory(engine)
        with transaction(sessions) as session:
            atlas = repo.create_atlas(session, name="bench", description="", feature_signature={})
            submap = repo.create_submap(session, atlas=atlas, name="s")
        try:
            yield sessions, atlas, submap
        finally:
            engine.dispose()

"""The data directory and the SQLite files are created readable by their owner only."""

from __future__ import annotations

import stat
from pathlib import Path

from sqlalchemy import text

from service.runtime.queue import Queue
from service.storage.db import make_engine, upgrade_database
from tests.conftest import make_settings


def mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def test_the_data_directory_and_databases_are_owner_only(tmp_path: Path) -> None:
    settings = make_settings(tmp_path / "data")
    upgrade_database(settings.resolved_database_url)  # what creates the file at first start
    engine = make_engine(settings.resolved_database_url)
    with engine.begin() as connection:  # a write: the WAL and shared-memory files appear
        connection.execute(text("CREATE TABLE probe (x INTEGER)"))
        connection.execute(text("INSERT INTO probe VALUES (1)"))
        database = settings.data_dir / "loopnet.sqlite3"
        assert mode(settings.data_dir) == 0o700
        for path in (database, Path(f"{database}-wal"), Path(f"{database}-shm")):
            assert path.exists() and mode(path) & 0o077 == 0, (path, oct(mode(path)))
    engine.dispose()
    Queue(settings).enqueue(1)
    assert mode(settings.queue_path) & 0o077 == 0

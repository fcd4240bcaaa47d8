"""The schema comes from Alembic, matches the models, and SQLite runs in WAL mode."""

from __future__ import annotations

from pathlib import Path

from alembic.autogenerate import compare_metadata
from alembic.migration import MigrationContext
from sqlalchemy import inspect

from service.storage.db import make_engine, upgrade_database
from service.storage.models import Base


def test_upgrade_creates_the_models_schema(tmp_path: Path) -> None:
    url = f"sqlite:///{tmp_path / 'db' / 'loopnet.sqlite3'}"
    upgrade_database(url)
    engine = make_engine(url)
    with engine.connect() as connection:
        assert compare_metadata(MigrationContext.configure(connection), Base.metadata) == []
        tables = set(inspect(connection).get_table_names())
        assert {"atlases", "submaps", "frames", "frame_features", "model_versions"} <= tables
        assert connection.exec_driver_sql("PRAGMA journal_mode").scalar() == "wal"
        assert connection.exec_driver_sql("PRAGMA foreign_keys").scalar() == 1
    engine.dispose()


def test_upgrade_is_idempotent_and_downgrade_works(tmp_path: Path) -> None:
    url = f"sqlite:///{tmp_path / 'loopnet.sqlite3'}"
    upgrade_database(url)
    upgrade_database(url)
    upgrade_database(url, "base")
    engine = make_engine(url)
    with engine.connect() as connection:
        assert "frames" not in inspect(connection).get_table_names()
    engine.dispose()

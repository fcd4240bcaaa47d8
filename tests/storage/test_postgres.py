"""The migrations on PostgreSQL: they build the models' schema, run concurrently, and undo."""

from __future__ import annotations

import subprocess
import sys

from alembic.autogenerate import compare_metadata
from alembic.migration import MigrationContext
from sqlalchemy import inspect

from service.storage.db import make_engine, upgrade_database
from service.storage.models import Base


def test_migrations_match_the_models_on_postgres(postgres_url: str) -> None:
    # API replicas and workers all migrate at start: concurrent upgrades must take turns.
    code = (
        "import sys; from service.storage.db import upgrade_database; upgrade_database(sys.argv[1])"
    )
    processes = [
        subprocess.Popen([sys.executable, "-c", code, postgres_url], stderr=subprocess.PIPE)
        for _ in range(3)
    ]
    for process in processes:
        _, stderr = process.communicate(timeout=120)
        assert process.returncode == 0, stderr.decode()
    engine = make_engine(postgres_url)
    with engine.connect() as connection:
        assert compare_metadata(MigrationContext.configure(connection), Base.metadata) == []
        tables = set(inspect(connection).get_table_names())
        assert {"atlases", "frames", "atlas_changes", "api_keys", "loop_closures"} <= tables
    engine.dispose()
    upgrade_database(postgres_url, "base")
    engine = make_engine(postgres_url)
    with engine.connect() as connection:
        assert "frames" not in inspect(connection).get_table_names()
    engine.dispose()

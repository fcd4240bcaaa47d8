"""Binary ``COPY`` of vector rows into PostgreSQL: the fast path for bulk loads (re-embedding
an atlas, benchmarks). Rows are ``(frame_id int4, robot_id text, submap_id int4, ts float8,
embedding vector|halfvec)`` encoded with numpy (PostgreSQL's binary COPY format; pgvector's
binary form is ``int16 dim, int16 0`` then big-endian float32, or float16 for ``halfvec``).
"""

from __future__ import annotations

import struct

import numpy as np
from sqlalchemy.orm import Session

HEADER = b"PGCOPY\n\xff\r\n\x00" + struct.pack("!ii", 0, 0)
TRAILER = struct.pack("!h", -1)
BATCH = 20_000  # rows encoded at a time


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
    columns = "(frame_id, robot_id, submap_id, ts, embedding)"
    with (
        driver.cursor() as cursor,
        cursor.copy(f"COPY {table} {columns} FROM STDIN WITH (FORMAT binary)") as copy,
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

"""Bounds the service enforces on what callers send, shared by the settings and the code that
checks them."""

from __future__ import annotations

from dataclasses import dataclass

# Ids are INTEGER primary keys: 32-bit on PostgreSQL, so no row has a larger id (a lookup of
# one must be refused before it reaches the database, which raises "integer out of range").
MAX_ROW_ID = 2**31 - 1


@dataclass(frozen=True)
class ArchiveLimits:
    """Largest member and largest sum of members (uncompressed bytes) a restore reads."""

    max_member_bytes: int
    max_total_bytes: int

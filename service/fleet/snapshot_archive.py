"""Reading a snapshot archive without trusting it: only the members export writes, each and
all of them bounded in size before a byte of them is read, and checked against the manifest.

An archive may be plain or compressed tar. Members are regular files with the exact names
export writes (``manifest.json``, the row files, ``features.npz``, ``index.faiss`` and
``models/v<N>.pt``); links, folders, devices, absolute or ``..`` paths, duplicates and any
other name are refused, as is a member whose header declares more bytes than the limit: the
check happens on the header, so a small compressed archive announcing a huge member is
refused without inflating it.
"""

from __future__ import annotations

import hashlib
import json
import re
import tarfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from service.errors import InvalidInput

FORMAT = "loopnet-atlas-snapshot"
FORMAT_VERSION = 1

ROW_MEMBERS = (
    "atlas.json",
    "submaps.jsonl",
    "frames.jsonl",
    "model_versions.jsonl",
    "loop_closures.jsonl",
)
REQUIRED_MEMBERS = frozenset({"manifest.json", *ROW_MEMBERS, "features.npz", "index.faiss"})
WEIGHTS_MEMBER = re.compile(r"^models/v[1-9][0-9]{0,8}\.pt$")


def weights_member(version: int) -> str:
    """The archive member holding a trained version's weights (what ``WEIGHTS_MEMBER`` matches)."""
    return f"models/v{version}.pt"


def _migrations() -> Any:
    """Alembic's view of the migrations (imported here: settings import this module, and
    alembic is slow to import)."""
    from alembic.config import Config
    from alembic.script import ScriptDirectory

    from service.storage.db import MIGRATIONS_DIR

    config = Config()
    config.set_main_option("script_location", str(MIGRATIONS_DIR))
    return ScriptDirectory.from_config(config)


def head_revision() -> str:
    """The schema revision an export writes into its manifest."""
    head = _migrations().get_current_head()
    assert head is not None
    return str(head)


def known_revisions() -> set[str]:
    """The schema revisions this LoopNet knows (a restore refuses a newer one)."""
    return {s.revision for s in _migrations().walk_revisions()}


@dataclass(frozen=True)
class ArchiveLimits:
    """Largest member and largest sum of members (uncompressed bytes) a restore reads."""

    max_member_bytes: int
    max_total_bytes: int


class Counts(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)

    submaps: int = Field(ge=0)
    frames: int = Field(ge=0)
    model_versions: int = Field(ge=1)
    loop_closures: int = Field(ge=0)
    indexed: int = Field(ge=0)


class Manifest(BaseModel):
    """``manifest.json``: what the archive is and the SHA-256 of every other member."""

    model_config = ConfigDict(extra="forbid", strict=True)

    format: str
    format_version: int
    schema_revision: str
    loopnet_version: str
    atlas: str = Field(max_length=64)
    feature_signature: dict[str, Any]
    active_model_version: int = Field(ge=1)
    counts: Counts
    checksums: dict[str, str]


@dataclass(frozen=True)
class Archive:
    manifest: Manifest
    members: dict[str, bytes]  # every member but the manifest, checksums verified


OPTIONAL_MEMBERS = frozenset({"thumbnails.npz"})  # absent from archives written before them


def _allowed(name: str) -> bool:
    return (
        name in REQUIRED_MEMBERS
        or name in OPTIONAL_MEMBERS
        or WEIGHTS_MEMBER.match(name) is not None
    )


def _read_members(path: Path, limits: ArchiveLimits) -> dict[str, bytes]:
    members: dict[str, bytes] = {}
    total = 0
    with tarfile.open(path, "r:*") as archive:
        for member in archive:  # streams: each header is checked before its data is read
            if not _allowed(member.name):
                raise InvalidInput(f"the snapshot holds an unexpected member {member.name!r}")
            if not member.isreg():
                raise InvalidInput(f"the snapshot's {member.name} is not a regular file")
            if member.name in members:
                raise InvalidInput(f"the snapshot holds {member.name} twice")
            if member.size > limits.max_member_bytes:
                raise InvalidInput(
                    f"the snapshot's {member.name} has {member.size} bytes, more than "
                    f"LOOPNET_SNAPSHOT_MAX_MEMBER_BYTES ({limits.max_member_bytes})"
                )
            total += member.size
            if total > limits.max_total_bytes:
                raise InvalidInput(
                    "the snapshot's members add up to more than "
                    f"LOOPNET_SNAPSHOT_MAX_TOTAL_BYTES ({limits.max_total_bytes})"
                )
            stream = archive.extractfile(member)
            if stream is None:
                raise InvalidInput(f"the snapshot's {member.name} cannot be read")
            data = stream.read(member.size)
            if len(data) != member.size:
                raise InvalidInput(f"the snapshot's {member.name} is truncated")
            members[member.name] = data
    return members


def read_archive(path: Path, limits: ArchiveLimits) -> Archive:
    """The manifest and the members of an archive, checked against the manifest."""
    try:
        members = _read_members(path, limits)
    except (tarfile.TarError, OSError, EOFError) as exc:
        raise InvalidInput(f"the upload is not a readable snapshot archive: {exc}") from exc
    missing = REQUIRED_MEMBERS - set(members)
    if "manifest.json" in missing:
        raise InvalidInput("the upload has no manifest.json: it is not a LoopNet atlas snapshot")
    try:
        raw = json.loads(members.pop("manifest.json"))
    except ValueError as exc:
        raise InvalidInput("the snapshot's manifest.json is not JSON") from exc
    if not isinstance(raw, dict) or raw.get("format") != FORMAT:
        raise InvalidInput("the upload is not a LoopNet atlas snapshot")
    if raw.get("format_version") != FORMAT_VERSION:
        raise InvalidInput(
            f"snapshot format version {raw.get('format_version')} is not supported "
            f"(this LoopNet reads version {FORMAT_VERSION})"
        )
    try:
        manifest = Manifest.model_validate(raw)
    except ValidationError as exc:
        raise InvalidInput(
            f"the snapshot's manifest.json is malformed: {first_error(exc)}"
        ) from exc
    if missing:
        raise InvalidInput(f"the snapshot lacks {', '.join(sorted(missing))}")
    if set(manifest.checksums) != set(members):
        raise InvalidInput("the snapshot's members do not match its manifest")
    for name, digest in manifest.checksums.items():
        if hashlib.sha256(members[name]).hexdigest() != digest:
            raise InvalidInput(f"the snapshot's {name} is corrupt (checksum mismatch)")
    return Archive(manifest, members)


def first_error(exc: ValidationError) -> str:
    """The first problem of a validation error, in one line."""
    error = exc.errors()[0]
    where = ".".join(str(part) for part in error["loc"]) or "value"
    return f"{where}: {error['msg']}"

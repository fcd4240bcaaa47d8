"""Reading a snapshot archive without trusting it: only the members export writes, each and
all of them bounded in size before a byte of them is read, streamed to disk, and checked
against the manifest.

An archive may be plain or compressed tar. Members are regular files with the exact names
export writes (``manifest.json``, the row files, ``features.npz``, ``index.faiss`` and
``models/v<N>.pt``); links, folders, devices, absolute or ``..`` paths, duplicates and any
other name are refused, as is a member whose header declares more bytes than the limit: the
check happens on the header, so a small compressed archive announcing a huge member is
refused without inflating it. The members within the limits are copied to files in a folder
the caller owns (a temporary one) through a buffer of :data:`COPY_CHUNK` bytes, hashed on the
way: a small ``.tar.gz`` of zeros costs disk up to the limits, never memory. The row files are then read a line at a time, the arrays
memory-mapped (:mod:`service.fleet.snapshot_features`).
"""

from __future__ import annotations

import hashlib
import json
import lzma
import re
import tarfile
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from service.domain.limits import ArchiveLimits
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
CALIBRATION_MEMBER = re.compile(r"^models/v[1-9][0-9]{0,8}-calibration\.npz$")


def weights_member(version: int) -> str:
    """The archive member holding a trained version's weights (what ``WEIGHTS_MEMBER`` matches)."""
    return f"models/v{version}.pt"


def calibration_member(version: int) -> str:
    """The archive member holding a calibrated version's calibration (``CALIBRATION_MEMBER``)."""
    return f"models/v{version}-calibration.npz"


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


COPY_CHUNK = 256 * 1024  # bytes copied at a time (a gzip-compressed archive's reader holds ~5x)
SMALL_MEMBER_BYTES = 1024 * 1024  # manifest.json and atlas.json: read whole, at most this


@dataclass(frozen=True)
class Archive:
    """The manifest and every other member's file (checksums verified)."""

    manifest: Manifest
    files: dict[str, Path]

    def __contains__(self, name: str) -> bool:
        return name in self.files

    def read(self, name: str) -> bytes:
        """A small member's bytes (the JSON objects; the large ones are read by path)."""
        return _read_small(self.files[name], name)

    def lines(self, name: str) -> Iterator[bytes]:
        """A row member's lines, one at a time."""
        with self.files[name].open("rb") as rows:
            yield from rows


OPTIONAL_MEMBERS = frozenset({"thumbnails.npz"})  # absent from archives written before them


def _allowed(name: str) -> bool:
    return (
        name in REQUIRED_MEMBERS
        or name in OPTIONAL_MEMBERS
        or WEIGHTS_MEMBER.match(name) is not None
        or CALIBRATION_MEMBER.match(name) is not None
    )


def _extract_members(
    path: Path, limits: ArchiveLimits, folder: Path
) -> dict[str, tuple[Path, str]]:
    """Every member copied to a file in ``folder``, each and all of them within ``limits``;
    returns each member's file and SHA-256 (computed on the way) by member name."""
    files: dict[str, tuple[Path, str]] = {}
    total = 0
    with tarfile.open(path, "r:*") as archive:
        for member in archive:  # streams: each header is checked before its data is read
            if not _allowed(member.name):
                raise InvalidInput(f"the snapshot holds an unexpected member {member.name!r}")
            if not member.isreg():
                raise InvalidInput(f"the snapshot's {member.name} is not a regular file")
            if member.name in files:
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
            target = folder / f"member-{len(files):04d}"  # never a name from the archive
            files[member.name] = (target, _copy(stream, target, member.size, member.name))
    return files


def _copy(stream: IO[bytes], target: Path, size: int, name: str) -> str:
    """``size`` bytes of ``stream`` into ``target``, :data:`COPY_CHUNK` at a time; returns
    their SHA-256."""
    digest = hashlib.sha256()
    left = size
    with target.open("wb") as out:
        while left:
            chunk = stream.read(min(left, COPY_CHUNK))
            if not chunk:
                raise InvalidInput(f"the snapshot's {name} is truncated")
            digest.update(chunk)
            out.write(chunk)
            left -= len(chunk)
    return digest.hexdigest()


def _read_small(path: Path, name: str) -> bytes:
    if path.stat().st_size > SMALL_MEMBER_BYTES:
        raise InvalidInput(f"the snapshot's {name} is over {SMALL_MEMBER_BYTES} bytes")
    return path.read_bytes()


def read_archive(path: Path, limits: ArchiveLimits, folder: Path) -> Archive:
    """The manifest and the members of an archive (their files in ``folder``, which the caller
    removes), checked against the manifest."""
    try:
        extracted = _extract_members(path, limits, folder)
    except (tarfile.TarError, OSError, EOFError, zlib.error, lzma.LZMAError) as exc:
        raise InvalidInput(f"the upload is not a readable snapshot archive: {exc}") from exc
    files = {name: file for name, (file, _) in extracted.items()}
    missing = REQUIRED_MEMBERS - set(files)
    if "manifest.json" in missing:
        raise InvalidInput("the upload has no manifest.json: it is not a LoopNet atlas snapshot")
    try:
        raw = json.loads(_read_small(files.pop("manifest.json"), "manifest.json"))
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
    if set(manifest.checksums) != set(files):
        raise InvalidInput("the snapshot's members do not match its manifest")
    for name, digest in manifest.checksums.items():
        if extracted[name][1] != digest:
            raise InvalidInput(f"the snapshot's {name} is corrupt (checksum mismatch)")
    return Archive(manifest, files)


def first_error(exc: ValidationError) -> str:
    """The first problem of a validation error, in one line."""
    error = exc.errors()[0]
    where = ".".join(str(part) for part in error["loc"]) or "value"
    return f"{where}: {error['msg']}"

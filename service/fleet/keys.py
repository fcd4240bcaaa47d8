"""API keys and roles: who may call what, on which atlases.

A key is a random token (``lnk_`` + 256 random bits) shown once at creation; the database keeps
only its SHA-256. A slow password hash (bcrypt, argon2) exists to make guessing low-entropy
passwords expensive; a 256-bit random token cannot be guessed, so a fast hash loses nothing and
keeps the per-request check to one indexed lookup. The first characters (``prefix``) and the id
identify a key for listing and revocation.

Roles nest: ``robot`` (ingest, query, observe) < ``operator`` (jobs, model versions, deleting
frames and submaps) < ``admin`` (keys, atlases, snapshots). A key may be limited to some atlases.

Modes (``LOOPNET_AUTH``): ``auto`` (default) asks for a key once one active key exists, so the
embedded single-user service runs open until its owner creates the first key; ``required``
always asks; ``off`` never does. An open service says so in its log at start.
"""

from __future__ import annotations

import enum
import hashlib
import logging
import secrets
import time
from dataclasses import dataclass

from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from service.config import Settings
from service.errors import Forbidden, InvalidInput, NotFound, Unauthorized
from service.storage.db import transaction
from service.storage.models import ApiKey, utcnow

log = logging.getLogger(__name__)

TOKEN_PREFIX = "lnk_"


class Role(enum.IntEnum):
    robot = 1
    operator = 2
    admin = 3


def parse_role(name: str) -> Role:
    try:
        return Role[name]
    except KeyError:
        raise InvalidInput(
            f"unknown role {name!r}; choose one of {[r.name for r in Role]}"
        ) from None


@dataclass(frozen=True)
class Principal:
    """The caller: a key's role and atlases (empty: every atlas); ``key_id`` None when open."""

    role: Role
    atlases: tuple[str, ...] = ()
    key_id: int | None = None
    name: str = "anonymous"

    def may_use(self, atlas: str) -> bool:
        return not self.atlases or atlas in self.atlases


OPEN = Principal(Role.admin, name="open access (no API keys)")


def hash_token(token: str) -> str:
    return hashlib.sha256(token.encode()).hexdigest()


@dataclass(frozen=True)
class NewKey:
    key: ApiKey
    token: str  # shown once; only its hash is stored


def create_key(session: Session, *, name: str, role: Role, atlases: list[str]) -> NewKey:
    from service.atlas.names import validate_name

    if not name.strip() or len(name) > 128:
        raise InvalidInput("a key's name must have 1-128 characters")
    for atlas in atlases:
        validate_name("atlas", atlas)
    token = TOKEN_PREFIX + secrets.token_urlsafe(32)
    key = ApiKey(
        name=name,
        role=role.name,
        atlases=sorted(set(atlases)),
        prefix=token[:12],
        key_hash=hash_token(token),
    )
    session.add(key)
    session.flush()
    return NewKey(key, token)


def list_keys(session: Session) -> list[ApiKey]:
    return list(session.scalars(select(ApiKey).order_by(ApiKey.id)))


def revoke_key(session: Session, *, key_id: int) -> ApiKey:
    key = session.get(ApiKey, key_id)
    if key is None:
        raise NotFound(f"API key {key_id} does not exist")
    if key.revoked_at is None:
        key.revoked_at = utcnow()
    return key


def issue(sessions: sessionmaker[Session], *, name: str, role: Role, atlases: list[str]) -> NewKey:
    """Create a key in its own transaction (the API and the CLI call this)."""
    with transaction(sessions) as session:
        return create_key(session, name=name, role=role, atlases=atlases)


def listing(sessions: sessionmaker[Session]) -> list[ApiKey]:
    with sessions() as session:
        return list_keys(session)


def revoke(sessions: sessionmaker[Session], *, key_id: int) -> ApiKey:
    with transaction(sessions) as session:
        return revoke_key(session, key_id=key_id)


class Authenticator:
    """Turns a presented token into a :class:`Principal`, or raises 401/403 errors."""

    KEYS_EXIST_TTL = 2.0  # seconds a process trusts "no active key exists" (mode auto)

    def __init__(self, settings: Settings, sessions: sessionmaker[Session]) -> None:
        self.mode = settings.auth
        self.sessions = sessions
        self._keys_exist: tuple[float, bool] | None = None

    def enforced(self) -> bool:
        if self.mode != "auto":
            return self.mode == "required"
        now = time.monotonic()
        if self._keys_exist is None or now - self._keys_exist[0] > self.KEYS_EXIST_TTL:
            with self.sessions() as session:
                exists = session.scalar(select(ApiKey.id).where(ApiKey.revoked_at.is_(None)))
            self._keys_exist = (now, exists is not None)
        return self._keys_exist[1]

    def authenticate(self, token: str | None) -> Principal:
        if not self.enforced():
            return OPEN
        if not token:
            raise Unauthorized("an API key is required: send 'Authorization: Bearer <key>'")
        with self.sessions() as session:
            key = session.scalar(select(ApiKey).where(ApiKey.key_hash == hash_token(token)))
        if key is None or key.revoked_at is not None:
            raise Unauthorized("the API key is unknown or revoked")
        return Principal(Role[key.role], tuple(key.atlases), key.id, key.name)

    def authorize(self, token: str | None, role: Role, atlas: str | None) -> Principal:
        """The caller, if its key has at least ``role`` and may use ``atlas``."""
        principal = self.authenticate(token)
        if principal.role < role:
            raise Forbidden(
                f"this needs the {role.name} role; key '{principal.name}' is {principal.role.name}"
            )
        if atlas is not None and not principal.may_use(atlas):
            raise Forbidden(f"key '{principal.name}' may not use atlas '{atlas}'")
        return principal

    def announce(self) -> None:
        """Say at start whether the API is open."""
        if self.mode == "off":
            log.warning("LOOPNET_AUTH=off: the API is open to anyone who can reach it")
        elif self.mode == "auto" and not self.enforced():
            log.warning(
                "no API keys exist, so the API is open to anyone who can reach it (embedded "
                "single-user mode); `loopnet keys create` turns key checks on, "
                "LOOPNET_AUTH=required makes them mandatory"
            )
        else:
            log.info("API keys required (LOOPNET_AUTH=%s)", self.mode)

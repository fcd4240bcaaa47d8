"""API keys and roles: who may call what, on which atlases.

A key is a random token (``lnk_`` + 256 random bits) shown once at creation; the database keeps
only its SHA-256. A slow password hash (bcrypt, argon2) exists to make guessing low-entropy
passwords expensive; a 256-bit random token cannot be guessed, so a fast hash loses nothing and
keeps the per-request check to one indexed lookup. The first characters (``prefix``) and the id
identify a key for listing and revocation.

Roles nest: ``robot`` (ingest, query, observe) < ``operator`` (jobs, model versions, deleting
frames and submaps) < ``admin`` (keys, atlases, snapshots). A key may be limited to some atlases
(a *scoped* key). A scoped key never reaches beyond its atlases: it creates keys only for a
subset of its own atlases and at most its own role, and sees and revokes only keys whose atlases
all lie within its own. Creating atlases, restoring snapshots, creating unscoped keys and
listing every key take an unscoped admin.

Modes (``LOOPNET_AUTH``): ``auto`` (default) asks for a key once a key has ever been created
(revoked keys count, so revoking the last key never reopens the API), so the embedded
single-user service runs open until its owner creates the first key; ``required`` always asks;
``off`` never does. An open service says so in its log at start, and the switch to keys is
logged. Failed authentications are logged (never the token) and limited per client address.
"""

from __future__ import annotations

import hashlib
import logging
import secrets
import time
from collections.abc import Iterable
from dataclasses import dataclass

from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from service.app.names import validate_name
from service.config import Settings
from service.domain.statuses import Role as Role
from service.errors import Forbidden, InvalidInput, NotFound, TooManyFailures, Unauthorized
from service.fleet.failures import FailureLimiter
from service.storage.db import transaction
from service.storage.models import ApiKey, Atlas, utcnow

log = logging.getLogger(__name__)

TOKEN_PREFIX = "lnk_"


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

    @property
    def scoped(self) -> bool:
        return bool(self.atlases)

    def may_use(self, atlas: str) -> bool:
        return not self.atlases or atlas in self.atlases

    def covers(self, atlases: Iterable[str]) -> bool:
        """Whether a key limited to ``atlases`` (empty: every atlas) lies within this caller's."""
        wanted = set(atlases)
        return not self.atlases or (bool(wanted) and wanted <= set(self.atlases))


OPEN = Principal(Role.admin, name="open access (no API keys)")


def hash_token(token: str) -> str:
    return hashlib.sha256(token.encode()).hexdigest()


@dataclass(frozen=True)
class NewKey:
    key: ApiKey
    token: str  # shown once; only its hash is stored


def create_key(
    session: Session,
    *,
    name: str,
    role: Role,
    atlases: list[str],
    creator: Principal = OPEN,
) -> NewKey:
    """A new key; ``creator`` may only hand out its own atlases and at most its own role."""
    if not name.strip() or len(name) > 128:
        raise InvalidInput("a key's name must have 1-128 characters")
    if role is Role.robot:
        validate_name("robot", name)  # a robot key is its robot: its name is the robot id
    for atlas in atlases:
        validate_name("atlas", atlas)
    if role > creator.role:
        raise Forbidden(
            f"key '{creator.name}' ({creator.role.name}) may not create {role.name} keys"
        )
    if not creator.covers(atlases):
        raise Forbidden(
            f"key '{creator.name}' may only create keys limited to its atlases "
            f"{list(creator.atlases)}"
        )
    known = set(session.scalars(select(Atlas.name).where(Atlas.name.in_(atlases))))
    if missing := sorted(set(atlases) - known):
        raise NotFound(f"atlas(es) {missing} do not exist")
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


def list_keys(session: Session, *, viewer: Principal = OPEN) -> list[ApiKey]:
    """The keys ``viewer`` may see: all for an unscoped one, else those within its atlases."""
    keys = session.scalars(select(ApiKey).order_by(ApiKey.id))
    return [key for key in keys if viewer.covers(key.atlases)]


def revoke_key(session: Session, *, key_id: int, revoker: Principal = OPEN) -> ApiKey:
    key = session.get(ApiKey, key_id)
    if key is None or not revoker.covers(key.atlases):
        raise NotFound(f"API key {key_id} does not exist")
    if key.revoked_at is None:
        key.revoked_at = utcnow()
    return key


class Authenticator:
    """Turns a presented token into a :class:`Principal`, or raises 401/403/429 errors."""

    KEYS_EXIST_TTL = 2.0  # seconds a process trusts "no key was ever created" (mode auto)

    def __init__(self, settings: Settings, sessions: sessionmaker[Session]) -> None:
        self.mode = settings.auth
        self.sessions = sessions
        # (checked at, a key exists); once True it stays True: keys never turn off again
        self._keys_exist: tuple[float, bool] | None = None
        self.failures = FailureLimiter(
            settings.auth_failure_limit, settings.auth_failure_window_seconds
        )

    def enforced(self) -> bool:
        if self.mode != "auto":
            return self.mode == "required"
        now = time.monotonic()
        known = self._keys_exist
        if known is not None and (known[1] or now - known[0] <= self.KEYS_EXIST_TTL):
            return known[1]
        with self.sessions() as session:
            exists = session.scalar(select(ApiKey.id).limit(1)) is not None  # revoked ones too
        if exists and (known is None or not known[1]):
            log.warning(
                "an API key exists: API keys are now required (LOOPNET_AUTH=auto); revoking "
                "keys never reopens the API"
            )
        self._keys_exist = (now, exists)
        return exists

    def authenticate(self, token: str | None, client: str | None = None) -> Principal:
        """The caller behind ``token``; ``client`` (its address) is what failures count against."""
        if not self.enforced():
            return OPEN
        address = client or "unknown"
        if not token:
            self._failed(address, "no API key")
            raise Unauthorized("an API key is required: send 'Authorization: Bearer <key>'")
        with self.sessions() as session:
            key = session.scalar(select(ApiKey).where(ApiKey.key_hash == hash_token(token)))
        if key is None or key.revoked_at is not None:
            self._failed(address, "unknown key" if key is None else f"revoked key {key.id}")
            raise Unauthorized("the API key is unknown or revoked")
        return Principal(Role[key.role], tuple(key.atlases), key.id, key.name)

    def identify(self, token: str | None, client: str | None = None) -> Principal | None:
        """The caller if it shows a valid key (or the API is open); None otherwise, no error."""
        if self.enforced() and not token:
            return None
        try:
            return self.authenticate(token, client)
        except (Unauthorized, TooManyFailures):
            return None

    def _failed(self, address: str, reason: str) -> None:
        """Count a failure; over the limit the address's failures are answered 429 instead of
        401. A valid key always passes: a fleet behind one address (NAT, a proxy) is not locked
        out by one misconfigured robot, and 256-bit keys cannot be guessed anyway."""
        self.failures.check(address)
        self.failures.record(address)
        log.warning("authentication failed from %s: %s", address, reason)

    @staticmethod
    def authorize(
        principal: Principal, role: Role, atlas: str | None, *, unscoped: bool = False
    ) -> Principal:
        """``principal``, if it has at least ``role``, may use ``atlas`` and (where the route
        asks for it) is not limited to some atlases."""
        if principal.role < role:
            raise Forbidden(
                f"this needs the {role.name} role; key '{principal.name}' is {principal.role.name}"
            )
        if atlas is not None and not principal.may_use(atlas):
            raise Forbidden(f"key '{principal.name}' may not use atlas '{atlas}'")
        if unscoped and principal.scoped:
            raise Forbidden(
                f"this needs a key for every atlas; key '{principal.name}' is limited to "
                f"{list(principal.atlases)}"
            )
        return principal

    def announce(self) -> None:
        """Say at start whether the API is open."""
        if self.mode == "off":
            log.warning("LOOPNET_AUTH=off: the API is open to anyone who can reach it")
        elif self.mode == "auto" and not self.enforced():
            log.warning(
                "no API key was ever created, so the API is open to anyone who can reach it "
                "(embedded single-user mode); `loopnet keys create` turns key checks on for "
                "good, LOOPNET_AUTH=required makes them mandatory"
            )
        else:
            log.info("API keys required (LOOPNET_AUTH=%s)", self.mode)


class KeyAdmin:
    """Creating, listing and revoking API keys, each in one transaction of its own (the API
    and the CLI call these)."""

    def __init__(self, sessions: sessionmaker[Session]) -> None:
        self.sessions = sessions

    def issue(
        self,
        *,
        name: str,
        role: Role,
        atlases: list[str],
        creator: Principal = OPEN,
    ) -> NewKey:
        """Create a key in its own transaction (the API and the CLI call this; the CLI, run on the
        server itself, creates as :data:`OPEN`)."""
        with transaction(self.sessions) as session:
            return create_key(session, name=name, role=role, atlases=atlases, creator=creator)

    def listing(self, *, viewer: Principal = OPEN) -> list[ApiKey]:
        with self.sessions() as session:
            return list_keys(session, viewer=viewer)

    def revoke(self, *, key_id: int, revoker: Principal = OPEN) -> ApiKey:
        with transaction(self.sessions) as session:
            return revoke_key(session, key_id=key_id, revoker=revoker)

"""``loopnet keys`` and ``loopnet snapshot``: work on the database and data directory directly
(the same ``LOOPNET_*`` settings as the service), so they run with or without a server."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from sqlalchemy.orm import Session, sessionmaker


def add_parsers(commands: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    keys = commands.add_parser("keys", help="API keys: create, list, revoke")
    key_commands = keys.add_subparsers(dest="keys_command", required=True)
    create = key_commands.add_parser("create", help="create a key and print its token once")
    create.add_argument("--role", required=True, choices=("robot", "operator", "admin"))
    create.add_argument("--name", required=True, help="who or what holds the key")
    create.add_argument(
        "--atlas",
        action="append",
        default=[],
        help="an atlas the key may use (repeat; default: every atlas)",
    )
    create.set_defaults(func=cmd_keys_create)
    listing = key_commands.add_parser("list", help="list keys (never their tokens)")
    listing.set_defaults(func=cmd_keys_list)
    revoke = key_commands.add_parser("revoke", help="revoke a key by id")
    revoke.add_argument("id", type=int)
    revoke.set_defaults(func=cmd_keys_revoke)

    snapshot = commands.add_parser("snapshot", help="export an atlas to one archive, restore it")
    snapshot_commands = snapshot.add_subparsers(dest="snapshot_command", required=True)
    export = snapshot_commands.add_parser("export", help="write an atlas to an archive")
    export.add_argument("atlas")
    export.add_argument("file", type=Path)
    export.set_defaults(func=cmd_snapshot_export)
    restore = snapshot_commands.add_parser("restore", help="restore an archive as a new atlas")
    restore.add_argument("file", type=Path)
    restore.add_argument("--as", dest="name", help="the new atlas's name (default: the archive's)")
    restore.set_defaults(func=cmd_snapshot_restore)


def _sessions() -> tuple[Any, sessionmaker[Session]]:
    from service.config import Settings
    from service.storage.db import make_engine, make_session_factory, upgrade_database

    settings = Settings()
    upgrade_database(settings.resolved_database_url)
    return settings, make_session_factory(make_engine(settings.resolved_database_url))


def _key_row(key: Any) -> dict[str, Any]:
    return {
        "id": key.id,
        "name": key.name,
        "role": key.role,
        "atlases": list(key.atlases),  # as the API shows them: empty means every atlas
        "prefix": key.prefix,
        "created_at": key.created_at.isoformat(),
        "revoked_at": key.revoked_at.isoformat() if key.revoked_at else None,
    }


def _run(action: Any) -> int:
    from service.errors import LoopNetError

    try:
        action()
    except LoopNetError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    return 0


def cmd_keys_create(args: argparse.Namespace) -> int:
    from service.fleet.keys import KeyAdmin, parse_role

    def action() -> None:
        _, sessions = _sessions()
        new = KeyAdmin(sessions).issue(
            name=args.name, role=parse_role(args.role), atlases=args.atlas
        )
        row = _key_row(new.key)
        print(json.dumps({**row, "token": new.token}, indent=2))
        print("store the token now: it is not shown again", file=sys.stderr)

    return _run(action)


def cmd_keys_list(_args: argparse.Namespace) -> int:
    from service.fleet.keys import KeyAdmin

    def action() -> None:
        _, sessions = _sessions()
        for key in KeyAdmin(sessions).listing():
            print(json.dumps(_key_row(key)))

    return _run(action)


def cmd_keys_revoke(args: argparse.Namespace) -> int:
    from service.fleet.keys import KeyAdmin

    def action() -> None:
        _, sessions = _sessions()
        key = KeyAdmin(sessions).revoke(key_id=args.id)
        print(f"key {key.id} ({key.name}) revoked")

    return _run(action)


def cmd_snapshot_export(args: argparse.Namespace) -> int:
    from service.fleet.snapshot_use_case import Snapshots

    def action() -> None:
        manifest = Snapshots(*_sessions()).export(args.atlas, args.file)
        print(f"{args.file}: {json.dumps(manifest['counts'])}")

    return _run(action)


def cmd_snapshot_restore(args: argparse.Namespace) -> int:
    from service.fleet.snapshot_use_case import Snapshots

    def action() -> None:
        name = Snapshots(*_sessions()).restore(args.file, name=args.name)
        print(f"restored {args.file} as atlas '{name}'")

    return _run(action)

"""``loopnet atlas``: check, delete or repair atlases with the service stopped."""

from __future__ import annotations

import argparse
import sys

from service.cli_fleet import _run, _sessions


def add_parsers(commands: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    atlas = commands.add_parser(
        "atlas", help="check, delete or repair atlases (on the database, service stopped)"
    )
    atlas_commands = atlas.add_subparsers(dest="atlas_command", required=True)
    check = atlas_commands.add_parser("check", help="which atlases load and which do not")
    check.add_argument("atlases", nargs="*", help="atlas names (default: all)")
    check.set_defaults(func=cmd_atlas_check)
    delete = atlas_commands.add_parser("delete", help="delete an atlas with its files")
    delete.add_argument("atlas")
    delete.set_defaults(func=cmd_atlas_delete)
    activate = atlas_commands.add_parser(
        "activate", help="make another model version active (e.g. the previous one)"
    )
    activate.add_argument("atlas")
    activate.add_argument("version", type=int)
    activate.set_defaults(func=cmd_atlas_activate)


def cmd_atlas_check(args: argparse.Namespace) -> int:
    from service.fleet.atlas_repair import check_atlases, unfinished_restores

    broken = 0

    def action() -> None:
        nonlocal broken
        settings, sessions = _sessions()
        for check in check_atlases(settings, sessions, args.atlases or None):
            if check.problem is None:
                print(f"{check.name}: ok (model version {check.model_version})")
            else:
                broken += 1
                print(
                    f"{check.name}: BROKEN (model version {check.model_version}): {check.problem}"
                )
        for name in unfinished_restores(sessions):
            broken += 1
            print(f"{name}: UNFINISHED snapshot restore (remove it with `loopnet atlas delete`)")
        if broken:
            print(
                f"{broken} atlas(es) cannot be loaded: `loopnet atlas activate ATLAS VERSION` "
                "serves another version, `loopnet atlas delete ATLAS` removes one",
                file=sys.stderr,
            )

    return _run(action) or (1 if broken else 0)


def cmd_atlas_delete(args: argparse.Namespace) -> int:
    from service.fleet.atlas_repair import delete_atlas

    def action() -> None:
        settings, sessions = _sessions()
        delete_atlas(settings, sessions, args.atlas)
        print(f"atlas '{args.atlas}' deleted")

    return _run(action)


def cmd_atlas_activate(args: argparse.Namespace) -> int:
    from service.fleet.atlas_repair import activate_version

    def action() -> None:
        settings, sessions = _sessions()
        activate_version(settings, sessions, args.atlas, args.version)
        print(f"atlas '{args.atlas}' now serves model version {args.version}")

    return _run(action)

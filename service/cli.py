"""The ``loopnet`` command: serve, worker, ingest, query, reindex, eval, keys, snapshot, db, weights.

``ingest`` and ``query`` talk to a running service over HTTP (the same path robots use), so the
server's in-memory index always sees what they add. ``reindex`` and ``db upgrade`` work on the
database directly.
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from service.cli_atlas import add_parsers as add_atlas_parsers
from service.cli_eval import add_parsers as add_eval_parsers
from service.cli_fleet import add_parsers as add_fleet_parsers

if TYPE_CHECKING:
    from service.client import LoopNetClient, LoopNetError

DEFAULT_URL = "http://127.0.0.1:8000"


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    args.argv = None if argv is None else list(argv)
    logging.basicConfig(
        level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s"
    )
    # one INFO line per HTTP request would break the progress bars of ingest and eval
    for chatty in ("httpx", "httpcore"):
        logging.getLogger(chatty).setLevel(logging.WARNING)
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except Exception as exc:
        message = one_line_error(exc, getattr(args, "url", None))
        if message is None:
            raise
        print(f"error: {message}", file=sys.stderr)
        return 1


def one_line_error(exc: Exception, url: str | None) -> str | None:
    """What the user can act on, for the errors a command line meets (None: a real bug)."""
    if isinstance(exc, FileNotFoundError | IsADirectoryError | PermissionError):
        return f"{exc.strerror}: {exc.filename}"
    if "httpx" in sys.modules:
        import httpx

        if isinstance(exc, httpx.ConnectError):
            return f"cannot reach the service at {url} (is `loopnet serve` running?): {exc}"
        if isinstance(exc, httpx.TransportError):
            return f"the service at {url} did not answer properly: {exc}"
    from service.errors import LoopNetError

    if isinstance(exc, LoopNetError):
        return str(exc)
    return None


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="loopnet", description=__doc__)
    commands = parser.add_subparsers(dest="command", required=True)

    serve = commands.add_parser("serve", help="run the HTTP service (migrates the database first)")
    serve.add_argument("--host", help="bind address (default: LOOPNET_HOST or 127.0.0.1)")
    serve.add_argument("--port", type=int, help="port (default: LOOPNET_PORT or 8000)")
    serve.set_defaults(func=cmd_serve)

    worker = commands.add_parser("worker", help="run the job queue's worker (retraining jobs)")
    worker.add_argument("--threads", type=int, default=1, help="jobs run at once (default 1)")
    worker.set_defaults(func=cmd_worker)

    ingest = commands.add_parser("ingest", help="add a folder of images to a submap")
    ingest.add_argument("folder", type=Path)
    ingest.add_argument("--atlas", required=True)
    ingest.add_argument("--submap", required=True)
    ingest.add_argument("--robot", default="cli", help="robot id recorded with each frame")
    ingest.add_argument("--create", action="store_true", help="create the atlas/submap if missing")
    ingest.add_argument("--url", default=DEFAULT_URL, help=f"service address ({DEFAULT_URL})")
    ingest.set_defaults(func=cmd_ingest)

    query = commands.add_parser("query", help="find the place an image revisits")
    query.add_argument("image", type=Path)
    query.add_argument("--atlas", required=True)
    query.add_argument("-k", type=int, default=5)
    query.add_argument("--robot", help="the robot asking (its recent frames never match)")
    query.add_argument("--url", default=DEFAULT_URL)
    query.set_defaults(func=cmd_query)

    reindex = commands.add_parser(
        "reindex", help="rebuild atlas indexes from the database's stored features (no CNN pass)"
    )
    reindex.add_argument("atlases", nargs="*", help="atlas names (default: all)")
    reindex.set_defaults(func=cmd_reindex)

    add_eval_parsers(commands)
    add_fleet_parsers(commands)
    add_atlas_parsers(commands)

    seed = commands.add_parser("weights", help="pretrained weights in the torch hub cache")
    seed_commands = seed.add_subparsers(dest="weights_command", required=True)
    seed_cmd = seed_commands.add_parser(
        "seed", help="link a folder of verified weights files into $TORCH_HOME/hub/checkpoints"
    )
    seed_cmd.add_argument("folder", type=Path)
    seed_cmd.set_defaults(func=cmd_weights_seed)

    db = commands.add_parser("db", help="database maintenance")
    db_commands = db.add_subparsers(dest="db_command", required=True)
    upgrade = db_commands.add_parser("upgrade", help="apply migrations (alembic upgrade head)")
    upgrade.add_argument("--revision", default="head")
    upgrade.set_defaults(func=cmd_db_upgrade)
    return parser


def cmd_serve(args: argparse.Namespace) -> int:
    from service.api.app import create_app
    from service.api.serving import serve
    from service.config import Settings

    # --host/--port override LOOPNET_HOST/PORT (the host named is one the API answers to)
    listen = {name: value for name, value in (("host", args.host), ("port", args.port)) if value}
    settings = Settings(**listen)  # type: ignore[arg-type]
    serve(create_app(settings), settings, settings.host, settings.port)
    return 0


def cmd_worker(args: argparse.Namespace) -> int:
    from service.config import Settings
    from service.runtime.worker import run_worker

    run_worker(Settings(), workers=args.threads)
    return 0


def _client(url: str) -> LoopNetClient:
    from service.client import LoopNetClient

    return LoopNetClient(url)  # the key from LOOPNET_API_KEY, needed once the service asks


def _fail(error: LoopNetError) -> int:
    detail = error.detail
    if error.status == 401:
        detail = f"{detail} (set LOOPNET_API_KEY to a key; `loopnet keys create` makes one)"
    print(f"error {error.status}: {detail}", file=sys.stderr)
    return 1


def cmd_ingest(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from service.client import LoopNetError
    from service.evaluation.datasets import list_images

    if not args.folder.is_dir():
        print(f"error: {args.folder} is not a folder", file=sys.stderr)
        return 2
    images = list_images(args.folder)
    if not images:
        print(f"error: no JPEG/PNG/WebP images in {args.folder}", file=sys.stderr)
        return 2
    with _client(args.url) as client:
        try:
            if args.create:
                _create_missing(client, args.atlas, args.submap)
        except LoopNetError as error:
            return _fail(error)
        for image in tqdm(images, desc=f"ingest {args.atlas}/{args.submap}", unit="frame"):
            try:
                client.add_frame(args.atlas, image, submap=args.submap, robot_id=args.robot)
            except LoopNetError as error:
                print(f"{image}: ", end="", file=sys.stderr)
                return _fail(error)
    print(f"ingested {len(images)} frames into {args.atlas}/{args.submap}")
    return 0


def _create_missing(client: LoopNetClient, atlas: str, submap: str) -> None:
    from service.client import LoopNetError

    for create in (lambda: client.create_atlas(atlas), lambda: client.create_submap(atlas, submap)):
        try:
            create()
        except LoopNetError as error:
            if error.status != 409:  # 409: it exists already
                raise


def cmd_query(args: argparse.Namespace) -> int:
    from service.client import LoopNetError

    with _client(args.url) as client:
        try:
            answer = client.query(args.atlas, args.image, k=args.k, robot_id=args.robot)
        except LoopNetError as error:
            return _fail(error)
    print(answer.model_dump_json(indent=2))
    return 0


def cmd_reindex(args: argparse.Namespace) -> int:
    from service.config import Settings
    from service.runtime import Runtime
    from service.storage import repository as repo

    runtime = Runtime(Settings())
    runtime.start(background=False)
    service = runtime.service
    with service.sessions() as session:
        names = args.atlases or [a.name for a in repo.list_atlases(session)]
    for name in names:
        print(f"{name}: {service.rebuild_index(name)} frames indexed")
    runtime.stop()
    return 0


def cmd_weights_seed(args: argparse.Namespace) -> int:
    from service.ml.weights import seed_cache

    for path in seed_cache(args.folder):
        print(path)
    return 0


def cmd_db_upgrade(args: argparse.Namespace) -> int:
    from service.config import Settings
    from service.storage.db import upgrade_database

    settings = Settings()
    upgrade_database(settings.resolved_database_url, args.revision)
    print(f"database at {settings.resolved_database_url} is at revision {args.revision}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

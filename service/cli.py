"""The ``loopnet`` command: serve, worker, ingest, query, reindex, eval, keys, snapshot, db, weights.

``ingest`` and ``query`` talk to a running service over HTTP (the same path robots use), so the
server's in-memory index always sees what they add. ``reindex`` and ``db upgrade`` work on the
database directly.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
from collections.abc import Sequence
from pathlib import Path

from service.cli_atlas import add_parsers as add_atlas_parsers
from service.cli_fleet import add_parsers as add_fleet_parsers

DEFAULT_URL = "http://127.0.0.1:8000"


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    args.argv = None if argv is None else list(argv)
    logging.basicConfig(
        level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s"
    )
    return int(args.func(args) or 0)


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

    add_eval_parser(commands)
    add_eval_online_parser(commands)
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


def _csv_list(kind: type, text: str) -> tuple:  # type: ignore[type-arg]
    return tuple(kind(v) for v in text.split(",") if v.strip())


def add_eval_parser(commands: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    from service.evaluation.datasets import LAYOUTS

    ev = commands.add_parser(
        "eval",
        help="evaluate LoopNet, its ablations and classical baselines on a dataset folder",
        description=(
            "Runs every method on one dataset through the service's own code path (temporary "
            "atlas) and writes report.json, report.md and PNG plots. Layouts: traversals (two "
            "frame-aligned folders), vpr-bench (query/, ref/, ground_truth_new.npy), loopdb "
            "(datastream_1/2/data_descriptor.csv), csv (dataset.csv), places (<place>/<image>)."
        ),
    )
    ev.add_argument("dataset", type=Path, help="the dataset folder")
    ev.add_argument("--out", type=Path, required=True, help="report folder (created)")
    ev.add_argument("--layout", default="auto", choices=("auto", *LAYOUTS))
    ev.add_argument("--tolerance", type=int, help="frame tolerance (default 1)")
    ev.add_argument("--distance", type=float, default=25.0, help="metres, for CSV positions")
    ev.add_argument("--reference", help="traversals: the map's folder")
    ev.add_argument("--query", help="traversals: the queries' folder")
    ev.add_argument("--submap-size", type=int, default=5, help="consecutive frames per submap")
    ev.add_argument("--preset", default="default", help="model preset (default, fast, paper)")
    ev.add_argument("--long-side", type=int, help="local extractors' working long side")
    ev.add_argument("--max-keypoints", type=int, help="keypoints per frame")
    ev.add_argument("--backbone", help="global backbone (mobilenetv2, resnet18)")
    ev.add_argument("--extractors", default="disk,xfeat", help="comma-separated, first = LoopNet")
    ev.add_argument("--alphas", default="0,0.3,0.5,0.7,1", help="ablation fusion weights")
    ev.add_argument("--baselines", default="bow-orb,seqslam-sad", help="comma-separated, or ''")
    ev.add_argument("--limit", type=int, help="only the first N reference frames (a quick slice)")
    ev.add_argument("--cache-dir", type=Path, help="feature cache (default OUT/cache)")
    ev.add_argument("--examples", type=int, default=6, help="example queries in the strip")
    ev.add_argument(
        "--retrain-shots",
        default="1,3,5",
        help="K values (shots per submap) of the retrained rows, comma-separated; '' for none",
    )
    ev.add_argument(
        "--retrain-protocols",
        default="map,revisit",
        help="map (reference shots only) and/or revisit (the paper's: also query-condition shots)",
    )
    ev.add_argument(
        "--verify",
        default="",
        help="comma-separated matchers (mnn, lightglue): add geometric-verification rows",
    )
    ev.add_argument("--verify-top", type=int, default=5, help="candidates verified per query")
    ev.add_argument("--query-stride", type=int, default=1, help="keep every n-th query only")
    ev.add_argument(
        "--sequence",
        default="",
        help="comma-separated sequence lengths L: add <method>+seqL rows and full SeqSLAM",
    )
    ev.add_argument(
        "--sequence-contrast",
        type=int,
        default=0,
        help="sequence rows: local contrast window in frames (0: whole-map z-scores)",
    )
    ev.add_argument(
        "--sequence-seed-frames",
        type=int,
        default=1,
        help="sequence rows: newest query frames whose best matches propose candidates "
        "(1: the service's; 0: all)",
    )
    ev.set_defaults(func=cmd_eval)


def add_eval_online_parser(commands: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    on = commands.add_parser(
        "eval-online",
        help="replay one robot's trajectory in order and score its loop closures",
        description=(
            "Each frame asks about every earlier frame but the robot's own recent ones, then "
            "joins the map. Trajectory: two frame-aligned traversals driven one after the "
            "other (DATASET), or --images with a FAB-MAP-style --ground-truth matrix."
        ),
    )
    on.add_argument("dataset", type=Path, nargs="?", help="a traversals dataset folder")
    on.add_argument("--images", type=Path, help="one trajectory's image folder")
    on.add_argument("--ground-truth", type=Path, help="loop-closure matrix (.mat/.npy/.csv)")
    on.add_argument("--variable", help="the matrix's variable in a .mat file")
    on.add_argument("--tolerance", type=int, help="traversals: frame tolerance (default 1)")
    on.add_argument("--out", type=Path, required=True, help="report folder (created)")
    on.add_argument("--preset", default="default")
    on.add_argument("--long-side", type=int)
    on.add_argument("--extractors", default="xfeat", help="comma-separated local extractors")
    on.add_argument("--alphas", default="0.7,0", help="fusion weights (0 = global only)")
    on.add_argument("--sequence", default="1,5,10", help="sequence lengths (1 = single frame)")
    on.add_argument("--exclude-recent", type=int, default=20)
    on.add_argument("--consistency", type=int, default=3, help="agreeing observations (k)")
    on.add_argument("--cache-dir", type=Path, help="feature cache (loopnet eval's)")
    on.set_defaults(func=cmd_eval_online)


def cmd_eval_online(args: argparse.Namespace) -> int:
    from service.evaluation.datasets import load_dataset
    from service.evaluation.loop_ground_truth import (
        trajectory_from_matrix,
        trajectory_from_traversals,
    )
    from service.evaluation.online import OnlineConfig, run_online
    from service.evaluation.runner import command_line

    if args.images is not None and args.ground_truth is not None:
        trajectory = trajectory_from_matrix(args.images, args.ground_truth, args.variable)
    elif args.dataset is not None:
        dataset = load_dataset(args.dataset, layout="traversals", tolerance=args.tolerance)
        trajectory = trajectory_from_traversals(dataset)
    else:
        raise SystemExit("give a traversals DATASET, or --images and --ground-truth")
    methods: list[tuple[str, str, float]] = []
    for extractor in _csv_list(str, args.extractors):
        for alpha in _csv_list(float, args.alphas):
            if alpha == 0.0 and any(m[2] == 0.0 for m in methods):
                continue  # the global branch is the same for every extractor
            name = "global-only" if alpha == 0.0 else f"loopnet-{extractor}-alpha{alpha:g}"
            methods.append((name, extractor, alpha))
    config = OnlineConfig(
        trajectory=trajectory,
        output=args.out,
        methods=tuple(methods),
        lengths=_csv_list(int, args.sequence),
        preset=args.preset,
        long_side=args.long_side,
        cache_dir=args.cache_dir,
        exclude_recent=args.exclude_recent,
        consistency=args.consistency,
        command=command_line(sys.argv[1:] if args.argv is None else args.argv),
    )
    run_online(config)
    print((args.out / "online.md").read_text())
    return 0


def cmd_eval(args: argparse.Namespace) -> int:
    from service.evaluation.runner import EvalConfig, command_line, run_evaluation

    config = EvalConfig(
        dataset=args.dataset,
        output=args.out,
        layout=args.layout,
        tolerance=args.tolerance,
        distance=args.distance,
        reference=args.reference,
        query=args.query,
        submap_size=args.submap_size,
        preset=args.preset,
        long_side=args.long_side,
        max_keypoints=args.max_keypoints,
        backbone=args.backbone,
        extractors=_csv_list(str, args.extractors),
        alphas=_csv_list(float, args.alphas),
        baselines=_csv_list(str, args.baselines),
        limit=args.limit,
        cache_dir=args.cache_dir,
        examples=args.examples,
        retrain_shots=_csv_list(int, args.retrain_shots),
        retrain_protocols=_csv_list(str, args.retrain_protocols),
        verify=_csv_list(str, args.verify),
        verify_top=args.verify_top,
        query_stride=args.query_stride,
        sequence=_csv_list(int, args.sequence),
        sequence_contrast=args.sequence_contrast,
        sequence_seed_frames=args.sequence_seed_frames,
        command=command_line(sys.argv[1:] if args.argv is None else args.argv),
    )
    result = run_evaluation(config)
    print((args.out / "report.md").read_text())
    print(f"report written to {args.out}/report.json, report.md and PNG plots")
    return 0 if result.methods else 1


def cmd_serve(args: argparse.Namespace) -> int:
    import uvicorn

    from service.api.app import create_app
    from service.config import Settings

    settings = Settings()
    uvicorn.run(
        create_app(settings),
        host=args.host or settings.host,
        port=args.port or settings.port,
        log_level="info",
    )
    return 0


def cmd_worker(args: argparse.Namespace) -> int:
    from service.config import Settings
    from service.jobs.worker import run_worker

    run_worker(Settings(), workers=args.threads)
    return 0


def _client(url: str):  # type: ignore[no-untyped-def]
    import httpx

    key = os.environ.get("LOOPNET_API_KEY")  # needed once the service asks for keys
    headers = {"Authorization": f"Bearer {key}"} if key else {}
    return httpx.Client(base_url=url.rstrip("/") + "/v1", timeout=300, headers=headers)


def _fail(response) -> int:  # type: ignore[no-untyped-def]
    try:
        detail = response.json().get("detail", response.text)
    except ValueError:
        detail = response.text
    print(f"error {response.status_code}: {detail}", file=sys.stderr)
    return 1


def cmd_ingest(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from service.evaluation.datasets import list_images

    if not args.folder.is_dir():
        print(f"error: {args.folder} is not a folder", file=sys.stderr)
        return 2
    images = list_images(args.folder)
    if not images:
        print(f"error: no JPEG/PNG/WebP images in {args.folder}", file=sys.stderr)
        return 2
    with _client(args.url) as client:
        if args.create:
            for path, body in (
                ("/atlases", {"name": args.atlas}),
                (f"/atlases/{args.atlas}/submaps", {"name": args.submap}),
            ):
                response = client.post(path, json=body)
                if response.status_code not in (201, 409):
                    return _fail(response)
        for image in tqdm(images, desc=f"ingest {args.atlas}/{args.submap}", unit="frame"):
            response = client.post(
                f"/atlases/{args.atlas}/frames",
                data={"submap": args.submap, "robot_id": args.robot},
                files={"image": (image.name, image.read_bytes())},
            )
            if response.status_code != 201:
                print(f"{image}: ", end="", file=sys.stderr)
                return _fail(response)
    print(f"ingested {len(images)} frames into {args.atlas}/{args.submap}")
    return 0


def cmd_query(args: argparse.Namespace) -> int:
    data: dict[str, str] = {"k": str(args.k)}
    if args.robot:
        data["robot_id"] = args.robot
    with _client(args.url) as client:
        response = client.post(
            f"/atlases/{args.atlas}/query",
            data=data,
            files={"image": (args.image.name, args.image.read_bytes())},
        )
    if response.status_code != 200:
        return _fail(response)
    print(json.dumps(response.json(), indent=2))
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

"""``loopnet eval`` and ``loopnet eval-online``: run every method on one dataset folder (or
replay one trajectory) and write the report (the evaluation modules are imported only when
the command runs)."""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path
from typing import Any


def _named_values(pairs: list[str]) -> dict[str, Any]:
    """``NAME=VALUE`` strings as a dict, each value read as JSON where it parses (numbers,
    booleans, lists) and as text otherwise; the retraining job's schema validates them."""
    values: dict[str, Any] = {}
    for pair in pairs:
        name, sep, text = pair.partition("=")
        if not sep or not name:
            raise SystemExit(f"error: expected NAME=VALUE, got {pair!r}")
        try:
            values[name] = json.loads(text)
        except json.JSONDecodeError:
            values[name] = text
    return values


def _csv_list(kind: type, text: str) -> tuple:  # type: ignore[type-arg]
    return tuple(kind(v) for v in text.split(",") if v.strip())


def add_parsers(commands: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    from service.evaluation.datasets import LAYOUTS
    from service.jobs.adaptation_config import ADAPT_METHODS, DEFAULT_METHOD

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
    ev.add_argument(
        "--precision",
        default="fp32",
        choices=("auto", "fp32", "bf16"),
        help="CNN arithmetic; the cache does not record it: one --cache-dir per precision",
    )
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
        "--retrain-param",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="a retraining job parameter other than its default (repeatable), e.g. "
        "positive_window=0",
    )
    ev.add_argument(
        "--adapt-shots",
        default="",
        help="K values of the adapted rows (an adapt job's learned whitening from K revisit "
        "pairs per submap, left out of the test queries), comma-separated; '' for none",
    )
    ev.add_argument(
        "--adapt-pairs-from-observe",
        default="",
        metavar="K[,K...]",
        help="K values of the pairs protocol: K query-condition frames per submap observed "
        "through the service (as served), the pairs observe verified given to a real adapt job, "
        "the other queries answered as served before and after; '' for none",
    )
    ev.add_argument(
        "--adapt-pairs-labelled",
        default="",
        metavar="K[,K...]",
        help="the same with the K shots per submap stored and labelled as pairs with their "
        "partner references (the revisit protocol as served); '' for none",
    )
    ev.add_argument(
        "--adapt-pairs-from-stream",
        default="",
        metavar="P[,P...]",
        help="the pairs protocol on a drive: the first P %% of the queries observed in order by "
        "one robot (its sequence on), every closure observe kept (verified or a sequence's "
        "loop) given to a real adapt job, the rest of the queries answered as served before and "
        "after; '' for none",
    )
    ev.add_argument(
        "--adapt-shrinkage",
        type=float,
        help="the adapt job's shrinkage of the pairs' covariance (default: Ledoit-Wolf's)",
    )
    ev.add_argument(
        "--adapt-method",
        default=DEFAULT_METHOD,
        choices=ADAPT_METHODS,
        help="the adapt job's method: the learned whitening, then a listwise loss over the "
        "pairs (whitening+pairs), or the loss alone (pairs)",
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
        default=0,
        help="sequence rows: newest query frames whose best matches propose candidates "
        "(0: all, the service's default; 1: the newest only)",
    )
    ev.add_argument(
        "--no-served",
        dest="served",
        action="store_false",
        help="skip the <method>-served rows (queries answered with verification and the loop "
        "decision at the service's defaults)",
    )
    ev.set_defaults(func=cmd_eval)
    add_online_parser(commands)


def add_online_parser(commands: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
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
    on.add_argument(
        "--served",
        default="10",
        help="sequence lengths of the loopnet-<extractor>-served rows: the service's defaults "
        "(verification, loop_probability, calibration at its milestones during the replay); "
        "'' for none",
    )
    on.add_argument(
        "--served-adapt-after",
        default="",
        metavar="N[,N...]",
        help="each served row again with automatic adaptation after every N revisit pairs the "
        "replay's observations kept instead of the service's default (LOOPNET_ADAPT_AFTER_PAIRS, "
        "500; 0: off, the row without adaptation; the jobs run between frames); '' for none",
    )
    on.add_argument(
        "--limit", type=int, help="DATASET: only the first N map frames and their revisits"
    )
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
        if args.limit:
            dataset = dataset.head(args.limit)
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
        served_lengths=_csv_list(int, args.served),
        served_adapt_after=_csv_list(int, args.served_adapt_after),
        command=command_line(sys.argv[1:] if args.argv is None else args.argv),
    )
    run_online(config)
    print((args.out / "online.md").read_text())
    return 0


def cmd_eval(args: argparse.Namespace) -> int:
    # their INFO lines (faiss's loader, each temporary atlas's migrations) would break the bars
    for chatty in ("faiss", "alembic"):
        logging.getLogger(chatty).setLevel(logging.WARNING)
    from service.config import Settings
    from service.evaluation.datasets import DatasetError
    from service.evaluation.runner import EvalConfig, command_line, run_evaluation
    from service.ml.precision import resolve_precision

    try:
        resolve_precision(args.precision)  # a forced bf16 the CPU lacks: say so before any work
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    from service.ml.weights import set_offline

    settings = Settings()
    set_offline(settings.offline)
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
        retrain_params=_named_values(args.retrain_param),
        adapt_shots=_csv_list(int, args.adapt_shots),
        adapt_shrinkage=args.adapt_shrinkage,
        adapt_method=args.adapt_method,
        adapt_observe_shots=_csv_list(int, args.adapt_pairs_from_observe),
        adapt_labelled_shots=_csv_list(int, args.adapt_pairs_labelled),
        adapt_stream_percents=_csv_list(int, args.adapt_pairs_from_stream),
        verify=_csv_list(str, args.verify),
        verify_top=args.verify_top,
        ransac_backend=settings.ransac_backend,
        query_stride=args.query_stride,
        sequence=_csv_list(int, args.sequence),
        sequence_contrast=args.sequence_contrast,
        sequence_seed_frames=args.sequence_seed_frames,
        served=args.served,
        precision=args.precision,
        command=command_line(sys.argv[1:] if args.argv is None else args.argv),
    )
    try:
        result = run_evaluation(config)
    except DatasetError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print((args.out / "report.md").read_text())
    print(f"report written to {args.out}/report.json, report.md and PNG plots")
    return 0 if result.methods else 1

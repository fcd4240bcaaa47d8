"""``loopnet eval``: run every method on one dataset folder and write the report (the
evaluation modules are imported only when the command runs)."""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path


def _csv_list(kind: type, text: str) -> tuple:  # type: ignore[type-arg]
    return tuple(kind(v) for v in text.split(",") if v.strip())


def add_parsers(commands: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
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
        "--verify",
        default="",
        help="comma-separated matchers (mnn, lightglue): add geometric-verification rows",
    )
    ev.add_argument("--verify-top", type=int, default=5, help="candidates verified per query")
    ev.add_argument("--query-stride", type=int, default=1, help="keep every n-th query only")
    ev.set_defaults(func=cmd_eval)


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

    set_offline(Settings().offline)
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

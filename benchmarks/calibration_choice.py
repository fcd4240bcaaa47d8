"""How the calibration's defaults were chosen: variants fitted on a development set's stored
references, scored on the first half of its queries (the choice) and reported on the second
half (the check), from the feature cache a ``loopnet eval --cache-dir DIR`` run left.

    python benchmarks/calibration_choice.py ../shared/data/gardenspoint_cohog200 \\
        --cache-dir /work/evalcache/gp --extractor disk --tolerance 2 \\
        --shrinkage 1,4 --words auto,64 --alpha 0.5,0.7 --pooling gem-layout,gem

Each variant is fitted exactly as the calibration job fits (:meth:`Calibration.fit`, on the
references only, no labels); queries are embedded by it and ranked by exact cosine; R@1 is
counted with the dataset's own ground truth, on queries in dataset (route) order split in
halves. ``--pooling gem`` keeps only the GeM part of a ``gem-layout`` vector R (its first
``C`` values, re-normalised), so both poolings come from one cache. Nothing here is a
service path: it is the record of a choice, rerunnable on any dataset the harness reads.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from service.evaluation.datasets import load_dataset
from service.evaluation.feature_cache import CachedFeatures, LocalFeatureCache
from service.ml.aggregation import l2_normalize
from service.ml.calibration import Calibration, CalibrationConfig, CalibrationInputs
from service.ml.whitening import WhiteningConfig


@dataclass(frozen=True)
class Variant:
    pooling: str
    shrinkage: float
    words: int | None
    alpha: float


@dataclass(frozen=True)
class Outcome:
    variant: Variant
    dev: float  # R@1 on the first half of the queries (where a choice may look)
    held: float  # R@1 on the second half
    all: float


def _cache_files(cache_dir: Path, dataset_name: str, extractor: str) -> Path:
    found = sorted(
        p
        for p in cache_dir.glob(f"{dataset_name}-{extractor}*.npz")
        if not p.name.endswith("-local.npz") and ".tmp" not in p.name
    )
    if len(found) != 1:
        sys.exit(f"expected one {extractor} vector cache of {dataset_name} in {cache_dir}: {found}")
    return found[0]


def _gem_part(vectors: np.ndarray, gem_dim: int) -> np.ndarray:
    return l2_normalize(vectors[:, :gem_dim])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("dataset", type=Path)
    parser.add_argument("--cache-dir", type=Path, required=True)
    parser.add_argument("--extractor", default="disk")
    parser.add_argument("--tolerance", type=int, default=1)
    parser.add_argument("--shrinkage", default="1")
    parser.add_argument("--words", default="auto", help="comma-separated; auto = 16384 / d")
    parser.add_argument("--alpha", default="0.5")
    parser.add_argument("--pooling", default="gem-layout", help="gem-layout and/or gem")
    parser.add_argument("--gem-dim", type=int, default=1280, help="C of the GeM part of R")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()

    dataset = load_dataset(args.dataset, tolerance=args.tolerance)
    vector_path = _cache_files(args.cache_dir, dataset.name, args.extractor)
    cached = CachedFeatures.load(vector_path)
    if cached is None:
        sys.exit(f"{vector_path} is not a feature cache of this format")
    local = LocalFeatureCache.for_vectors(vector_path).load()
    rows = cached.rows()

    def frames(paths: list[Path]) -> tuple[list[np.ndarray], list[np.ndarray], np.ndarray]:
        missing = [p for p in paths if p.resolve() not in rows or p.resolve() not in local]
        if missing:
            sys.exit(f"{len(missing)} frames are not in the cache (first: {missing[0]})")
        feats = [local[p.resolve()] for p in paths]
        vectors = cached.global_[[rows[p.resolve()] for p in paths]]
        # as stored: R is kept as float16
        return (
            [f.descriptors for f in feats],
            [f.scores for f in feats],
            vectors.astype(np.float16).astype(np.float32),
        )

    ref_desc, ref_scores, ref_r = frames([r.path for r in dataset.references])
    q_desc, q_scores, q_r = frames([q.path for q in dataset.queries])
    robots = ["map"] * len(ref_r)
    order = np.array([r.order for r in dataset.references])
    positives = [q.positives for q in dataset.queries]
    half = len(positives) // 2

    variants = [
        Variant(p, float(s), None if w == "auto" else int(w), float(a))
        for p in args.pooling.split(",")
        for s in args.shrinkage.split(",")
        for w in args.words.split(",")
        for a in args.alpha.split(",")
    ]
    outcomes = []
    for v in variants:
        refs_r = ref_r if v.pooling == "gem-layout" else _gem_part(ref_r, args.gem_dim)
        queries_r = q_r if v.pooling == "gem-layout" else _gem_part(q_r, args.gem_dim)
        branch = WhiteningConfig(max_dims=512, shrinkage=v.shrinkage)
        config = CalibrationConfig(words=v.words, alpha=v.alpha, local=branch, global_=branch)
        inputs = CalibrationInputs(ref_desc, ref_scores, refs_r, robots, order)
        calibration = Calibration.fit(inputs, config).calibration
        refs = calibration.fuse(*calibration.branch_vectors(ref_desc, ref_scores, refs_r))
        queries = calibration.fuse(*calibration.branch_vectors(q_desc, q_scores, queries_r))
        best = (queries @ refs.T).argmax(1)
        right = np.array([int(b) in truth for b, truth in zip(best, positives, strict=True)])
        outcome = Outcome(
            v, float(right[:half].mean()), float(right[half:].mean()), float(right.mean())
        )
        outcomes.append(outcome)
        print(
            f"{v.pooling:10s} s={v.shrinkage:<4g} words={v.words or 'auto':<5} "
            f"alpha={v.alpha:<4g} R@1 first half {outcome.dev:.3f}  second half "
            f"{outcome.held:.3f}  all {outcome.all:.3f}",
            flush=True,
        )
    if args.json:
        args.json.write_text(json.dumps([asdict(o) for o in outcomes], indent=1))


if __name__ == "__main__":
    main()

"""Cost of sequence scoring on one observe, on a synthetic atlas of ``--frames`` frames.

The atlas is ``--robots`` trajectories of consecutive frames (``synthetic_embeddings.py``, one
place per frame); each observation is a noisy revisit of a random stretch of L frames. What an
observe adds to today's single-frame query, in two cases:

- warm (the steady state of a robot streaming): the previous L - 1 frames' best matches and
  map statistics are cached; the newest frame's own search is already done by the query. Timed:
  the newest frame's map statistics (:class:`MapMoments`), candidate proposal, vector lookup,
  scoring, and the consistency decision.
- warm CPU: the same step's CPU time (process time), which contended cores do not inflate;
- cold (a replica or restart with nothing cached): also the L - 1 earlier frames' FAISS searches
  (flat inner product, as the service's exact index) and their map statistics.

    nice -n 10 python benchmarks/sequence_scoring.py --frames 100000 --dim 1408 --json out.json

Prints a table and, with ``--json``, writes the figures.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import faiss
import numpy as np
from synthetic_embeddings import ClusteredEmbeddings, unit_rows

from service.ml.sequences import (
    ConsistencySettings,
    Hypothesis,
    MapMoments,
    SequenceSettings,
    Trajectories,
    decide,
    match_sequence,
)


def build_atlas(frames: int, dim: int, robots: int) -> tuple[np.ndarray, Trajectories]:
    vectors = np.concatenate(
        [v for _, v in ClusteredEmbeddings(n=frames, dim=dim, per_place=1).chunks()]
    )
    robot_of = [f"robot-{i * robots // frames:03d}" for i in range(frames)]
    return vectors, Trajectories.build(robot_of, [float(i) for i in range(frames)])


def run(args: argparse.Namespace) -> dict[str, object]:
    faiss.omp_set_num_threads(args.threads)
    vectors, trajectories = build_atlas(args.frames, args.dim, args.robots)
    index = faiss.IndexFlatIP(args.dim)
    index.add(vectors)
    moments = MapMoments.of(vectors)
    rng = np.random.default_rng(7)
    results: dict[str, object] = {}
    for length in args.lengths:
        settings = SequenceSettings(length=length)
        warm, cold, warm_cpu, right = [], [], [], 0
        for _ in range(args.observations):
            robot_start = rng.integers(0, args.robots) * (args.frames // args.robots)
            end = int(robot_start + rng.integers(length, args.frames // args.robots))
            truth = np.arange(end - length + 1, end + 1)
            queries = unit_rows(
                vectors[truth]
                + args.noise
                * rng.standard_normal((length, args.dim), dtype=np.float32)
                / np.sqrt(args.dim)
                * 8
            )
            _, found = index.search(queries, settings.seeds)
            cached_stats = moments.row_stats(queries[:-1])
            start, cpu = time.perf_counter(), time.process_time()
            newest_mean, newest_std = moments.row_stats(queries[-1:])
            stats = (np.r_[cached_stats[0], newest_mean], np.r_[cached_stats[1], newest_std])
            matches = match_sequence(
                queries,
                list(found),
                vectors.__getitem__,
                trajectories,
                moments,
                settings,
                row_stats=stats,
            )
            decide([Hypothesis(matches[0].reference, True)], trajectories, ConsistencySettings())
            warm.append((time.perf_counter() - start) * 1000.0)
            warm_cpu.append((time.process_time() - cpu) * 1000.0)
            start = time.perf_counter()
            _, again = index.search(queries[:-1], settings.seeds)
            match_sequence(
                queries, [*again, found[-1]], vectors.__getitem__, trajectories, moments, settings
            )
            cold.append((time.perf_counter() - start) * 1000.0)
            right += int(matches[0].reference == end)
        results[f"L={length}"] = {
            "warm_ms": {"p50": float(np.median(warm)), "p95": float(np.percentile(warm, 95))},
            "warm_cpu_ms": {
                "p50": float(np.median(warm_cpu)),
                "p95": float(np.percentile(warm_cpu, 95)),
            },
            "cold_ms": {"p50": float(np.median(cold)), "p95": float(np.percentile(cold, 95))},
            "top1_right": right / args.observations,
        }
    return {
        "frames": args.frames,
        "dim": args.dim,
        "robots": args.robots,
        "observations": args.observations,
        "threads": args.threads,
        "machine": f"{platform.machine()}, {platform.platform()}",
        "results": results,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=100_000)
    parser.add_argument("--dim", type=int, default=1408)
    parser.add_argument("--robots", type=int, default=100)
    parser.add_argument("--lengths", type=int, nargs="+", default=[5, 10, 20])
    parser.add_argument("--observations", type=int, default=200)
    parser.add_argument("--noise", type=float, default=0.5)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    report = run(args)
    print(
        f"{args.frames} frames x {args.dim} dims, {args.robots} trajectories, "
        f"{args.observations} observations each, {args.threads} thread(s)"
    )
    print("| L | warm p50 ms | warm p95 ms | warm CPU p50 ms | cold p50 ms | cold p95 ms | top-1 |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for name, row in report["results"].items():  # type: ignore[attr-defined]
        print(
            f"| {name[2:]} | {row['warm_ms']['p50']:.2f} | {row['warm_ms']['p95']:.2f} | "
            f"{row['warm_cpu_ms']['p50']:.2f} | "
            f"{row['cold_ms']['p50']:.2f} | {row['cold_ms']['p95']:.2f} | {row['top1_right']:.2f} |"
        )
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()

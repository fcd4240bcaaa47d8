"""What an adapt job costs on a large atlas: the learned whitening from revisit pairs, its
not-worse gate (held-out pairs and stretches, both versions) and the re-embedding + index
build of every frame, on synthetic calibrated branches of the real size.

    OMP_NUM_THREADS=1 python benchmarks/adaptation.py --frames 10000 --pairs 1000 --threads 1

``--method`` as the job's (default: the job's default, whitening+pairs: the learned whitening,
then the listwise loss over the pairs of :mod:`service.ml.pair_loss`).

The atlas is one robot's route of ``frames - pairs`` frames plus ``pairs`` frames of a second
robot revisiting evenly spaced places under a shifted condition (a random offset shared by the
revisits plus noise), each paired with the frame it revisits. Vector generation is not timed;
reading stored vectors from the database is timed in ``benchmarks/retraining.py``.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from service.index import AtlasIndex
from service.jobs.adaptation_config import ADAPT_METHODS, DEFAULT_METHOD, AdaptConfig
from service.ml.adaptation import adapt_heads
from service.ml.heads import HeadsConfig, LoopNetHeads
from service.ml.pair_loss import PairLossConfig
from service.ml.pair_whitening import PairWhiteningConfig
from service.ml.pipeline import embed_vectors
from service.ml.training import TrainingData


def unit(x: np.ndarray) -> np.ndarray:
    return (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)


def synthetic(frames: int, pairs: int, dims: int, seed: int = 0) -> tuple[TrainingData, np.ndarray]:
    rng = np.random.default_rng(seed)
    mapped = frames - pairs
    route = np.cumsum(rng.normal(size=(mapped, 2 * dims)) * 0.2, axis=0)  # a smooth route
    route += rng.normal(size=route.shape)
    places = np.linspace(0, mapped - 1, pairs).astype(int)
    condition = rng.normal(size=2 * dims) * 2.0
    revisits = route[places] + condition + rng.normal(size=(pairs, 2 * dims)) * 0.5
    vectors = np.concatenate([route, revisits])
    data = TrainingData(
        unit(vectors[:, :dims]),
        unit(vectors[:, dims:]),
        np.r_[np.arange(mapped) // 50, places // 50],
        np.r_[np.arange(mapped), np.arange(pairs)],
        np.array(["map"] * mapped + ["revisit"] * pairs),
    )
    return data, np.stack([mapped + np.arange(pairs), places], axis=1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=10_000)
    parser.add_argument("--pairs", type=int, default=1_000)
    parser.add_argument("--dims", type=int, default=512, help="per branch (the calibrated size)")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--method", default=DEFAULT_METHOD, choices=ADAPT_METHODS)
    parser.add_argument("--rank", type=int, help="of the loss's change (default: full)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    data, pairs = synthetic(args.frames, args.pairs, args.dims)
    active = LoopNetHeads(HeadsConfig(local_dim=args.dims, global_dim=args.dims)).eval()
    start, start_cpu = time.perf_counter(), time.process_time()
    job = AdaptConfig(method=args.method)
    loss = PairLossConfig(rank=args.rank) if job.trains_on_pairs else None
    result = adapt_heads(
        data, pairs, active, PairWhiteningConfig(), whiten=job.whitens, pair_loss=loss
    )
    adapted = time.perf_counter()
    index = AtlasIndex(result.heads.config.fused_dim)
    embeddings = embed_vectors(result.heads, data.local, data.global_)
    robots = [str(r) for r in np.asarray(data.robots)]
    index.add(np.arange(len(embeddings)), embeddings, robots)
    wall, cpu = time.perf_counter() - start, time.process_time() - start_cpu
    gate = result.gate
    print(
        f"{args.frames} frames of {2 * args.dims} dims, {args.pairs} pairs, "
        f"{args.threads} thread(s): fit {result.metrics['fit_seconds']:.1f} s, gate "
        f"{result.metrics['gate_seconds']:.1f} s, re-embedding + index "
        f"{time.perf_counter() - adapted:.1f} s; total {wall:.1f} s wall, {cpu:.1f} s CPU. "
        f"Held-out pairs {gate['pairs']}: partner first {gate['active']} -> {gate['new']} "
        f"(shrinkage {result.metrics['shrinkage']}); {args.method}: "
        + ", ".join(f"{k} {v}" for k, v in result.metrics.items() if k.startswith("pair_loss"))
    )


if __name__ == "__main__":
    main()

"""Retraining cost: a few-shot job's training time, and re-embedding + index rebuild of a
large atlas from stored features (synthetic vectors with the real dimensions).

    python benchmarks/retraining.py                      # 100 submaps x 5 shots, 1M frames
    python benchmarks/retraining.py --frames 200000      # smaller re-embedding run
    python benchmarks/retraining.py --threads 1          # what LOOPNET_TORCH_THREADS=1 gives

Wall and CPU seconds are both printed: on a machine shared with other work, CPU seconds of a
one-thread run estimate what a quiet machine's wall clock would show.

Training uses the production code (``train_heads``); re-embedding uses ``embed_vectors`` and
``AtlasIndex.add`` in 100k-frame chunks, as the worker does (vector generation not timed).
Reading stored vectors back from SQLite is timed separately on a smaller sample.
"""

from __future__ import annotations

import argparse
import os
import platform
import time

import numpy as np
import torch

from service.index import AtlasIndex
from service.ml.features import FrameFeatures, LocalFeatures
from service.ml.heads import HeadsConfig
from service.ml.pipeline import embed_vectors
from service.ml.precision import Precision
from service.ml.presets import PRESETS
from service.ml.training import TrainingConfig, TrainingData, train_heads

LOCAL_DIM, GLOBAL_DIM = PRESETS["default"].signature.dims  # DISK, MobileNetV2 GeM + layout


def unit(x: np.ndarray) -> np.ndarray:
    return (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)


def synthetic_atlas(submaps: int, per_submap: int, seed: int = 0) -> TrainingData:
    """Stored vectors scattered around one centre per submap (plus a shared component)."""
    rng = np.random.default_rng(seed)
    labels = np.repeat(np.arange(submaps), per_submap)
    shared_d, shared_r = rng.normal(size=LOCAL_DIM) * 3, rng.normal(size=GLOBAL_DIM)
    local = shared_d + rng.normal(size=(submaps, LOCAL_DIM))[labels]
    global_ = shared_r + rng.normal(size=(submaps, GLOBAL_DIM))[labels]
    local += 0.8 * rng.normal(size=local.shape)
    global_ += 0.8 * rng.normal(size=global_.shape)
    return TrainingData(unit(local), unit(global_), labels, np.arange(len(labels)))


def bench_training(submaps: int, per_submap: int, shots: int, repeats: int) -> None:
    data = synthetic_atlas(submaps, per_submap)
    base = HeadsConfig(LOCAL_DIM, GLOBAL_DIM)
    config = TrainingConfig(shots=shots)
    train_heads(data, base, TrainingConfig(shots=shots, epochs=2))  # warm-up (imports, allocator)
    times, cpu_times, epochs = [], [], []
    for _ in range(repeats):
        start, cpu_start = time.perf_counter(), time.process_time()
        result = train_heads(data, base, config)
        times.append(time.perf_counter() - start)
        cpu_times.append(time.process_time() - cpu_start)
        epochs.append(result.metrics["epochs_run"])
    print(
        f"training: {submaps} submaps x {shots} shots ({len(data.submaps)} frames, "
        f"{per_submap - shots} validation frames per submap): median {np.median(times):.2f} s "
        f"wall, {np.median(cpu_times):.2f} s CPU over {repeats} runs (epochs run: {epochs}, "
        f"at most {config.epochs})"
    )


def bench_reembedding(frames: int, embed_dim: int, precision: Precision = "fp32") -> None:
    base = HeadsConfig(LOCAL_DIM, GLOBAL_DIM)
    data = synthetic_atlas(20, 10)
    heads = train_heads(data, base, TrainingConfig(shots=5, epochs=3, embed_dim=embed_dim)).heads
    index = AtlasIndex(heads.config.fused_dim)
    rng = np.random.default_rng(1)
    chunk, elapsed, cpu = 100_000, 0.0, 0.0
    for start in range(0, frames, chunk):
        n = min(chunk, frames - start)
        local = unit(rng.standard_normal((n, LOCAL_DIM), dtype=np.float32))
        global_ = unit(rng.standard_normal((n, GLOBAL_DIM), dtype=np.float32))
        ids = np.arange(start, start + n)
        robots = ["r"] * n
        begin, cpu_begin = time.perf_counter(), time.process_time()
        index.add(ids, embed_vectors(heads, local, global_, precision), robots)
        elapsed += time.perf_counter() - begin
        cpu += time.process_time() - cpu_begin
    begin, cpu_begin = time.perf_counter(), time.process_time()
    index.wait_rebuilt()  # the size-chosen index (IVF past 32 MiB) finishes in the background
    elapsed += time.perf_counter() - begin
    cpu += time.process_time() - cpu_begin
    per_100k = elapsed / frames * 100_000
    print(
        f"re-embedding ({precision}) + index rebuild: {frames} frames, embed_dim {embed_dim}: "
        f"{elapsed:.2f} s "
        f"wall, {cpu:.2f} s CPU ({per_100k:.2f} s wall per 100k frames; index {index.size} "
        f"vectors, {index.describe()})"
    )


def bench_database_read(frames: int) -> None:
    from scratch_atlas import scratch_atlas

    from service.storage.db import transaction
    from service.storage.feature_store import iter_stored_vectors, to_row
    from service.storage.models import Frame

    rng = np.random.default_rng(2)
    with scratch_atlas() as (sessions, atlas, submap):
        atlas_id, submap_id = atlas.id, submap.id
        empty = LocalFeatures.empty(LOCAL_DIM)
        for start in range(0, frames, 5000):
            with transaction(sessions) as session:
                for _ in range(min(5000, frames - start)):
                    frame = Frame(
                        atlas_id=atlas_id,
                        submap_id=submap_id,
                        robot_id="r",
                        width=1,
                        height=1,
                        keypoint_count=0,
                    )
                    session.add(frame)
                    session.flush()
                    features = FrameFeatures(
                        empty,
                        unit(rng.normal(size=(1, LOCAL_DIM)))[0],
                        unit(rng.normal(size=(1, GLOBAL_DIM)))[0],
                        (1, 1),
                    )
                    session.add(to_row(frame.id, features))
        begin = time.perf_counter()
        with sessions() as session:
            count = sum(len(batch) for batch in iter_stored_vectors(session, atlas_id))
        elapsed = time.perf_counter() - begin
    print(
        f"reading stored D and R back from SQLite: {count} frames in {elapsed:.2f} s "
        f"({elapsed / count * 100_000:.2f} s per 100k frames)"
    )


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--submaps", type=int, default=100)
    parser.add_argument("--frames-per-submap", type=int, default=20)
    parser.add_argument("--shots", type=int, default=5)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--frames", type=int, default=1_000_000, help="frames to re-embed")
    parser.add_argument("--embed-dim", type=int, default=256)
    parser.add_argument("--db-frames", type=int, default=20_000)
    parser.add_argument("--precision", default="fp32", choices=("fp32", "bf16"))
    parser.add_argument("--threads", type=int, help="torch threads (default: torch's)")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    print(
        f"machine: {platform.machine()}, {os.cpu_count()} cores, torch {torch.__version__}, "
        f"{torch.get_num_threads()} threads"
    )
    bench_training(args.submaps, args.frames_per_submap, args.shots, args.repeats)
    bench_reembedding(args.frames, args.embed_dim, args.precision)
    bench_database_read(args.db_frames)


if __name__ == "__main__":
    main()

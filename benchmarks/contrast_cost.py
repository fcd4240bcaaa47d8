"""What trajectory contrast costs the sequence map (service.app.sequence_map): building the map
of an atlas at start, appending a streamed frame, and the memory of the contrasted copy.

    OMP_NUM_THREADS=1 python benchmarks/contrast_cost.py --frames 100000 --dim 1024

Random unit vectors of four robots streaming in turn, one second apart. Each figure is the
median of ``--repeats`` runs, contrast off (0) and on (the default window) in the same process.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from service.app.sequence_map import SequenceMap
from service.ml.sequences.contrast import DEFAULT_CONTRAST_FRAMES


def rows(frames: int) -> list[tuple[int, str, float | None]]:
    return [(i + 1, f"r{i % 4}", float(i // 4)) for i in range(frames)]


def build_ms(vectors: np.ndarray, window: int) -> float:
    start = time.perf_counter()
    SequenceMap(0, 0, vectors.shape[1], 10.0, window).append(rows(len(vectors)), vectors)
    return (time.perf_counter() - start) * 1000.0


def append_ms(vectors: np.ndarray, window: int, streamed: int) -> float:
    """Median milliseconds of appending one frame at a time after the first frames."""
    base = len(vectors) - streamed
    held = SequenceMap(0, 0, vectors.shape[1], 10.0, window)
    all_rows = rows(len(vectors))
    held.append(all_rows[:base], vectors[:base])
    times = []
    for i in range(base, len(vectors)):
        start = time.perf_counter()
        held.append([all_rows[i]], vectors[i : i + 1])
        times.append((time.perf_counter() - start) * 1000.0)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=100_000)
    parser.add_argument("--dim", type=int, default=1024)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--streamed", type=int, default=500)
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    vectors = rng.standard_normal((args.frames, args.dim)).astype(np.float32)
    vectors /= np.linalg.norm(vectors, axis=1, keepdims=True)
    print(f"{args.frames:,} frames of {args.dim}-d, four robots; medians of {args.repeats} runs")
    for window in (0, DEFAULT_CONTRAST_FRAMES):
        build = statistics.median(build_ms(vectors, window) for _ in range(args.repeats))
        step = statistics.median(
            append_ms(vectors, window, args.streamed) for _ in range(args.repeats)
        )
        extra = args.frames * args.dim * 4 / 2**20 if window else 0.0
        print(
            f"window {window:>2}: build {build:,.0f} ms, append one frame {step:.3f} ms "
            f"(median of {args.streamed}), contrasted copy {extra:,.0f} MiB"
        )


if __name__ == "__main__":
    main()

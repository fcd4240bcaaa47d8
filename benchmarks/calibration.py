"""Cost of an atlas calibration: fitting (vocabulary, aggregation, whitening, impostor model)
and re-embedding every frame from stored features, on a synthetic atlas with the real sizes.

    python benchmarks/calibration.py                         # 10,000 frames, DISK-sized
    python benchmarks/calibration.py --keypoints 512 --dim 64  # XFeat-sized (fast preset)
    python benchmarks/calibration.py --json out.json

Frames are generated on access, as a job reads them row by row from the feature store: each
frame's descriptors are drawn from a few "place" patterns plus noise and rounded to float16
(what the store holds). Generation is inside the timed loop, so figures are slightly
pessimistic (``fit_generation_cpu_s`` estimates how much: the fit reads every frame twice).
Wall and CPU seconds are both printed, per stage too (CPU seconds of a one-thread run estimate
a quiet machine's wall clock on a shared one).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from collections.abc import Sequence
from typing import overload

import numpy as np
import torch

from service.ml.calibration import Calibration, CalibrationConfig, CalibrationInputs
from service.ml.presets import PRESETS


class SyntheticDescriptors(Sequence[np.ndarray]):
    """Frame ``i``'s ``keypoints x dim`` float16 descriptors, generated deterministically."""

    def __init__(self, frames: int, keypoints: int, dim: int, seed: int = 0) -> None:
        rng = np.random.default_rng(seed)
        pool = rng.normal(size=(50_000, dim)).astype(np.float32)
        self.pool = pool / np.linalg.norm(pool, axis=1, keepdims=True)
        self.noise = (0.3 * rng.normal(size=(4 * keypoints, dim))).astype(np.float32)
        self.frames, self.keypoints, self.seed = frames, keypoints, seed

    def __len__(self) -> int:
        return self.frames

    @overload
    def __getitem__(self, i: int) -> np.ndarray: ...

    @overload
    def __getitem__(self, i: slice) -> Sequence[np.ndarray]: ...

    def __getitem__(self, i: int | slice) -> np.ndarray | Sequence[np.ndarray]:
        if isinstance(i, slice):
            return [self[j] for j in range(*i.indices(self.frames))]
        if not 0 <= i < self.frames:
            raise IndexError(i)
        rng = np.random.default_rng((self.seed, i))
        place = (i // 5) * 97 % (len(self.pool) - 2 * self.keypoints)
        rows = place + rng.integers(0, 2 * self.keypoints, self.keypoints)
        start = int(rng.integers(0, 3 * self.keypoints))
        noisy = self.pool[rows] + self.noise[start : start + self.keypoints]
        unit = noisy / np.linalg.norm(noisy, axis=1, keepdims=True)
        # rounded by torch: the same float16 values as numpy's astype, a tenth of the time
        # (the generator stands in for reads that cost a job almost nothing)
        return torch.from_numpy(unit).half().numpy()


def generation_cpu_s(descriptors: SyntheticDescriptors, sample: int = 500) -> float:
    """CPU seconds generating one frame takes (the fit reads each frame twice; a job's reads
    from the store are views of blobs already in memory, nearly free)."""
    start = time.process_time()
    for i in range(min(sample, len(descriptors))):
        descriptors[i]
    return (time.process_time() - start) / min(sample, len(descriptors))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=10_000)
    parser.add_argument("--keypoints", type=int, default=1024, help="per frame (default preset)")
    parser.add_argument("--dim", type=int, default=128, help="descriptor size (DISK 128)")
    parser.add_argument(
        "--global-dim",
        type=int,
        default=PRESETS["default"].signature.dims[1],
        help="R's length (default preset: MobileNetV2 GeM + layout)",
    )
    parser.add_argument(
        "--words", type=int, default=None, help="VLAD words (default: 16384 / --dim)"
    )
    parser.add_argument("--json", help="also write the figures to this file")
    args = parser.parse_args()

    descriptors = SyntheticDescriptors(args.frames, args.keypoints, args.dim)
    rng = np.random.default_rng(1)
    global_vectors = np.abs(rng.normal(size=(args.frames, args.global_dim))).astype(np.float32)
    global_vectors /= np.linalg.norm(global_vectors, axis=1, keepdims=True)
    scores = [np.ones(args.keypoints, np.float32)] * args.frames
    inputs = CalibrationInputs(
        descriptors=descriptors,
        scores=scores,
        global_vectors=global_vectors,
        robots=["robot"] * args.frames,
        order=np.arange(args.frames),
    )
    config = CalibrationConfig(words=args.words)

    wall, cpu = time.perf_counter(), time.process_time()
    fitted = Calibration.fit(inputs, config)
    fit_wall, fit_cpu = time.perf_counter() - wall, time.process_time() - cpu

    wall, cpu = time.perf_counter(), time.process_time()
    embedded = fitted.calibration.embed_many(descriptors, scores, global_vectors)
    embed_wall, embed_cpu = time.perf_counter() - wall, time.process_time() - cpu

    figures = {
        "frames": args.frames,
        "keypoints_per_frame": args.keypoints,
        "descriptor_dim": args.dim,
        "global_dim": args.global_dim,
        "words": config.words_for(args.dim),
        "fused_dim": int(embedded.shape[1]),
        "fit_wall_s": round(fit_wall, 2),
        "fit_cpu_s": round(fit_cpu, 2),
        "fit_stages_s": {k: round(v, 2) for k, v in fitted.timings_s.items()},
        "fit_stages_cpu_s": {k: round(v, 2) for k, v in fitted.cpu_s.items()},
        "fit_generation_cpu_s": round(2 * args.frames * generation_cpu_s(descriptors), 2),
        "reembed_wall_s": round(embed_wall, 2),
        "reembed_cpu_s": round(embed_cpu, 2),
        "reembed_ms_per_frame": round(embed_wall * 1000 / args.frames, 3),
        "job_wall_s": round(fit_wall, 2),
        "note": "a job re-embeds the fitted frames from the fit's own branch vectors; "
        "reembed_* is the cost for frames stored after (or a full re-embedding)",
        "machine": f"{platform.machine()}, {os.cpu_count()} cores visible, "
        f"OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', 'unset')}",
    }
    print(
        f"calibration of {args.frames} frames ({args.keypoints} x {args.dim}-d descriptors, "
        f"{args.global_dim}-d global, {config.words_for(args.dim)} words): fit {fit_wall:.1f} s wall / "
        f"{fit_cpu:.1f} s CPU (stages wall {figures['fit_stages_s']}, CPU "
        f"{figures['fit_stages_cpu_s']}); re-embed {embed_wall:.1f} s wall / "
        f"{embed_cpu:.1f} s CPU ({figures['reembed_ms_per_frame']} ms a frame); "
        f"fused dim {embedded.shape[1]}"
    )
    print(json.dumps(figures))
    if args.json:
        with open(args.json, "w") as handle:
            json.dump(figures, handle, indent=2)


if __name__ == "__main__":
    main()

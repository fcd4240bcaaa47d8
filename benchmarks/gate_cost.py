"""What a retraining job's not-worse gate costs on a large atlas: one version's held-out scores.

A synthetic atlas of random embeddings (one robot's route, submaps of 50 frames) split as a job
splits it; prints the held-out and judged frame counts and the wall and CPU time of
:func:`service.ml.held_out.held_out_scores` for one version (a job scores two):

    OMP_NUM_THREADS=1 python benchmarks/gate_cost.py --frames 100000 --threads 1
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from service.ml import held_out
from service.ml.heads import HeadsConfig, LoopNetHeads
from service.ml.training import TrainingData


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=100_000)
    parser.add_argument("--dims", type=int, default=512, help="per branch (the calibrated size)")
    parser.add_argument("--submap", type=int, default=50, help="frames per submap")
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    rng = np.random.default_rng(0)
    vectors = rng.normal(size=(args.frames, 2 * args.dims)).astype(np.float32)
    data = TrainingData(
        vectors[:, : args.dims],
        vectors[:, args.dims :],
        np.arange(args.frames) // args.submap,
        np.arange(args.frames),
        np.array(["robot"] * args.frames),
    )
    split = held_out.split_for_job(data, shots=1)
    heads = LoopNetHeads(HeadsConfig(local_dim=args.dims, global_dim=args.dims)).eval()
    start, start_cpu = time.perf_counter(), time.process_time()
    held_out.held_out_scores(heads, data, split.held_out, window=2)
    wall, cpu = time.perf_counter() - start, time.process_time() - start_cpu
    judged = min(len(split.held_out), held_out.JUDGED_FRAMES)
    print(
        f"{args.frames} frames of {2 * args.dims} dims, {args.threads} thread(s): "
        f"{len(split.held_out)} held out, {judged} judged, "
        f"{min(judged, held_out.AP_FRAMES)} ranked in full; one version {wall:.1f} s wall, "
        f"{cpu:.1f} s CPU"
    )


if __name__ == "__main__":
    main()

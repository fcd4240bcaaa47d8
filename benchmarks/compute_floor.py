"""How close an extractor runs to this machine's fp32 compute floor.

The floor of a network on an input is its FLOP count (counted by torch's ``FlopCounterMode``,
2 FLOPs per multiply-add) divided by the machine's fp32 throughput, measured as a large square
matmul with the same torch threads. The matmul runs just before and just after each timed
extraction, so both see the same share of a CPU that other jobs may be using; the ratio
``time / floor`` is then a property of the network's implementation, not of the load.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from torch.utils.flop_counter import FlopCounterMode

MATMUL_SIZE = 2048


def count_flops(fn: Callable[[], object]) -> float:
    """FLOPs of one call of ``fn`` (2 per multiply-add), as torch counts them."""
    with torch.inference_mode(), FlopCounterMode(display=False) as counter:
        fn()
    return float(counter.get_total_flops())


def matmul_gflops(repeats: int = 3, size: int = MATMUL_SIZE) -> float:
    """fp32 GFLOP/s of a ``size``-square matmul with torch's current threads (best of repeats)."""
    a, b = torch.rand(size, size), torch.rand(size, size)
    a @ b  # warm-up
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        a @ b
        best = min(best, time.perf_counter() - start)
    return 2 * size**3 / best / 1e9


@dataclass(frozen=True)
class FloorResult:
    gflop: float  # counted FLOPs of one call, in GFLOP
    seconds: float  # median time of one call
    gflops_machine: float  # matmul throughput measured around the calls
    ratio: float  # seconds / (gflop / gflops_machine): 1.0 means at the floor


def floor_ratio(
    fn: Callable[[], object], flops_of: Callable[[], object], repeats: int
) -> FloorResult:
    """Time ``fn`` (``repeats`` times, matmul throughput measured around each call) and compare
    it with the floor of ``flops_of`` (the network part whose FLOPs are counted)."""
    gflop = count_flops(flops_of) / 1e9
    fn()  # warm-up
    times, throughputs = [], [matmul_gflops()]
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
        throughputs.append(matmul_gflops())
    seconds = statistics.median(times)
    machine = statistics.median(throughputs)
    return FloorResult(gflop, seconds, machine, seconds / (gflop / machine))


def disk_floor_rows(rgb: np.ndarray, long_side: int, max_keypoints: int, repeats: int) -> list[str]:
    """Markdown rows: DISK at ``long_side`` on the frame and on a square frame of that side
    (the 675 GFLOP case at 1024) against this machine's floor."""
    from service.ml.images import resize_long_side, to_tensor
    from service.ml.local_extractors import LocalExtractorConfig, build_local_extractor

    disk = build_local_extractor(
        LocalExtractorConfig(long_side=long_side, max_keypoints=max_keypoints)
    )
    # The network's cost depends on the input size only: noise stands in for a square frame.
    rng = np.random.default_rng(0)
    square = (rng.random((long_side, long_side, 3)) * 255).astype(np.uint8)
    rows = []
    for label, frame in (("frame", rgb), ("square", square)):
        image = resize_long_side(to_tensor(frame), long_side)

        def network(image: torch.Tensor = image) -> object:
            return disk.model(  # type: ignore[attr-defined]
                image, n=max_keypoints, window_size=5, pad_if_not_divisible=True
            )

        def extract(frame: np.ndarray = frame) -> object:
            return disk.extract(frame)

        result = floor_ratio(extract, network, repeats)
        height, width = image.shape[-2:]
        rows.append(
            f"| DISK long side {long_side}, {label} {width}x{height} | {result.gflop:.0f} | "
            f"{result.seconds * 1000:.0f} | {result.gflops_machine:.1f} | "
            f"{result.gflop / result.gflops_machine * 1000:.0f} | {result.ratio:.2f} |"
        )
    return rows

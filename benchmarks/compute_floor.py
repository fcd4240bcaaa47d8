"""How close an extractor runs to this machine's compute floor (fp32, or bf16 with --precision).

The floor of a network on an input is its FLOP count (counted by torch's ``FlopCounterMode``,
2 FLOPs per multiply-add) divided by the machine's fp32 throughput, measured as a large square
matmul with the same torch threads. The matmul runs just before and just after each timed
extraction. Two ratios are reported: by wall time (what a caller waits, which includes any
share of the CPU other jobs take) and by CPU time (the process's own seconds on the cores,
which time-slicing with other jobs does not inflate: the implementation's efficiency).

    python benchmarks/compute_floor.py --image ../shared/data/gardenspoint_first10/query/0.jpg
    python benchmarks/compute_floor.py --precision bf16 --threads 1   # the paper preset's DISK
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch
from torch.utils.flop_counter import FlopCounterMode

MATMUL_SIZE = 2048


def count_flops(fn: Callable[[], object]) -> float:
    """FLOPs of one call of ``fn`` (2 per multiply-add), as torch counts them."""
    with torch.inference_mode(), FlopCounterMode(display=False) as counter:
        fn()
    return float(counter.get_total_flops())


def matmul_gflops(
    repeats: int = 3, size: int = MATMUL_SIZE, dtype: torch.dtype = torch.float32
) -> tuple[float, float]:
    """GFLOP/s of a ``size``-square ``dtype`` matmul with torch's current threads, per second of
    wall time and per second of CPU time (best of ``repeats``)."""
    a, b = torch.rand(size, size).to(dtype), torch.rand(size, size).to(dtype)
    a @ b  # warm-up
    wall = cpu = float("inf")
    for _ in range(repeats):
        start, start_cpu = time.perf_counter(), time.process_time()
        a @ b
        wall = min(wall, time.perf_counter() - start)
        cpu = min(cpu, time.process_time() - start_cpu)
    flops = 2 * size**3 / 1e9
    return flops / wall, flops / cpu


@dataclass(frozen=True)
class FloorResult:
    gflop: float  # counted FLOPs of one call, in GFLOP
    seconds: float  # median wall time of one call
    cpu_seconds: float  # median CPU time of one call
    gflops_wall: float  # matmul GFLOP per wall second, measured around the calls
    gflops_cpu: float  # matmul GFLOP per CPU second

    @property
    def ratio(self) -> float:
        """Wall time over the floor: 1.0 means at the floor."""
        return self.seconds / (self.gflop / self.gflops_wall)

    @property
    def cpu_ratio(self) -> float:
        """CPU time over the CPU-time floor."""
        return self.cpu_seconds / (self.gflop / self.gflops_cpu)


def floor_ratio(
    fn: Callable[[], object],
    flops_of: Callable[[], object],
    repeats: int,
    dtype: torch.dtype = torch.float32,
) -> FloorResult:
    """Time ``fn`` (``repeats`` times, matmul throughput measured around each call) and compare
    it with the floor of ``flops_of`` (the network part whose FLOPs are counted) in the
    arithmetic ``dtype`` it runs in."""
    gflop = count_flops(flops_of) / 1e9
    fn()  # warm-up
    times, cpu_times, throughputs = [], [], [matmul_gflops(dtype=dtype)]
    for _ in range(repeats):
        start, start_cpu = time.perf_counter(), time.process_time()
        fn()
        times.append(time.perf_counter() - start)
        cpu_times.append(time.process_time() - start_cpu)
        throughputs.append(matmul_gflops(dtype=dtype))
    return FloorResult(
        gflop,
        statistics.median(times),
        statistics.median(cpu_times),
        statistics.median(t[0] for t in throughputs),
        statistics.median(t[1] for t in throughputs),
    )


FLOOR_HEADER = (
    "| extractor and input | GFLOP (counted) | median ms (wall) | matmul GFLOP/s (wall) | "
    "wall / floor | median CPU ms | matmul GFLOP per CPU s | CPU time / floor |\n"
    "| --- | --- | --- | --- | --- | --- | --- | --- |"
)


def disk_floor_rows(
    rgb: np.ndarray,
    long_side: int,
    max_keypoints: int,
    repeats: int,
    precision: Literal["fp32", "bf16"] = "fp32",
) -> list[str]:
    """Markdown rows: DISK at ``long_side`` in ``precision`` on the frame and on a square frame
    of that side (the 675 GFLOP case at 1024) against this machine's floor in that precision."""
    from service.ml.images import resize_long_side, to_tensor
    from service.ml.local_extractors import LocalExtractorConfig, build_local_extractor

    disk = build_local_extractor(
        LocalExtractorConfig(long_side=long_side, max_keypoints=max_keypoints), precision
    )
    dtype = torch.bfloat16 if precision == "bf16" else torch.float32
    # The network's cost depends on the input size only: noise stands in for a square frame.
    rng = np.random.default_rng(0)
    square = (rng.random((long_side, long_side, 3)) * 255).astype(np.uint8)
    rows = []
    for label, frame in (("frame", rgb), ("square", square)):
        image = resize_long_side(to_tensor(frame), long_side)

        def network(image: torch.Tensor = image) -> object:
            return disk.detect(image)  # type: ignore[attr-defined]

        def extract(frame: np.ndarray = frame) -> object:
            return disk.extract(frame)

        result = floor_ratio(extract, network, repeats, dtype)
        height, width = image.shape[-2:]
        rows.append(
            f"| DISK {precision} long side {long_side}, {label} {width}x{height} | {result.gflop:.0f} | "
            f"{result.seconds * 1000:.0f} | {result.gflops_wall:.1f} | {result.ratio:.2f} | "
            f"{result.cpu_seconds * 1000:.0f} | {result.gflops_cpu:.1f} | "
            f"{result.cpu_ratio:.2f} |"
        )
    return rows


def main() -> None:
    import argparse
    import os
    import platform
    from pathlib import Path

    from service.ml.images import decode_image

    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--image", type=Path, default=Path("../shared/data/gardenspoint_first10/query/0.jpg")
    )
    parser.add_argument("--long-side", type=int, default=1024)
    parser.add_argument("--max-keypoints", type=int, default=2048)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--precision", choices=("fp32", "bf16"), default="fp32")
    parser.add_argument("--threads", type=int, help="torch threads (default: torch's)")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    print(
        f"machine: {platform.machine()}, {os.cpu_count()} cores, torch {torch.__version__}, "
        f"{torch.get_num_threads()} threads, load average {os.getloadavg()[0]:.1f}\n"
    )
    print(FLOOR_HEADER)
    rgb = decode_image(args.image.read_bytes())
    rows = disk_floor_rows(rgb, args.long_side, args.max_keypoints, args.repeats, args.precision)
    for row in rows:
        print(row, flush=True)


if __name__ == "__main__":
    main()

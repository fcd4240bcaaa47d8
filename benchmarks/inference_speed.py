"""Inference at this machine's limit: reduced precision, batching and re-embedding, one run.

Every comparison is measured in the same run, the two sides interleaved, so a shared
machine's load hits both alike; each figure gives wall time (what a caller waits) and CPU time
(the process's own seconds on a core, which other jobs' time-slicing does not inflate).
Writes ``inference_speed.json`` and ``inference_speed.md`` into ``--out``.

    OMP_NUM_THREADS=1 python benchmarks/inference_speed.py --threads 1
    python benchmarks/inference_speed.py --reembed-frames 200000 --no-index   # a quicker run
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import statistics
import threading
import time
from collections.abc import Callable, Iterator
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import torch
from compute_floor import floor_ratio
from index_search import add_policy_arguments, policy_from

from service.ml.backbones import BackboneConfig, build_backbone
from service.ml.backbones.registry import backbone_spec, pretrained_trunk
from service.ml.images import decode_image, resize_long_side, to_tensor
from service.ml.local_extractors import LocalExtractorConfig, build_local_extractor
from service.ml.pipeline import FeaturePipeline
from service.ml.precision import FastInference, Precision, cpu_has_native_bf16
from service.ml.presets import resolve_preset

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("LOOPNET_SHARED_DIR", ROOT.parent / "shared")) / "data"


def timed(fn: Callable[[], object], repeats: int) -> dict[str, float]:
    """Median wall and CPU milliseconds of ``repeats`` calls after one warm-up call."""
    fn()
    walls, cpus = [], []
    for _ in range(repeats):
        start, start_cpu = time.perf_counter(), time.process_time()
        fn()
        walls.append((time.perf_counter() - start) * 1000)
        cpus.append((time.process_time() - start_cpu) * 1000)
    return {"wall_ms": statistics.median(walls), "cpu_ms": statistics.median(cpus)}


def compare(
    baseline: Callable[[], object], candidate: Callable[[], object], repeats: int
) -> dict[str, Any]:
    """Both sides timed in alternation (one call each per round); ratio = baseline / candidate."""
    baseline(), candidate()
    sides: dict[str, dict[str, list[float]]] = {
        "baseline": {"wall": [], "cpu": []},
        "candidate": {"wall": [], "cpu": []},
    }
    for _ in range(repeats):
        for name, fn in (("baseline", baseline), ("candidate", candidate)):
            start, start_cpu = time.perf_counter(), time.process_time()
            fn()
            sides[name]["wall"].append((time.perf_counter() - start) * 1000)
            sides[name]["cpu"].append((time.process_time() - start_cpu) * 1000)
    out: dict[str, Any] = {
        name: {f"{k}_ms": statistics.median(v) for k, v in side.items()}
        for name, side in sides.items()
    }
    for k in ("wall", "cpu"):
        out[f"speedup_{k}"] = out["baseline"][f"{k}_ms"] / out["candidate"][f"{k}_ms"]
    return out


def plain_network(module: torch.nn.Module) -> torch.nn.Module:
    """The network as loaded (fp32, NCHW), out of the service's wrapper."""
    inner = module.inner if isinstance(module, FastInference) else module
    return inner.to(memory_format=torch.contiguous_format)  # type: ignore[call-overload,no-any-return]


def extractors(name: str, long_side: int, top_n: int, precision: Precision) -> tuple[Any, Any]:
    """(kornia's network as loaded, fp32; the service's extractor in ``precision``)."""
    config = LocalExtractorConfig(name=name, long_side=long_side, max_keypoints=top_n)
    reference = build_local_extractor(config, "fp32")
    attribute = "unet" if name == "disk" else "net"
    plain = plain_network(getattr(reference.model, attribute))  # type: ignore[attr-defined]
    setattr(reference.model, attribute, plain)  # type: ignore[attr-defined]
    return reference, build_local_extractor(config, precision)


def local_section(rgb: np.ndarray, precision: Precision, repeats: int) -> dict[str, Any]:
    rows: dict[str, Any] = {}
    for name, side, top_n in (("disk", 512, 1024), ("xfeat", 320, 512)):
        reference, ours = extractors(name, side, top_n, precision)
        rows[f"{name}@{side}"] = compare(
            partial(reference.extract, rgb), partial(ours.extract, rgb), repeats
        )
    return rows


def disk_floor(rgb: np.ndarray, precision: Precision, repeats: int) -> dict[str, Any]:
    """DISK at 1024 (the paper preset) against the floor of the arithmetic it runs in."""
    disk = build_local_extractor(
        LocalExtractorConfig(long_side=1024, max_keypoints=2048), precision
    )
    image = resize_long_side(to_tensor(rgb), 1024)

    def network() -> object:
        return disk.detect(image)  # type: ignore[attr-defined]

    dtype = torch.bfloat16 if precision == "bf16" else torch.float32
    result = floor_ratio(lambda: disk.extract(rgb), network, repeats, dtype)
    return {
        "precision": precision,
        "gflop": result.gflop,
        "wall_ms": result.seconds * 1000,
        "cpu_ms": result.cpu_seconds * 1000,
        "matmul_gflops_wall": result.gflops_wall,
        "matmul_gflops_cpu": result.gflops_cpu,
        "wall_over_floor": result.ratio,
        "cpu_over_floor": result.cpu_ratio,
    }


def backbone_section(rgb: np.ndarray, precision: Precision, repeats: int) -> dict[str, Any]:
    rows: dict[str, Any] = {}
    for name, size in (("mobilenetv2", 160), ("mobilenetv2", 224), ("resnet18", 224)):
        try:
            ours = build_backbone(BackboneConfig(name, size), precision)
        except Exception as exc:  # noqa: BLE001 - missing weights: reported, not fatal
            rows[f"{name}@{size}"] = {"skipped": str(exc).splitlines()[0]}
            continue
        reference = build_backbone(BackboneConfig(name, size), "fp32")
        reference.trunk = pretrained_trunk(backbone_spec(name)).eval()  # unfolded, NCHW, fp32
        rows[f"{name}@{size}"] = compare(
            partial(reference.describe, rgb), partial(ours.describe, rgb), repeats
        )
        eight = timed(partial(ours.describe_batch, [rgb] * 8), repeats)
        rows[f"{name}@{size}"]["batch8_per_frame"] = {k: v / 8 for k, v in eight.items()}
    return rows


def preset_section(frames: list[np.ndarray], precision: Precision, repeats: int) -> dict[str, Any]:
    """A preset's whole extraction per frame: alone, and in batches of 8 frames of one size."""
    rows: dict[str, Any] = {}
    for preset_name in ("fast", "default"):
        pipeline = FeaturePipeline(resolve_preset(preset_name), precision)
        one = timed(partial(pipeline.extract, frames[0]), repeats)
        eight = timed(partial(pipeline.extract_batch, frames[:8]), max(1, repeats // 2))
        rows[preset_name] = {
            "one_frame": one,
            "batch8_per_frame": {k: v / 8 for k, v in eight.items()},
            "stages_ms": pipeline.extract(frames[0]).timings_ms,
        }
    return rows


READ_BATCH = 4096  # rows a batch, as the feature store reads them (iter_stored_vectors)


class StepClock:
    """Wall and CPU seconds of a run's steps, summed per step name. A step's CPU is its
    thread's (steps of two threads overlap); ``whole`` is the process's."""

    def __init__(self) -> None:
        self.seconds: dict[str, dict[str, float]] = {}
        self._lock = threading.Lock()

    @contextlib.contextmanager
    def step(self, name: str, whole: bool = False) -> Iterator[None]:
        cpu = time.process_time if whole else time.thread_time
        start, start_cpu = time.perf_counter(), cpu()
        try:
            yield
        finally:
            wall, used = time.perf_counter() - start, cpu() - start_cpu
            with self._lock:
                totals = self.seconds.setdefault(name, {"wall_s": 0.0, "cpu_s": 0.0})
                totals["wall_s"] += wall
                totals["cpu_s"] += used


def reembedding(
    frames: int, with_index: bool, embed_dim: int, policy: Any = None
) -> dict[str, Any]:
    """Re-embedding ``frames`` stored frames in the feature store's batches, fp32 against bf16
    matrix products; then, optionally, the bf16 re-embedding into an empty size-chosen index
    (``policy``) by ``fill_index``, the loop of ``add_stored_frames``, its database reads
    replaced by in-memory vectors (not timed)."""
    from service.index import AtlasIndex, IndexPolicy
    from service.index.builder import fill_index
    from service.ml.heads import HeadsConfig, LoopNetHeads
    from service.ml.pipeline import embed_vectors

    heads = LoopNetHeads(HeadsConfig(128, 1280, alpha=0.7, embed_dim=embed_dim)).eval()
    generator = torch.Generator().manual_seed(0)
    with torch.no_grad():  # trained-like heads: weights away from their identity initialisation
        for parameter in heads.parameters():
            parameter.add_(0.05 * torch.randn(parameter.shape, generator=generator))
    rng = np.random.default_rng(1)
    chunk = 25 * READ_BATCH  # distinct stored frames, repeated up to ``frames``
    local = rng.standard_normal((chunk, 128), dtype=np.float32)
    global_ = np.abs(rng.standard_normal((chunk, 1280), dtype=np.float32))
    local /= np.linalg.norm(local, axis=1, keepdims=True)
    global_ /= np.linalg.norm(global_, axis=1, keepdims=True)

    def inputs(ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The stored vectors of frames ``ids`` (ascending; views for a batch)."""
        start = int(ids[0]) % chunk
        if ids[-1] - ids[0] == len(ids) - 1 and start + len(ids) <= chunk:
            return local[start : start + len(ids)], global_[start : start + len(ids)]
        return local[ids % chunk], global_[ids % chunk]

    every = np.arange(frames)
    batches = [every[o : o + READ_BATCH] for o in range(0, frames, READ_BATCH)]
    out: dict[str, Any] = {"frames": frames, "embed_dim": embed_dim, "batch": READ_BATCH}
    clock = StepClock()
    for precision in ("fp32", "bf16"):
        for ids in batches:
            rows = inputs(ids)
            with clock.step(f"embed_{precision}"):
                embed_vectors(heads, *rows, precision)  # type: ignore[arg-type]
    out.update(clock.seconds)
    fp32, bf16 = (embed_vectors(heads, local, global_, p) for p in ("fp32", "bf16"))
    cosine = (fp32 * bf16).sum(1)
    out["bf16_cosine_min"] = float(cosine.min())
    out["bf16_cosine_mean"] = float(cosine.mean())
    if not with_index:
        return out
    clock = StepClock()
    robots = ["r"] * READ_BATCH

    def embedded(ids: Any) -> Iterator[tuple[np.ndarray, np.ndarray, list[str]]]:
        wanted = batches if ids is None else np.array_split(ids, -(-len(ids) // READ_BATCH))
        for batch in wanted:
            rows = inputs(np.asarray(batch))
            with clock.step("embed"):
                embeddings = embed_vectors(heads, *rows, "bf16")
            yield np.asarray(batch), embeddings, robots[: len(batch)]

    class TimedIndex(AtlasIndex):
        def prepare(self, size: int, sample: np.ndarray) -> bool:
            with clock.step("train"):
                return super().prepare(size, sample)

        def add(self, ids: np.ndarray, vectors: np.ndarray, robots: list[str]) -> int:
            with clock.step("add"):
                return super().add(ids, vectors, robots)

    index = TimedIndex(embed_dim, policy=policy or IndexPolicy(background=False))
    with clock.step("total", whole=True):
        fill_index(index, embedded, None, lambda: every)
    out["index"] = {"type": index.describe(), **clock.seconds}
    return out


def markdown(report: dict[str, Any]) -> str:
    lines = [
        "# Inference speed",
        "",
        f"Machine: {report['machine']}; precision {report['precision']}; "
        f"load average {report['load_before']} -> {report['load_after']}.",
        "",
        "| what | baseline (fp32 as loaded) wall / CPU ms | ours wall / CPU ms | "
        "speed-up wall / CPU |",
        "| --- | --- | --- | --- |",
    ]
    for section in ("local", "backbones"):
        for name, row in report.get(section, {}).items():
            if "skipped" in row:
                lines.append(f"| {name} | skipped: {row['skipped']} | | |")
                continue
            b, c = row["baseline"], row["candidate"]
            lines.append(
                f"| {name} | {b['wall_ms']:.1f} / {b['cpu_ms']:.1f} | {c['wall_ms']:.1f} / "
                f"{c['cpu_ms']:.1f} | {row['speedup_wall']:.2f}x / {row['speedup_cpu']:.2f}x |"
            )
    if "disk1024_floor" in report:
        f = report["disk1024_floor"]
        lines += [
            "",
            f"DISK@1024 ({f['precision']}): {f['gflop']:.0f} GFLOP, {f['wall_ms']:.0f} ms wall, "
            f"{f['cpu_ms']:.0f} ms CPU; {f['precision']} matmul {f['matmul_gflops_cpu']:.0f} "
            f"GFLOP per CPU s; wall / floor {f['wall_over_floor']:.2f}, CPU / floor "
            f"{f['cpu_over_floor']:.2f}.",
        ]
    for name, row in report.get("presets", {}).items():
        one, eight = row["one_frame"], row["batch8_per_frame"]
        lines.append(
            f"\nPreset {name}: one frame {one['wall_ms']:.1f} ms wall / {one['cpu_ms']:.1f} ms "
            f"CPU; in batches of 8: {eight['wall_ms']:.1f} / {eight['cpu_ms']:.1f} ms per frame; "
            f"stages {json.dumps({k: round(v, 1) for k, v in row['stages_ms'].items()})}."
        )
    if "reembedding" in report:
        r = report["reembedding"]
        lines.append(
            f"\nRe-embedding {r['frames']} frames (embed_dim {r['embed_dim']}, batches of "
            f"{r['batch']}): fp32 {_seconds(r['embed_fp32'])}; bf16 {_seconds(r['embed_bf16'])} "
            f"(cosine to fp32: min {r['bf16_cosine_min']:.5f})."
        )
        if "index" in r:
            steps = r["index"]
            lines.append(
                f"bf16 re-embedding into an empty index ({steps['type']}): "
                + "; ".join(f"{name} {_seconds(steps[name])}" for name in STEPS if name in steps)
                + "."
            )
    return "\n".join(lines) + "\n"


STEPS = ("embed", "train", "add", "total")


def _seconds(step: dict[str, float]) -> str:
    return f"{step['wall_s']:.1f} s wall / {step['cpu_s']:.1f} s CPU"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/inference_speed"))
    parser.add_argument("--threads", type=int, help="torch threads (default: torch's)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--precision", default="bf16", choices=("fp32", "bf16"))
    parser.add_argument("--reembed-frames", type=int, default=1_000_000)
    parser.add_argument("--embed-dim", type=int, default=256, help="a retrained model's")
    parser.add_argument("--no-index", action="store_true", help="skip the index build")
    parser.add_argument("--only", default="local,floor,backbones,presets,reembedding")
    add_policy_arguments(parser)
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
        import faiss

        faiss.omp_set_num_threads(args.threads)
    precision: Precision = args.precision
    only = set(args.only.split(","))
    rgb = decode_image((DATA / "gardenspoint_first10" / "query" / "0.jpg").read_bytes())
    frames = [
        decode_image((DATA / "gardenspoint_first10" / "query" / f"{i}.jpg").read_bytes())
        for i in range(8)
    ]
    report: dict[str, Any] = {
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
        f"torch {torch.__version__}, {torch.get_num_threads()} threads, native bf16 "
        f"{cpu_has_native_bf16()}",
        "precision": precision,
        "load_before": round(os.getloadavg()[0], 2),
    }
    sections: dict[str, Callable[[], Any]] = {
        "local": lambda: local_section(rgb, precision, args.repeats),
        "floor": lambda: disk_floor(rgb, precision, max(1, args.repeats // 2)),
        "backbones": lambda: backbone_section(rgb, precision, args.repeats * 4),
        "presets": lambda: preset_section(frames, precision, args.repeats),
        "reembedding": lambda: reembedding(
            args.reembed_frames,
            not args.no_index,
            args.embed_dim,
            policy_from(args, background=False),
        ),
    }
    keys = {"floor": "disk1024_floor"}
    for name, run in sections.items():
        if name in only:
            report[keys.get(name, name)] = run()
            print(f"{name} done", flush=True)
    report["load_after"] = round(os.getloadavg()[0], 2)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "inference_speed.json").write_text(json.dumps(report, indent=2))
    text = markdown(report)
    (args.out / "inference_speed.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()

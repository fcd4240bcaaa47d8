"""Per-stage latency of ingest and query: decode, DISK and XFeat at several long sides,
backbones, heads, search, geometric verification of one candidate (MNN and LightGlue matching,
RANSAC for F and for E + pose; DISK at 512 px, day query vs its night reference), database
write; then DISK against this machine's fp32 compute floor (``compute_floor.py``). Prints
medians (and p90) over repeated runs on one real frame.

    python benchmarks/stage_latency.py --image ../shared/data/gardenspoint_first10/query/0.jpg

Needs the weights in $TORCH_HOME/hub/checkpoints (``loopnet weights seed ../shared/weights``).
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path

import numpy as np
import torch

from service.errors import WeightsUnavailable
from service.index import AtlasIndex
from service.ml.aggregation import aggregate_descriptors
from service.ml.backbones import BACKBONES, BackboneConfig, GlobalBackbone, build_backbone
from service.ml.features import LocalFeatures
from service.ml.heads import HeadsConfig, LoopNetHeads
from service.ml.images import decode_image
from service.ml.local_extractors import LocalExtractorConfig, build_local_extractor
from service.ml.matching import build_matcher
from service.ml.pipeline import embed_vectors
from service.ml.two_view import camera_matrix, estimate_two_view
from service.ml.verification import VerificationConfig, Verifier, View


def timed(fn: Callable[[], object], repeats: int, warmup: int = 1) -> list[float]:
    for _ in range(warmup):
        fn()
    samples = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        samples.append((time.perf_counter() - start) * 1000.0)
    return samples


def report(name: str, samples: list[float]) -> None:
    p90 = float(np.percentile(samples, 90))
    print(
        f"| {name:<38} | {statistics.median(samples):>10.2f} | {p90:>10.2f} | {len(samples):>3} |"
    )


def verification_latency(image: Path, local: LocalFeatures, repeats: int) -> None:
    """Verification of one candidate: the query frame against its night counterpart (same
    place), matched by MNN and LightGlue, then RANSAC (fundamental; essential with intrinsics)."""
    night_path = image.parent.parent / "ref" / image.name
    night_rgb = decode_image(night_path.read_bytes())
    day_rgb = decode_image(image.read_bytes())
    extractor = build_local_extractor(LocalExtractorConfig(long_side=512, max_keypoints=1024))
    a, b = extractor.extract(day_rgb), extractor.extract(night_rgb)
    size_a, size_b = (day_rgb.shape[1], day_rgb.shape[0]), (night_rgb.shape[1], night_rgb.shape[0])
    k_a = camera_matrix(0.8 * size_a[0], 0.8 * size_a[0], size_a[0] / 2, size_a[1] / 2)
    k_b = camera_matrix(0.8 * size_b[0], 0.8 * size_b[0], size_b[0] / 2, size_b[1] / 2)
    for name in ("mnn", "lightglue"):
        try:
            matcher = build_matcher(name)
        except WeightsUnavailable as exc:
            print(f"| {name}: skipped ({exc})")
            continue
        matches = matcher.match(a, size_a, b, size_b)
        report(
            f"match {name} ({a.count}x{b.count} kp, {matches.count} m)",
            timed(partial(matcher.match, a, size_a, b, size_b), repeats),
        )
        pa, pb = a.keypoints[matches.pairs[:, 0]], b.keypoints[matches.pairs[:, 1]]
        fundamental = estimate_two_view(pa, pb)
        report(
            f"RANSAC F on {name} ({fundamental.inliers} inl)",
            timed(partial(estimate_two_view, pa, pb), repeats),
        )
        report(
            f"RANSAC E + pose on {name}",
            timed(partial(estimate_two_view, pa, pb, k_a, k_b), repeats),
        )
        verifier = Verifier(VerificationConfig(matcher=name), matcher)
        report(
            f"verify 1 candidate, {name} (match+RANSAC)",
            timed(partial(verifier.verify, View(a, size_a), View(b, size_b)), repeats),
        )


def cpu_timed(fn: Callable[[], object], repeats: int, warmup: int = 1) -> list[float]:
    """CPU milliseconds of this process (every thread) per call."""
    for _ in range(warmup):
        fn()
    samples = []
    for _ in range(repeats):
        start = time.process_time()
        fn()
        samples.append((time.process_time() - start) * 1000.0)
    return samples


def decision_cost(image: Path, repeats: int) -> None:
    """CPU cost of the loop decision (issue 25) against a default-preset query in one run: the
    query's stages (decode, DISK 512 px / 1024 kp, MobileNetV2 224, verification of 5
    candidates by MNN + RANSAC) beside today's decision (``verification.decide``) and the new
    one (``answer_evidence`` + ``decide_loop`` + ``probable_candidate``), and the inliers' zoom
    of 5 candidates with the re-rank that weighs it (stop 35), and the one extra verification
    the decision may ask for: the rival reserve when the checked candidates show one place (stop
    36), and again the sequence's place when it is not among them (stop 37), p50 CPU ms."""
    from service.app.decision import answer_evidence, probable_candidate
    from service.app.results import Candidate
    from service.app.robot_evidence import single_frame_verdict
    from service.ml.decision import decide_loop
    from service.ml.verification import decide, rerank, view_units
    from service.ml.viewpoint import DEFAULT_SCALE_TOLERANCE, viewpoint_scale

    data = image.read_bytes()
    night = (image.parent.parent / "ref" / image.name).read_bytes()
    disk = build_local_extractor(LocalExtractorConfig(long_side=512, max_keypoints=1024))
    backbone = build_backbone(BackboneConfig(name="mobilenetv2", input_size=224))
    verifier = Verifier(VerificationConfig(matcher="mnn"))
    night_rgb = decode_image(night)
    stored = View(disk.extract(night_rgb), (night_rgb.shape[1], night_rgb.shape[0]))

    def query() -> None:
        rgb = decode_image(data)
        local = disk.extract(rgb)
        backbone.describe(rgb)
        verifier.verify_many(View(local, (rgb.shape[1], rgb.shape[0])), [stored] * 5)

    asked = View(disk.extract(decode_image(data)), stored.image_size)
    found = verifier.verify(asked, stored, keep_inliers=True)
    assert found.inlier_pairs is not None
    points = (
        asked.local.keypoints[found.inlier_pairs[:, 0]],
        stored.local.keypoints[found.inlier_pairs[:, 1]],
        *view_units(asked, stored),
    )
    candidates = [
        Candidate(i, f"s{i // 5}", "r", 0.9 - i * 0.001, found.inliers - i, 0.5, 0.6, True)
        for i in range(32)
    ]

    def old() -> None:
        verdict = decide(0.9, found, threshold=0.9, verify=True)
        single_frame_verdict(1, verdict)

    def new() -> None:
        decision = decide_loop(answer_evidence(candidates, 1000, None), min_inliers=44)
        probable_candidate(single_frame_verdict(1, decision.passed), decision)

    def zoom() -> None:
        scales = [viewpoint_scale(*points) for _ in range(5)]
        rerank([0.9] * 5, [found.inliers] * 5, scales, scale_tolerance=DEFAULT_SCALE_TOLERANCE)

    def extra() -> None:
        verifier.verify_many(asked, [stored])

    q = statistics.median(cpu_timed(query, repeats))
    x = statistics.median(cpu_timed(extra, repeats))
    o = statistics.median(cpu_timed(old, repeats * 200))
    n = statistics.median(cpu_timed(new, repeats * 200))
    z = statistics.median(cpu_timed(zoom, repeats * 200))
    print("| part | p50 CPU ms |\n| --- | --- |")
    print(f"| default-preset query (decode, DISK 512, MobileNetV2, verify 5) | {q:.2f} |")
    print(f"| decision today (threshold + verified) | {o:.4f} |")
    print(f"| decision issue 25 (evidence + loop_probability + status) | {n:.4f} |")
    print(f"| added by the decision | {n - o:.4f} ({100 * (n - o) / q:.3f} % of the query) |")
    print(f"| zoom of 5 candidates + its re-rank | {z:.4f} ({100 * z / q:.3f} % of the query) |")
    print(
        f"| one more candidate verified (rival reserve or the sequence's place, when needed; "
        f"at most two) | {x:.2f} ({100 * x / q:.1f} % of the query each) |"
    )


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--image", type=Path, default=Path("../shared/data/gardenspoint_first10/query/0.jpg")
    )
    parser.add_argument("--long-sides", type=int, nargs="+", default=[256, 512, 1024])
    parser.add_argument("--xfeat-long-sides", type=int, nargs="+", default=[320, 512])
    parser.add_argument("--max-keypoints", type=int, default=1024)
    parser.add_argument(
        "--floor-long-side", type=int, default=1024, help="DISK side checked against the floor"
    )
    parser.add_argument("--floor-repeats", type=int, default=3)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument(
        "--index-size", type=int, default=10_000, help="synthetic frames in the index"
    )
    parser.add_argument(
        "--decision-only", action="store_true", help="only the loop decision's cost (issue 25)"
    )
    args = parser.parse_args()
    if args.decision_only:
        decision_cost(args.image, args.repeats)
        return

    data = args.image.read_bytes()
    rgb = decode_image(data)
    print(
        f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
        f"torch {torch.__version__}, {torch.get_num_threads()} threads"
    )
    print(f"image: {args.image} ({rgb.shape[1]}x{rgb.shape[0]}), repeats {args.repeats}\n")
    print(f"| {'stage':<38} | {'median ms':>10} | {'p90 ms':>10} | {'n':>3} |")
    print(f"|{'-' * 40}|{'-' * 12}|{'-' * 12}|{'-' * 5}|")
    report("decode (JPEG -> RGB)", timed(lambda: decode_image(data), args.repeats * 3))

    local = None
    for side in args.long_sides:
        disk = build_local_extractor(
            LocalExtractorConfig(long_side=side, max_keypoints=args.max_keypoints)
        )
        samples = timed(partial(disk.extract, rgb), args.repeats)
        local = disk.extract(rgb)
        report(f"DISK long side {side} ({local.count} kp)", samples)
    assert local is not None
    for side in args.xfeat_long_sides:
        xfeat = build_local_extractor(
            LocalExtractorConfig(name="xfeat", long_side=side, max_keypoints=args.max_keypoints)
        )
        samples = timed(partial(xfeat.extract, rgb), args.repeats)
        report(f"XFeat long side {side} ({xfeat.extract(rgb).count} kp)", samples)
    report(
        "aggregate descriptors (D)",
        timed(lambda: aggregate_descriptors(local.descriptors, local.scores), args.repeats * 3),
    )

    dims = {}
    for name, size in (("mobilenetv2", 160), ("mobilenetv2", 224), ("resnet18", 224)):
        config = BackboneConfig(name=name, input_size=size)
        try:
            backbone = build_backbone(config)
            label = f"backbone {name} {size}x{size}"
        except WeightsUnavailable:
            # Same compute with random weights: the timing holds, the vectors mean nothing.
            backbone = GlobalBackbone(config, trunk=BACKBONES[name].make_trunk())
            label = f"backbone {name} {size}x{size} (random init)"
        dims[name] = backbone.dim
        report(label, timed(partial(backbone.describe, rgb), args.repeats))

    global_dim = dims.get("mobilenetv2", 1280)
    heads = LoopNetHeads(
        HeadsConfig(local_dim=128, global_dim=global_dim), class_labels=list(range(100))
    ).eval()
    d = local.descriptors[:1].mean(0, keepdims=True).astype(np.float32)
    r = np.random.default_rng(0).normal(size=(1, global_dim)).astype(np.float32)

    def heads_once() -> None:
        embed_vectors(heads, d, r)
        heads.predict_submap(torch.from_numpy(d), torch.from_numpy(r))

    report("heads (embed + classify, 100 submaps)", timed(heads_once, args.repeats * 3))

    rng = np.random.default_rng(1)
    index = AtlasIndex(heads.config.fused_dim)
    batch = 10_000
    for start in range(0, args.index_size, batch):
        n = min(batch, args.index_size - start)
        v = rng.normal(size=(n, index.dim)).astype(np.float32)
        index.add(
            np.arange(start, start + n), v / np.linalg.norm(v, axis=1, keepdims=True), ["r"] * n
        )
    query = embed_vectors(heads, d, r)[0]
    report(
        f"search k=5, exact, {args.index_size} frames",
        timed(lambda: index.search(query, 5), args.repeats * 3),
    )

    verification_latency(args.image, local, args.repeats)

    from scratch_atlas import scratch_atlas

    from service.ml.features import FrameFeatures
    from service.storage import repository as repo
    from service.storage.db import transaction

    features = FrameFeatures(
        local,
        aggregate_descriptors(local.descriptors, local.scores),
        r[0],
        (rgb.shape[1], rgb.shape[0]),
    )
    with scratch_atlas() as (sessions, atlas, submap):

        def write() -> None:
            with transaction(sessions) as session:
                repo.add_frame(
                    session,
                    atlas=atlas,
                    submap=submap,
                    robot_id="r",
                    timestamp=None,
                    pose=None,
                    intrinsics=None,
                    features=features,
                )

        report(f"database write (SQLite WAL, {local.count} kp)", timed(write, args.repeats * 3))

    from compute_floor import FLOOR_HEADER, disk_floor_rows

    print(f"\n{FLOOR_HEADER}")
    for row in disk_floor_rows(rgb, args.floor_long_side, 2048, args.floor_repeats):
        print(row, flush=True)


if __name__ == "__main__":
    main()

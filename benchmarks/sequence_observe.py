"""What sequence scoring and temporal consistency add to one observe, through the service's own
code: :class:`service.app.sequences.SequenceScorer` on a real SQLite database of ``--frames``
frame rows and the service's :class:`AtlasIndex` (inverted file at this size).

The atlas is ``--robots`` trajectories (``synthetic_embeddings.py``, one place per frame, one
second apart). A rover then streams noisy revisits of random stretches: before each timed
observe its previous frame is committed with the matches its own search found (as ``observe``
keeps them; ``--without-proposals``: stored as ``POST /frames`` stores, so every earlier frame
is searched again) and added to the index, so every timed call also brings the process's
sequence map up to date (one frame through the index's journal). Timed: reading the robot's
recent frames and their kept matches, the map update, candidate proposal and scoring, the
margin over the best rival, and the consistency check; not timed: the newest frame's own search
(the single-frame query does it anyway).

    nice -n 10 python benchmarks/sequence_observe.py --frames 100000 --dim 512 --json out.json
"""

from __future__ import annotations

import argparse
import json
import platform
import tempfile
import time
from pathlib import Path

import numpy as np
from sqlalchemy import create_engine, insert
from sqlalchemy.orm import sessionmaker
from synthetic_embeddings import ClusteredEmbeddings, unit_rows

from service.app.filters import Selection
from service.app.robot_evidence import RobotContext
from service.app.sequences import SequenceScorer
from service.app.state import LoadedAtlas
from service.config import Settings
from service.index import AtlasIndex, IndexPolicy
from service.storage.models import Atlas, Base, Frame, FrameProposals, Submap


def run(args: argparse.Namespace) -> dict[str, object]:
    vectors = np.concatenate(
        [v for _, v in ClusteredEmbeddings(n=args.frames, dim=args.dim, per_place=1).chunks()]
    ).astype(np.float32)
    per_robot = args.frames // args.robots
    with tempfile.TemporaryDirectory() as tmp:
        engine = create_engine(f"sqlite:///{tmp}/bench.db")
        Base.metadata.create_all(engine)
        sessions = sessionmaker(engine, expire_on_commit=False)
        with sessions.begin() as session:
            session.add(Atlas(id=1, name="bench", feature_signature={}, revision=0))
            session.add(Submap(id=1, atlas_id=1, name="s0"))
        rows = [
            dict(
                id=i + 1,
                atlas_id=1,
                submap_id=1,
                robot_id=f"robot-{i // per_robot:03d}",
                timestamp=float(i % per_robot),
                width=64,
                height=32,
                keypoint_count=0,
            )
            for i in range(args.frames)
        ]
        with sessions.begin() as session:
            session.execute(insert(Frame), rows)
        start = time.perf_counter()
        index = AtlasIndex(
            args.dim, policy=IndexPolicy(background=False, train_per_list=16, kmeans_iterations=5)
        )
        ids = np.arange(1, args.frames + 1, dtype=np.int64)
        index.add(ids, vectors, [str(r["robot_id"]) for r in rows])
        build_s = time.perf_counter() - start
        state = LoadedAtlas(1, 1, None, index)  # type: ignore[arg-type]  # heads are not used
        settings = Settings(
            data_dir=Path(tmp),
            sequence_max_gap_seconds=10.0,
            sequence_seed_frames=args.seed_frames,
        )
        scorer = SequenceScorer(settings)
        with sessions() as session:  # the first use builds the process's map (not timed)
            start = time.perf_counter()
            scorer.maps.refresh(session, state)
            map_build_s = time.perf_counter() - start
        rng = np.random.default_rng(7)
        results: dict[str, object] = {}
        next_id, clock = args.frames + 1, 10_000.0
        for length in args.lengths:
            timings, cpu_timings, right = [], [], 0
            for _ in range(args.observations):
                robot = rng.integers(0, args.robots)
                end = int(robot * per_robot + rng.integers(length, per_robot))
                truth = np.arange(end - length + 1, end + 1)
                noisy = unit_rows(
                    vectors[truth]
                    + args.noise
                    * rng.standard_normal((length, args.dim), dtype=np.float32)
                    * 8
                    / np.sqrt(args.dim)
                )
                clock += 100.0  # a new stretch: a new sequence
                for j in range(length - 1):  # the rover's earlier frames, stored by observe
                    rover = np.arange(args.frames + 1, next_id)
                    found = index.search(noisy[j], 50, exclude=rover)
                    with sessions.begin() as session:
                        session.execute(
                            insert(Frame),
                            [
                                dict(
                                    id=next_id,
                                    atlas_id=1,
                                    submap_id=1,
                                    robot_id="rover",
                                    timestamp=clock + j,
                                    width=64,
                                    height=32,
                                    keypoint_count=0,
                                )
                            ],
                        )
                        if not args.without_proposals:
                            kept = np.array([h.frame_id for h in found], dtype="<i4")
                            session.add(FrameProposals(frame_id=next_id, frame_ids=kept.tobytes()))
                    index.add(np.array([next_id]), noisy[j][None], ["rover"])
                    next_id += 1
                    if j < length - 2:  # all but the last one were observed earlier
                        with sessions() as session:
                            scorer.maps.refresh(session, state)
                hits = index.search(noisy[-1], 50, exclude=np.arange(args.frames + 1, next_id))
                selection = Selection(None, np.arange(args.frames + 1, next_id, dtype=np.int64))
                robot_context = RobotContext("rover", clock + length - 1, length)
                with sessions() as session:
                    start, cpu = time.perf_counter(), time.process_time()
                    evidence = scorer.answer(
                        session, state, robot_context, noisy[-1], hits, selection
                    )
                    evidence.verdict(hits[0].frame_id, True)
                    timings.append((time.perf_counter() - start) * 1000.0)
                    cpu_timings.append((time.process_time() - cpu) * 1000.0)
                assert evidence.sequence is not None
                right += int(evidence.sequence.frame_id == end + 1)
            results[f"L={length}"] = {
                "added_ms": {
                    "p50": float(np.median(timings)),
                    "p95": float(np.percentile(timings, 95)),
                },
                "added_cpu_ms": {
                    "p50": float(np.median(cpu_timings)),
                    "p95": float(np.percentile(cpu_timings, 95)),
                },
                "top1_right": right / args.observations,
            }
    return {
        "frames": args.frames,
        "dim": args.dim,
        "robots": args.robots,
        "observations": args.observations,
        "seed_frames": args.seed_frames,
        "proposals_kept": not args.without_proposals,
        "index": index.describe(),
        "index_build_s": round(build_s, 1),
        "map_build_s": round(map_build_s, 2),
        "machine": f"{platform.machine()}, {platform.platform()}",
        "results": results,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=100_000)
    parser.add_argument("--dim", type=int, default=512)
    parser.add_argument("--robots", type=int, default=100)
    parser.add_argument("--lengths", type=int, nargs="+", default=[5, 10])
    parser.add_argument("--observations", type=int, default=100)
    parser.add_argument("--noise", type=float, default=0.5)
    parser.add_argument(
        "--seed-frames", type=int, default=0, help="LOOPNET_SEQUENCE_SEED_FRAMES (0: all)"
    )
    parser.add_argument(
        "--without-proposals",
        action="store_true",
        help="earlier frames stored without their matches (POST /frames): searched again",
    )
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    report = run(args)
    print(json.dumps(report, indent=2))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()

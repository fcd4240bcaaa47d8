"""Restore time of a large snapshot, and how long writes to another atlas wait meanwhile.

Builds an atlas of ``--frames`` frames from synthetic stored features (clustered vectors from
:mod:`benchmarks.synthetic_embeddings`, random keypoints and descriptors; no CNN), exports it,
then restores it while a thread keeps committing one small frame at a time to another atlas of
the same SQLite database. Prints the restore time and the longest of those writes (a write's
time is the wait for the write lock plus the write), as text and as one JSON line.

    python benchmarks/snapshot_restore.py --frames 10000 --keypoints 64
"""

from __future__ import annotations

import argparse
import json
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
from sqlalchemy import insert
from synthetic_embeddings import ClusteredEmbeddings

from service.app import model_versions as models_store
from service.config import Settings
from service.fleet.snapshot_restore import restore_atlas
from service.fleet.snapshots import export_atlas
from service.ml.heads import HeadsConfig
from service.storage import repository as repo
from service.storage.db import make_engine, make_session_factory, transaction, upgrade_database
from service.storage.models import Frame, FrameFeatureRow

PER_SUBMAP = 100


def build_atlas(settings: Settings, sessions, name: str, frames: int, keypoints: int) -> None:  # type: ignore[no-untyped-def]
    """An atlas of ``frames`` synthetic frames, written in bulk."""
    preset = settings.preset()
    local_dim, global_dim = preset.signature.dims
    heads = HeadsConfig(local_dim=local_dim, global_dim=global_dim, alpha=preset.alpha)
    rng = np.random.default_rng(0)
    vectors = ClusteredEmbeddings(frames, local_dim + global_dim, per_place=PER_SUBMAP)
    with transaction(sessions) as session:
        atlas = repo.create_atlas(
            session, name=name, description="", feature_signature=preset.signature.to_json()
        )
        repo.create_model_version(
            session,
            atlas_id=atlas.id,
            config=models_store.initial_version_config(heads),
            metrics={},
            weights_path=None,
            activate=True,
        )
        submaps = [
            repo.create_submap(session, atlas=atlas, name=f"s{i}").id
            for i in range((frames + PER_SUBMAP - 1) // PER_SUBMAP)
        ]
        for ids, chunk in vectors.chunks():
            frame_ids = session.scalars(
                insert(Frame).returning(Frame.id, sort_by_parameter_order=True),
                [
                    {
                        "atlas_id": atlas.id,
                        "submap_id": submaps[int(i) // PER_SUBMAP],
                        "robot_id": f"robot-{int(i) % 3}",
                        "timestamp": float(i),
                        "width": 640,
                        "height": 480,
                        "keypoint_count": keypoints,
                    }
                    for i in ids
                ],
            ).all()
            local = chunk[:, :local_dim] / np.linalg.norm(chunk[:, :local_dim], axis=1)[:, None]
            global_ = chunk[:, local_dim:] / np.linalg.norm(chunk[:, local_dim:], axis=1)[:, None]
            session.execute(
                insert(FrameFeatureRow),
                [
                    {
                        "frame_id": frame_id,
                        "descriptor_dim": local_dim,
                        "global_dim": global_dim,
                        "keypoints": (rng.random((keypoints, 2), np.float32) * 480).tobytes(),
                        "descriptors": rng.standard_normal((keypoints, local_dim))
                        .astype("<f2")
                        .tobytes(),
                        "scores": rng.random(keypoints, np.float32).tobytes(),
                        "local_vector": local[j].astype("<f4").tobytes(),
                        "global_vector": global_[j].astype("<f4").tobytes(),
                    }
                    for j, frame_id in enumerate(frame_ids)
                ],
            )


class Writer(threading.Thread):
    """Commits one small frame at a time to another atlas; records how long each took."""

    def __init__(self, sessions, atlas: str) -> None:  # type: ignore[no-untyped-def]
        super().__init__(daemon=True)
        self.sessions, self.atlas = sessions, atlas
        self.durations: list[float] = []
        self.errors: list[str] = []
        self.stop = threading.Event()

    def run(self) -> None:
        while not self.stop.is_set():
            start = time.perf_counter()
            try:
                with transaction(self.sessions) as session:
                    atlas = repo.get_atlas(session, name=self.atlas)
                    submap = repo.get_submap(session, atlas=atlas, name="s")
                    session.add(
                        Frame(
                            atlas_id=atlas.id,
                            submap_id=submap.id,
                            robot_id="writer",
                            width=1,
                            height=1,
                            keypoint_count=0,
                        )
                    )
            except Exception as exc:
                self.errors.append(f"{type(exc).__name__}: {exc}")
            self.durations.append(time.perf_counter() - start)
            time.sleep(0.02)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=10_000)
    parser.add_argument("--keypoints", type=int, default=64, help="keypoints per frame")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        settings = Settings(data_dir=Path(tmp) / "data")
        upgrade_database(settings.resolved_database_url)
        engine = make_engine(settings.resolved_database_url)
        sessions = make_session_factory(engine)
        start = time.perf_counter()
        build_atlas(settings, sessions, "source", args.frames, args.keypoints)
        built_s = time.perf_counter() - start
        archive = Path(tmp) / "source.tar"
        start = time.perf_counter()
        export_atlas(settings, sessions, "source", archive)
        export_s = time.perf_counter() - start
        with transaction(sessions) as session:
            other = repo.create_atlas(session, name="other", description="", feature_signature={})
            repo.create_submap(session, atlas=other, name="s")
        writer = Writer(sessions, "other")
        writer.start()
        time.sleep(0.5)
        start = time.perf_counter()
        restore_atlas(settings, sessions, archive, name="copy")
        restore_s = time.perf_counter() - start
        time.sleep(0.5)
        writer.stop.set()
        writer.join()
        engine.dispose()
        result = {
            "frames": args.frames,
            "keypoints_per_frame": args.keypoints,
            "archive_mb": round(archive.stat().st_size / 1e6, 1),
            "build_s": round(built_s, 2),
            "export_s": round(export_s, 2),
            "restore_s": round(restore_s, 2),
            "concurrent_writes": len(writer.durations),
            "longest_write_s": round(max(writer.durations), 3),
            "write_errors": writer.errors[:3],
        }
    print(
        f"restored {args.frames} frames ({result['archive_mb']} MB archive) in "
        f"{result['restore_s']} s; longest of {result['concurrent_writes']} concurrent writes: "
        f"{result['longest_write_s']} s"
    )
    print(json.dumps(result))


if __name__ == "__main__":
    main()

"""How long a frame committed through one API process takes to be searchable in another.

Two ``AtlasService`` instances (as two processes would hold them: own indexes, own
``ChangeFollower`` thread) share one database; one ingests frames with synthetic features of
the real dimensions (the CNNs are not what is timed), the other's index is polled every
millisecond for each new frame id. Also times one catch-up of a burst of frames.

    python benchmarks/sync_delay.py --database-url postgresql+psycopg://postgres@127.0.0.1/test
    python benchmarks/sync_delay.py --sync-seconds 0.25 1.0 --frames 20 --burst 1000
"""

from __future__ import annotations

import argparse
import os
import platform
import random
import statistics
import tempfile
import time
import uuid
from pathlib import Path

import numpy as np
from sqlalchemy import create_engine, text
from sqlalchemy.engine import make_url

from service.atlas.catalog import AtlasService
from service.atlas.change_feed import ChangeFollower
from service.atlas.ingest import FrameFields
from service.config import Settings
from service.ml.features import FrameFeatures, LocalFeatures
from service.ml.pipeline import FeaturePipeline
from service.storage.db import make_engine, make_session_factory, upgrade_database

rng = np.random.default_rng(0)


def synthetic_features(local_dim: int, global_dim: int, keypoints: int = 512) -> FrameFeatures:
    def unit(*shape: int) -> np.ndarray:
        v = rng.standard_normal(shape).astype(np.float32)
        return v / np.linalg.norm(v, axis=-1, keepdims=True)

    return FrameFeatures(
        local=LocalFeatures(
            keypoints=rng.uniform(0, 256, (keypoints, 2)).astype(np.float32),
            descriptors=unit(keypoints, local_dim),
            scores=rng.uniform(0, 1, keypoints).astype(np.float32),
        ),
        local_vector=unit(local_dim),
        global_vector=unit(global_dim),
        image_size=(256, 144),
    )


def scratch_database(url: str | None, tmp: Path) -> tuple[str, str | None]:
    """A fresh database: a new PostgreSQL database beside ``url``, or a SQLite file."""
    if url is None:
        return f"sqlite:///{tmp / 'bench.sqlite3'}", None
    name = f"loopnet_bench_{uuid.uuid4().hex[:10]}"
    with create_engine(url, isolation_level="AUTOCOMMIT").connect() as connection:
        connection.execute(text(f'CREATE DATABASE "{name}"'))
    return make_url(url).set(database=name).render_as_string(hide_password=False), name


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--database-url", help="PostgreSQL server URL (default: SQLite)")
    parser.add_argument("--sync-seconds", type=float, nargs="+", default=[0.25, 1.0])
    parser.add_argument("--frames", type=int, default=20, help="frames timed one by one")
    parser.add_argument("--burst", type=int, default=1000, help="frames in the burst")
    args = parser.parse_args()

    with tempfile.TemporaryDirectory() as tmp:
        url, scratch = scratch_database(args.database_url, Path(tmp))
        settings = Settings(data_dir=Path(tmp) / "data", database_url=url, long_side=256)
        pipeline = FeaturePipeline(settings.preset())
        upgrade_database(url)
        engine = make_engine(url)
        sessions = make_session_factory(engine)
        writer = AtlasService(settings, sessions, pipeline)
        reader = AtlasService(settings, sessions, pipeline)
        atlas = writer.create_atlas("bench")
        writer.create_submap("bench", "s")
        dims = pipeline.heads_config()
        reader.loaded(atlas.id)
        print(
            f"machine: {platform.machine()}, {os.cpu_count()} CPUs; database: "
            f"{make_url(url).get_backend_name()}"
        )
        for interval in args.sync_seconds:
            follower = ChangeFollower(
                sessions, reader.follow, interval=interval, retention_seconds=3600
            )
            follower.start()
            delays = []
            for _ in range(args.frames):
                time.sleep(random.uniform(0, interval))
                frame = writer.ingest_features(
                    atlas_name="bench",
                    fields=FrameFields("s", "r"),
                    features=synthetic_features(dims.local_dim, dims.global_dim),
                )
                start = time.perf_counter()
                while frame.id not in set(reader.loaded(atlas.id).index.ids().tolist()):
                    time.sleep(0.001)
                delays.append(time.perf_counter() - start)
            follower.stop()
            ms = sorted(d * 1000 for d in delays)
            print(
                f"LOOPNET_SYNC_SECONDS={interval}: {len(ms)} frames, delay median "
                f"{statistics.median(ms):.0f} ms, p95 {ms[int(0.95 * (len(ms) - 1))]:.0f} ms, "
                f"max {ms[-1]:.0f} ms"
            )

        for _ in range(args.burst):
            writer.ingest_features(
                atlas_name="bench",
                fields=FrameFields("s", "r"),
                features=synthetic_features(dims.local_dim, dims.global_dim, keypoints=64),
            )
        follower = ChangeFollower(sessions, reader.follow, interval=1.0, retention_seconds=3600)
        start = time.perf_counter()
        follower.step()
        print(
            f"catch-up of a burst of {args.burst} frames: "
            f"{(time.perf_counter() - start) * 1000:.0f} ms"
        )
        engine.dispose()
        if scratch is not None:
            with create_engine(args.database_url, isolation_level="AUTOCOMMIT").connect() as c:
                c.execute(text(f'DROP DATABASE "{scratch}" WITH (FORCE)'))


if __name__ == "__main__":
    main()

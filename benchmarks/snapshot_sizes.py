"""What a snapshot export writes per frame: the figures the snapshot limits' defaults come from.

Builds an atlas of ``--frames`` synthetic frames at a preset's feature sizes with ``--keypoints``
keypoints each (random descriptors: they compress as little as real ones) and a real
thumbnail each (Gardens Point frames, made as ingest makes them), exports it with the
service's own export, then prints each member's bytes per frame, the bytes ``features.npz``
inflates to per frame, and how many such frames fit the limits given (default: the settings'
defaults), as text and one JSON line.

    python benchmarks/snapshot_sizes.py --preset default --keypoints 1024 --frames 300
"""

from __future__ import annotations

import argparse
import json
import os
import tarfile
import tempfile
import zipfile
from pathlib import Path

from snapshot_restore import build_atlas
from sqlalchemy import insert, select

from service.config import Settings
from service.fleet.snapshots import export_atlas
from service.ml.thumbnails import make_thumbnail
from service.storage.db import make_engine, make_session_factory, transaction, upgrade_database
from service.storage.models import Frame, FrameThumbnail

SHARED = Path(os.environ.get("LOOPNET_SHARED_DIR", Path(__file__).resolve().parents[2] / "shared"))
DATA = SHARED / "data" / "gardenspoint_first10"


def add_thumbnails(sessions, atlas_name: str) -> None:  # type: ignore[no-untyped-def]
    from service.ml.images import decode_image

    jpegs = [make_thumbnail(decode_image(p.read_bytes())) for p in sorted(DATA.glob("*/*.jpg"))]
    with transaction(sessions) as session:
        ids = session.scalars(select(Frame.id).order_by(Frame.id)).all()
        session.execute(
            insert(FrameThumbnail),
            [{"frame_id": i, "jpeg": jpegs[n % len(jpegs)]} for n, i in enumerate(ids)],
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="default")
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--keypoints", type=int, default=1024)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        settings = Settings(data_dir=Path(tmp), model_preset=args.preset)
        upgrade_database(settings.resolved_database_url)
        sessions = make_session_factory(make_engine(settings.resolved_database_url))
        build_atlas(settings, sessions, "source", args.frames, args.keypoints)
        add_thumbnails(sessions, "source")
        archive = Path(tmp) / "source.tar"
        export_atlas(settings, sessions, "source", archive)
        with tarfile.open(archive) as tar:
            members = {m.name: m.size for m in tar.getmembers()}
            npz = tar.extractfile("features.npz")
            assert npz is not None
            with zipfile.ZipFile(npz) as zipped:
                inflated = sum(info.file_size for info in zipped.infolist())
        archive_bytes = archive.stat().st_size
    per_frame = {name: round(size / args.frames) for name, size in sorted(members.items())}
    largest = max(members.values()) / args.frames
    defaults = Settings()
    result = {
        "preset": args.preset,
        "keypoints": args.keypoints,
        "frames": args.frames,
        "archive_bytes_per_frame": round(archive_bytes / args.frames),
        "member_bytes_per_frame": per_frame,
        "features_inflated_bytes_per_frame": round(inflated / args.frames),
        "frames_within_defaults": {
            "upload (max_snapshot_bytes)": int(
                defaults.max_snapshot_bytes * args.frames / archive_bytes
            ),
            "largest member (snapshot_max_member_bytes)": int(
                defaults.snapshot_max_member_bytes / largest
            ),
            "members and inflated arrays (snapshot_max_total_bytes)": int(
                defaults.snapshot_max_total_bytes * args.frames / max(archive_bytes, inflated)
            ),
        },
    }
    print(
        f"{args.preset} preset, {args.keypoints} keypoints: "
        f"{result['archive_bytes_per_frame']} archive bytes a frame, features.npz "
        f"{per_frame['features.npz']} (inflating to {result['features_inflated_bytes_per_frame']})"
    )
    for limit, frames in result["frames_within_defaults"].items():
        print(f"  {limit}: {frames} frames")
    print(json.dumps(result))


if __name__ == "__main__":
    main()

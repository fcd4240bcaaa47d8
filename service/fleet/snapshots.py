"""Atlas snapshots: one archive with everything an atlas is, restorable on another deployment.

The archive is a tar file:

- ``manifest.json``: format and format version, the schema revision and feature signature it
  was written with, row counts, the SHA-256 of every other member;
- ``atlas.json``, ``submaps.jsonl``, ``frames.jsonl``, ``model_versions.jsonl``,
  ``loop_closures.jsonl``: the rows, one JSON object a line (ids are the source's; restore maps
  them to new ones);
- ``features.npz``: every frame's stored features as arrays (ragged keypoints by offsets);
- ``thumbnails.npz``: the frames' thumbnails (absent from archives written before them);
- ``models/v<N>.pt``: trained heads; ``index.faiss``: the active version's FAISS index.

This module writes it; :mod:`service.fleet.snapshot_restore` reads it back without trusting it
(:mod:`service.fleet.snapshot_archive` for the archive, :mod:`service.fleet.snapshot_rows` for
the rows, arrays and weights).
"""

from __future__ import annotations

import hashlib
import io
import json
import tarfile
from collections.abc import Iterable
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np
from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from service import __version__
from service.app import model_versions as models_store
from service.app import thumbnails
from service.config import Settings
from service.errors import Conflict
from service.fleet.snapshot_archive import (
    FORMAT,
    FORMAT_VERSION,
    calibration_member,
    head_revision,
    weights_member,
)
from service.index import AtlasIndex
from service.index.builder import add_stored_frames
from service.ml.active_model import ActiveModel
from service.storage import repository as repo
from service.storage.feature_store import global_vector_of
from service.storage.models import Base, Frame, FrameFeatureRow, LoopClosure, Submap

# ----- rows <-> JSON -------------------------------------------------------------------------


def _row(obj: Base, skip: Iterable[str] = ()) -> dict[str, Any]:
    """A model row as JSON-able values (datetimes as ISO 8601)."""
    out: dict[str, Any] = {}
    for column in obj.__table__.columns:
        if column.key in skip:
            continue
        value = getattr(obj, column.key)
        out[column.key] = value.isoformat() if isinstance(value, datetime) else value
    return out


def _jsonl(rows: Iterable[dict[str, Any]]) -> bytes:
    return "".join(json.dumps(r, sort_keys=True) + "\n" for r in rows).encode()


# ----- export --------------------------------------------------------------------------------


def _features_npz(rows: list[FrameFeatureRow]) -> bytes:
    counts = np.array([len(r.scores) // 4 for r in rows], np.int64)
    dims = {(r.descriptor_dim, r.global_dim) for r in rows}
    if len(dims) > 1:
        raise Conflict(f"frames of one atlas have different feature sizes: {sorted(dims)}")
    descriptor_dim, global_dim = dims.pop() if dims else (0, 0)

    def joined(field: str, dtype: str, width: int) -> np.ndarray:
        parts = [np.frombuffer(getattr(r, field), dtype).reshape(-1, width) for r in rows]
        return np.concatenate(parts) if parts else np.zeros((0, width), dtype)

    buffer = io.BytesIO()
    np.savez_compressed(
        buffer,
        frame_ids=np.array([r.frame_id for r in rows], np.int64),
        keypoint_counts=counts,
        descriptor_dim=np.int64(descriptor_dim),
        global_dim=np.int64(global_dim),
        keypoints=joined("keypoints", "<f4", 2),
        descriptors=joined("descriptors", "<f2", max(descriptor_dim, 1)),
        scores=joined("scores", "<f4", 1)[:, 0],
        local_vectors=joined("local_vector", "<f4", max(descriptor_dim, 1)),
        global_vectors=np.stack([global_vector_of(r.global_vector, global_dim) for r in rows])
        if rows
        else np.zeros((0, max(global_dim, 1)), "<f4"),
    )
    return buffer.getvalue()


def export_atlas(
    settings: Settings, sessions: sessionmaker[Session], atlas_name: str, path: Path
) -> dict[str, Any]:
    """Write atlas ``atlas_name`` to the archive ``path``; returns the manifest."""
    members: dict[str, bytes] = {}
    with sessions() as session:
        atlas = repo.get_atlas(session, name=atlas_name)
        frames = list(
            session.scalars(select(Frame).where(Frame.atlas_id == atlas.id).order_by(Frame.id))
        )
        feature_rows = list(
            session.scalars(
                select(FrameFeatureRow)
                .join(Frame, Frame.id == FrameFeatureRow.frame_id)
                .where(Frame.atlas_id == atlas.id)
                .order_by(FrameFeatureRow.frame_id)
            )
        )
        submaps = list(
            session.scalars(select(Submap).where(Submap.atlas_id == atlas.id).order_by(Submap.id))
        )
        versions = repo.list_model_versions(session, atlas_id=atlas.id)
        closures = list(
            session.scalars(select(LoopClosure).where(LoopClosure.atlas_id == atlas.id))
        )
        members["atlas.json"] = json.dumps(
            _row(atlas, skip=("id", "revision")), sort_keys=True
        ).encode()
        members["submaps.jsonl"] = _jsonl(_row(s, skip=("atlas_id",)) for s in submaps)
        members["frames.jsonl"] = _jsonl(_row(f, skip=("atlas_id",)) for f in frames)
        members["loop_closures.jsonl"] = _jsonl(_row(c, skip=("id", "atlas_id")) for c in closures)
        members["features.npz"] = _features_npz(feature_rows)
        version_rows = []
        for version in versions:
            row = _row(version, skip=("id", "atlas_id", "weights_path"))
            row["weights"] = None
            weights = models_store.weights_of(version, settings.models_dir)
            if weights is not None:
                row["weights"] = weights_member(version.version)
                members[row["weights"]] = weights.read_bytes()
            calibration = models_store.VersionConfig.of(version).calibration
            if calibration is not None:
                fitted = Path(calibration["path"])
                fitted = fitted if fitted.is_absolute() else settings.models_dir / fitted
                row["calibration_file"] = calibration_member(version.version)
                members[row["calibration_file"]] = fitted.read_bytes()
            version_rows.append(row)
        members["model_versions.jsonl"] = _jsonl(version_rows)
        active = repo.active_model_version(session, atlas_id=atlas.id)
        model = ActiveModel(
            models_store.load_heads(active, settings.models_dir),
            models_store.load_calibration(active, settings.models_dir),
        )
        index = AtlasIndex(model.dim)
        add_stored_frames(session, atlas.id, model, index)
        members["index.faiss"] = index.to_bytes()
        members[thumbnails.SNAPSHOT_MEMBER] = thumbnails.export_member(session, atlas.id)
        manifest = {
            "format": FORMAT,
            "format_version": FORMAT_VERSION,
            "schema_revision": head_revision(),
            "loopnet_version": __version__,
            "atlas": atlas.name,
            "feature_signature": atlas.feature_signature,
            "active_model_version": active.version,
            "counts": {
                "submaps": len(submaps),
                "frames": len(frames),
                "model_versions": len(versions),
                "loop_closures": len(closures),
                "indexed": index.size,
            },
            "checksums": {name: hashlib.sha256(data).hexdigest() for name, data in members.items()},
        }
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp_path = path.with_name(path.name + ".tmp")
    with tarfile.open(tmp_path, "w") as archive:
        for name, data in [
            ("manifest.json", json.dumps(manifest, indent=2).encode()),
            *members.items(),
        ]:
            info = tarfile.TarInfo(name)
            info.size = len(data)
            archive.addfile(info, io.BytesIO(data))
    tmp_path.replace(path)
    return manifest

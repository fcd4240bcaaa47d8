"""Restoring an atlas snapshot (the archive :mod:`service.fleet.snapshots` writes) as a new atlas.

A restore reads the archive within size limits (:mod:`service.fleet.snapshot_archive`), its
members streamed to a temporary folder (``TMPDIR``: it needs about the archive's size plus the
inflated features there), refuses an unknown format version, an unknown schema revision or
features of another signature than the restoring service extracts, and validates every row,
array, weights and calibration file (:mod:`service.fleet.snapshot_rows`) before it writes
anything. It then writes in short transactions under a hidden name, renamed in the last one; a
failure deletes what was written. Each transaction also marks the hidden atlas as alive
(its ``created_at``, set to the restore's time at the end), so that a process starting after
a restore was killed (SIGKILL, power loss) can tell an abandoned one from a running one:
:func:`service.fleet.atlas_repair.clean_unfinished_restores` deletes those silent for
:data:`ABANDONED_AFTER` and reports the others. Frames get new ids; the index is rebuilt from
the archived features with the active heads and calibration (cheap: no CNN), so a FAISS file
from elsewhere is never parsed.
"""

from __future__ import annotations

import logging
import shutil
import tempfile
import uuid
from collections.abc import Iterable
from datetime import timedelta
from pathlib import Path

import numpy as np
from sqlalchemy import delete, insert, select, update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session, sessionmaker

from service.app import model_versions as models_store
from service.app import thumbnails
from service.app.names import validate_name
from service.config import Settings
from service.errors import Conflict, InvalidInput
from service.fleet.snapshot_archive import known_revisions, read_archive
from service.fleet.snapshot_rows import DecodedSnapshot, decode_snapshot
from service.fleet.snapshot_schema import FrameRow
from service.index import AtlasIndex
from service.ml.features import as_stored
from service.ml.pipeline import embed_vectors
from service.storage import repository as repo
from service.storage.db import transaction
from service.storage.feature_store import global_vector_bytes
from service.storage.models import (
    Atlas,
    Frame,
    FrameFeatureRow,
    LoopClosure,
    ModelVersion,
    Submap,
    utcnow,
)

log = logging.getLogger(__name__)

# Frames written per transaction: bounded in bytes so that a concurrent writer never waits
# long for SQLite's write lock.
BATCH_BYTES = 4 * 1024 * 1024
EMBED_CHUNK = 4096  # frames embedded at once
# Restores in progress are atlases under a name the API refuses, so no request can address
# them and listings skip them; the last transaction gives them their real name.
RESTORING_PREFIX = ".restoring-"
# A hidden atlas not marked alive for this long belongs to a restore that was killed: every
# write transaction marks it, and the longest step between two (the index build) takes
# minutes at the atlas sizes export archives hold.
ABANDONED_AFTER = timedelta(minutes=15)


def restore_atlas(
    settings: Settings, sessions: sessionmaker[Session], path: Path, *, name: str | None = None
) -> str:
    """Restore the archive ``path`` as a new atlas (``name`` or the archived one's).

    Everything is read, decoded and validated first, with no database lock held; the rows are
    then written in short batches under a hidden name, and a failure deletes what was written.
    """
    with tempfile.TemporaryDirectory(prefix="loopnet-restore-") as folder:
        return _restore(settings, sessions, path, name, Path(folder))


def _restore(
    settings: Settings,
    sessions: sessionmaker[Session],
    path: Path,
    name: str | None,
    folder: Path,
) -> str:
    limits = settings.snapshot_limits
    archive = read_archive(path, limits, folder)
    if archive.manifest.schema_revision not in known_revisions():
        raise InvalidInput(
            f"the snapshot was written at schema revision {archive.manifest.schema_revision!r}, "
            "which this LoopNet does not know: restore it with a newer LoopNet"
        )
    preset = settings.preset()
    expected = preset.signature
    if not expected.matches(archive.manifest.feature_signature):
        raise Conflict(
            f"the snapshot holds features {archive.manifest.feature_signature}, but this "
            f"deployment extracts {expected.to_json()}; restore it on a service running the "
            "snapshot's settings"
        )
    name = validate_name("atlas", name or archive.manifest.atlas)
    with sessions() as session:
        if session.scalar(select(Atlas.id).where(Atlas.name == name)) is not None:
            raise Conflict(f"atlas '{name}' already exists")
    snapshot = decode_snapshot(archive, limits, expected.dims, folder)
    if not expected.matches(snapshot.atlas.feature_signature):
        raise InvalidInput("the snapshot's atlas.json disagrees with its manifest's features")
    vectors = _embeddings(snapshot)
    written: list[Path] = []
    atlas_id: int | None = None
    try:
        atlas_id, submap_map = _write_atlas(settings, sessions, snapshot)
        frame_map = _write_frames(sessions, atlas_id, snapshot, submap_map)
        with transaction(sessions) as session:
            _mark_alive(session, atlas_id)  # the index build is the longest step
        _write_files(settings, atlas_id, snapshot, vectors, submap_map, frame_map, written)
        with transaction(sessions) as session:
            _write_loop_closures(session, atlas_id, snapshot, submap_map, frame_map)
            thumbnails.restore_member(
                session,
                archive.files.get(thumbnails.SNAPSHOT_MEMBER),
                frame_map,
                folder,
                limits.max_total_bytes,
            )
            session.execute(
                update(Atlas).where(Atlas.id == atlas_id).values(name=name, created_at=utcnow())
            )
    except BaseException as exc:
        _undo(settings, sessions, atlas_id, written)
        if isinstance(exc, IntegrityError):  # a concurrent create took the name meanwhile
            raise Conflict(f"atlas '{name}' already exists") from exc
        raise
    return name


def _heads_inputs(
    snapshot: DecodedSnapshot, start: int, stop: int
) -> tuple[np.ndarray, np.ndarray]:
    """The active heads' inputs of frames ``start:stop``: the stored vectors, or the
    calibrated branches of the stored descriptors."""
    features, calibration = snapshot.features, snapshot.active.calibration
    # R rounded as the store keeps it, so the restored embedding is the stored frame's
    global_vectors = as_stored(features.global_vectors[start:stop])
    if calibration is None:
        return np.array(features.local_vectors[start:stop]), global_vectors  # writable copies
    offsets = features.offsets
    descriptors = [
        features.descriptors[offsets[i] : offsets[i + 1]].astype(np.float32)
        for i in range(start, min(stop, len(features.frame_ids)))
    ]
    scores = [
        np.array(features.scores[offsets[i] : offsets[i + 1]])
        for i in range(start, min(stop, len(features.frame_ids)))
    ]
    return calibration.branch_vectors(descriptors, scores, global_vectors)


def _embeddings(snapshot: DecodedSnapshot) -> np.ndarray:
    """Every frame's embedding under the active version (the index is rebuilt, never read:
    a FAISS file from elsewhere is not parsed)."""
    heads, features = snapshot.active.heads, snapshot.features
    chunks = [
        embed_vectors(heads, *_heads_inputs(snapshot, start, start + EMBED_CHUNK))
        for start in range(0, len(features.frame_ids), EMBED_CHUNK)
    ]
    if not chunks:
        return np.zeros((0, heads.config.fused_dim), np.float32)
    return np.concatenate(chunks)


def _write_atlas(
    settings: Settings, sessions: sessionmaker[Session], snapshot: DecodedSnapshot
) -> tuple[int, dict[int, int]]:
    """The atlas under its hidden name, its submaps and its model versions; returns the atlas
    id and the submap ids by archived id."""
    with transaction(sessions) as session:
        atlas = repo.create_atlas(
            session,
            name=RESTORING_PREFIX + uuid.uuid4().hex,
            description=snapshot.atlas.description,
            feature_signature=snapshot.atlas.feature_signature,
        )
        new_ids = (
            session.scalars(
                insert(Submap).returning(Submap.id, sort_by_parameter_order=True),
                [
                    {"atlas_id": atlas.id, "name": s.name, "created_at": s.created_at}
                    for s in snapshot.submaps
                ],
            ).all()
            if snapshot.submaps
            else []
        )
        submap_map = {s.id: new for s, new in zip(snapshot.submaps, new_ids, strict=True)}
        for version in snapshot.versions:
            row = version.row
            weights_path = None
            if row.weights is not None:
                weights_path = models_store.row_weights_path(
                    settings.models_dir, atlas.id, row.version
                )
            config = row.config.model_dump()
            if config["calibration"] is None:
                del config["calibration"]
            else:  # the calibration file is written under the new atlas
                target = models_store.calibration_file(settings.models_dir, atlas.id, row.version)
                config["calibration"]["path"] = str(target.relative_to(settings.models_dir))
            session.add(
                ModelVersion(
                    atlas_id=atlas.id,
                    version=row.version,
                    config=config,
                    metrics=row.metrics,
                    weights_path=weights_path,
                    is_active=row.is_active,
                    created_at=row.created_at,
                )
            )
        return atlas.id, submap_map


def _batches(snapshot: DecodedSnapshot) -> Iterable[range]:
    """Ranges of frames of about ``BATCH_BYTES`` stored features each."""
    features = snapshot.features
    per_keypoint = 2 * 4 + features.descriptor_dim * 2 + 4
    per_frame = 4 * (features.descriptor_dim + features.global_dim)
    start, size = 0, 0
    for i in range(len(snapshot.frames)):
        size += per_frame + per_keypoint * int(features.offsets[i + 1] - features.offsets[i])
        if size >= BATCH_BYTES:
            yield range(start, i + 1)
            start, size = i + 1, 0
    if start < len(snapshot.frames):
        yield range(start, len(snapshot.frames))


def _write_frames(
    sessions: sessionmaker[Session],
    atlas_id: int,
    snapshot: DecodedSnapshot,
    submap_map: dict[int, int],
) -> dict[int, int]:
    """Frames and their features in short transactions; returns new frame ids by archived id."""
    features = snapshot.features
    frame_map: dict[int, int] = {}
    columns = [c for c in FrameRow.model_fields if c not in ("id", "submap_id")]
    for batch in _batches(snapshot):
        frames = [snapshot.frames[i] for i in batch]
        with transaction(sessions) as session:
            _mark_alive(session, atlas_id)
            new_ids = session.scalars(
                insert(Frame).returning(Frame.id, sort_by_parameter_order=True),
                [
                    {
                        "atlas_id": atlas_id,
                        "submap_id": submap_map[f.submap_id],
                        **{c: getattr(f, c) for c in columns},
                    }
                    for f in frames
                ],
            ).all()
            rows = []
            for i, frame, new_id in zip(batch, frames, new_ids, strict=True):
                a, b = int(features.offsets[i]), int(features.offsets[i + 1])
                frame_map[frame.id] = new_id
                rows.append(
                    {
                        "frame_id": new_id,
                        "descriptor_dim": features.descriptor_dim,
                        "global_dim": features.global_dim,
                        "keypoints": features.keypoints[a:b].tobytes(),
                        "descriptors": features.descriptors[a:b].tobytes(),
                        "scores": features.scores[a:b].tobytes(),
                        "local_vector": features.local_vectors[i].tobytes(),
                        "global_vector": global_vector_bytes(features.global_vectors[i]),
                    }
                )
            session.execute(insert(FrameFeatureRow), rows)
    return frame_map


def _write_files(
    settings: Settings,
    atlas_id: int,
    snapshot: DecodedSnapshot,
    vectors: np.ndarray,
    submap_map: dict[int, int],
    frame_map: dict[int, int],
    written: list[Path],
) -> None:
    """Calibrations, weights (their classifier relabelled with the new submap ids) and the
    active version's index under the new frame ids; each file is listed in ``written`` before
    it is written."""
    for version in snapshot.versions:
        if version.calibration_file is not None:
            path = models_store.calibration_file(settings.models_dir, atlas_id, version.row.version)
            written.append(path)
            path.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(version.calibration_file, path)
        if version.row.weights is None:
            continue
        heads = version.heads
        heads.class_labels = [submap_map[label] for label in heads.class_labels]
        target = models_store.weights_file(settings.models_dir, atlas_id, version.row.version)
        written.append(target)
        heads.save(target)
    index = AtlasIndex(snapshot.active.heads.config.fused_dim)
    ids = np.array([frame_map[f.id] for f in snapshot.frames], np.int64)
    index.add(ids, vectors, [f.robot_id for f in snapshot.frames])
    index.wait_rebuilt()
    target = models_store.index_file(settings.index_dir, atlas_id, snapshot.active.row.version)
    written.append(target)
    index.save(target)


def _mark_alive(session: Session, atlas_id: int) -> None:
    """Say the restore of hidden atlas ``atlas_id`` is still running (see ABANDONED_AFTER)."""
    session.execute(update(Atlas).where(Atlas.id == atlas_id).values(created_at=utcnow()))


def _write_loop_closures(
    session: Session,
    atlas_id: int,
    snapshot: DecodedSnapshot,
    submap_map: dict[int, int],
    frame_map: dict[int, int],
) -> None:
    if not snapshot.loop_closures:
        return
    session.execute(
        insert(LoopClosure),
        [
            {
                **c.model_dump(),
                "atlas_id": atlas_id,
                "frame_id": frame_map[c.frame_id],
                "submap_id": submap_map[c.submap_id],
                "query_frame_id": (
                    frame_map[c.query_frame_id] if c.query_frame_id is not None else None
                ),
            }
            for c in snapshot.loop_closures
        ],
    )


def _undo(
    settings: Settings, sessions: sessionmaker[Session], atlas_id: int | None, written: list[Path]
) -> None:
    """Delete a failed restore's atlas (its rows cascade) and its files."""
    for file in written:
        file.unlink(missing_ok=True)
    if atlas_id is None:
        return
    shutil.rmtree(models_store.atlas_models_dir(settings.models_dir, atlas_id), ignore_errors=True)
    try:
        with transaction(sessions) as session:
            session.execute(delete(Atlas).where(Atlas.id == atlas_id))
    except Exception:
        log.exception("a failed restore's atlas %d could not be deleted", atlas_id)

"""Atlas snapshots: one archive with everything an atlas is, restorable on another deployment.

The archive is a tar file:

- ``manifest.json``: format and format version, the schema revision and feature signature it
  was written with, row counts, the SHA-256 of every other member;
- ``atlas.json``, ``submaps.jsonl``, ``frames.jsonl``, ``model_versions.jsonl``,
  ``loop_closures.jsonl``: the rows, one JSON object a line (ids are the source's; restore maps
  them to new ones);
- ``features.npz``: every frame's stored features as arrays (ragged keypoints by offsets);
- ``models/v<N>.pt``: trained heads; ``index.faiss``: the active version's FAISS index.

A restore checks the manifest and checksums and refuses an unknown format version, an unknown
schema revision or features of another signature than the restoring service extracts, then
writes every row in one transaction under the same or a new atlas name (a failure leaves
nothing). Frames get new ids; the index is re-keyed to them, so no embedding is recomputed.
"""

from __future__ import annotations

import hashlib
import io
import json
import logging
import tarfile
from collections.abc import Iterable
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np
from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from service import __version__
from service.atlas import model_versions as models_store
from service.atlas.names import validate_name
from service.config import Settings
from service.errors import Conflict, InvalidInput
from service.index import AtlasIndex
from service.index.builder import add_stored_frames
from service.ml.active_model import ActiveModel
from service.ml.presets import preset_signature
from service.storage import repository as repo
from service.storage.db import MIGRATIONS_DIR, transaction
from service.storage.models import (
    Base,
    Frame,
    FrameFeatureRow,
    LoopClosure,
    ModelVersion,
    Submap,
    UTCDateTime,
)

log = logging.getLogger(__name__)

FORMAT = "loopnet-atlas-snapshot"
FORMAT_VERSION = 1


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


def _values(model: type[Base], row: dict[str, Any], drop: Iterable[str]) -> dict[str, Any]:
    """Keyword arguments for ``model`` from an archived row: known columns only, minus ``drop``."""
    out: dict[str, Any] = {}
    for column in model.__table__.columns:
        if column.key in drop or column.key not in row:
            continue
        value = row[column.key]
        if value is not None and isinstance(column.type, UTCDateTime):
            value = datetime.fromisoformat(value)
        out[column.key] = value
    return out


def _jsonl(rows: Iterable[dict[str, Any]]) -> bytes:
    return "".join(json.dumps(r, sort_keys=True) + "\n" for r in rows).encode()


def _read_jsonl(data: bytes) -> list[dict[str, Any]]:
    return [json.loads(line) for line in data.decode().splitlines() if line.strip()]


def head_revision() -> str:
    from alembic.config import Config
    from alembic.script import ScriptDirectory

    config = Config()
    config.set_main_option("script_location", str(MIGRATIONS_DIR))
    head = ScriptDirectory.from_config(config).get_current_head()
    assert head is not None
    return head


def known_revisions() -> set[str]:
    from alembic.config import Config
    from alembic.script import ScriptDirectory

    config = Config()
    config.set_main_option("script_location", str(MIGRATIONS_DIR))
    return {s.revision for s in ScriptDirectory.from_config(config).walk_revisions()}


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
        global_vectors=joined("global_vector", "<f4", max(global_dim, 1)),
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
            if version.weights_path is not None:
                weights = Path(version.weights_path)
                weights = weights if weights.is_absolute() else settings.models_dir / weights
                row["weights"] = f"models/v{version.version}.pt"
                members[row["weights"]] = weights.read_bytes()
            calibration = models_store.VersionConfig.of(version).calibration
            if calibration is not None:
                fitted = Path(calibration["path"])
                fitted = fitted if fitted.is_absolute() else settings.models_dir / fitted
                row["calibration_file"] = f"models/v{version.version}-calibration.npz"
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


# ----- restore -------------------------------------------------------------------------------


def read_archive(path: Path) -> tuple[dict[str, Any], dict[str, bytes]]:
    """The manifest and the members of an archive, checked against the manifest."""
    try:
        with tarfile.open(path, "r") as archive:
            members = {
                m.name: archive.extractfile(m).read()  # type: ignore[union-attr]
                for m in archive.getmembers()
                if m.isfile()
            }
    except (tarfile.TarError, OSError) as exc:
        raise InvalidInput(f"{path} is not a readable snapshot archive: {exc}") from exc
    try:
        manifest = json.loads(members.pop("manifest.json"))
    except (KeyError, ValueError) as exc:
        raise InvalidInput(f"{path} has no valid manifest.json") from exc
    if manifest.get("format") != FORMAT:
        raise InvalidInput(f"{path} is not a LoopNet atlas snapshot")
    if manifest.get("format_version") != FORMAT_VERSION:
        raise InvalidInput(
            f"snapshot format version {manifest.get('format_version')} is not supported "
            f"(this LoopNet reads version {FORMAT_VERSION})"
        )
    if manifest.get("schema_revision") not in known_revisions():
        raise InvalidInput(
            f"the snapshot was written at schema revision {manifest.get('schema_revision')!r}, "
            "which this LoopNet does not know: restore it with a newer LoopNet"
        )
    checksums: dict[str, str] = manifest.get("checksums", {})
    if set(checksums) != set(members):
        raise InvalidInput("the snapshot's members do not match its manifest")
    for name, digest in checksums.items():
        if hashlib.sha256(members[name]).hexdigest() != digest:
            raise InvalidInput(f"the snapshot's {name} is corrupt (checksum mismatch)")
    return manifest, members


def _feature_rows(data: bytes, frame_id_map: dict[int, int]) -> list[FrameFeatureRow]:
    arrays = np.load(io.BytesIO(data))
    descriptor_dim, global_dim = int(arrays["descriptor_dim"]), int(arrays["global_dim"])
    offsets = np.concatenate([[0], np.cumsum(arrays["keypoint_counts"])])
    rows = []
    for i, old_id in enumerate(arrays["frame_ids"].tolist()):
        a, b = int(offsets[i]), int(offsets[i + 1])
        rows.append(
            FrameFeatureRow(
                frame_id=frame_id_map[old_id],
                descriptor_dim=descriptor_dim,
                global_dim=global_dim,
                keypoints=np.ascontiguousarray(arrays["keypoints"][a:b], "<f4").tobytes(),
                descriptors=np.ascontiguousarray(arrays["descriptors"][a:b], "<f2").tobytes(),
                scores=np.ascontiguousarray(arrays["scores"][a:b], "<f4").tobytes(),
                local_vector=np.ascontiguousarray(arrays["local_vectors"][i], "<f4").tobytes(),
                global_vector=np.ascontiguousarray(arrays["global_vectors"][i], "<f4").tobytes(),
            )
        )
    return rows


def _rekeyed_index(
    data: bytes, frame_id_map: dict[int, int], robot_of: dict[int, str]
) -> AtlasIndex | None:
    """The archived index under the new frame ids (None if its type cannot give vectors back:
    the service then rebuilds it from the stored features at load)."""
    try:
        source = AtlasIndex.from_bytes(data)
        old_ids, vectors = source.entries()
    except Exception as exc:
        log.warning("snapshot index not re-keyed (%s); it is rebuilt from features", exc)
        return None
    new_ids = np.array([frame_id_map[int(i)] for i in old_ids], np.int64)
    index = AtlasIndex(source.dim)
    index.add(new_ids, vectors, [robot_of[int(i)] for i in new_ids])
    return index


def restore_atlas(
    settings: Settings, sessions: sessionmaker[Session], path: Path, *, name: str | None = None
) -> str:
    """Restore the archive ``path`` as a new atlas (``name`` or the archived one's)."""
    manifest, members = read_archive(path)
    expected = preset_signature(settings.preset())
    if manifest["feature_signature"] != expected:
        raise Conflict(
            f"the snapshot holds features {manifest['feature_signature']}, but this deployment "
            f"extracts {expected}; restore it on a service running the snapshot's settings"
        )
    name = validate_name("atlas", name or manifest["atlas"])
    written: list[Path] = []
    try:
        with transaction(sessions) as session:
            atlas_row = json.loads(members["atlas.json"])
            atlas = repo.create_atlas(
                session,
                name=name,
                description=atlas_row.get("description", ""),
                feature_signature=manifest["feature_signature"],
            )
            submap_map: dict[int, int] = {}
            for row in _read_jsonl(members["submaps.jsonl"]):
                submap = Submap(atlas_id=atlas.id, **_values(Submap, row, ("id", "atlas_id")))
                session.add(submap)
                session.flush()
                submap_map[int(row["id"])] = submap.id
            frame_map: dict[int, int] = {}
            robot_of: dict[int, str] = {}
            for row in _read_jsonl(members["frames.jsonl"]):
                values = _values(Frame, row, ("id", "atlas_id", "submap_id"))
                frame = Frame(atlas_id=atlas.id, submap_id=submap_map[row["submap_id"]], **values)
                session.add(frame)
                session.flush()
                frame_map[int(row["id"])] = frame.id
                robot_of[frame.id] = frame.robot_id
            session.add_all(_feature_rows(members["features.npz"], frame_map))
            for row in _read_jsonl(members["model_versions.jsonl"]):
                weights_path = None
                if row["weights"] is not None:
                    target = models_store.weights_file(
                        settings.models_dir, atlas.id, int(row["version"])
                    )
                    target.parent.mkdir(parents=True, exist_ok=True)
                    target.write_bytes(members[row["weights"]])
                    written.append(target)
                    weights_path = str(target.relative_to(settings.models_dir))
                if row.get("calibration_file") is not None:
                    target = models_store.calibration_file(
                        settings.models_dir, atlas.id, int(row["version"])
                    )
                    target.parent.mkdir(parents=True, exist_ok=True)
                    target.write_bytes(members[row["calibration_file"]])
                    written.append(target)
                    row["config"]["calibration"]["path"] = str(
                        target.relative_to(settings.models_dir)
                    )
                session.add(
                    ModelVersion(
                        atlas_id=atlas.id,
                        weights_path=weights_path,
                        **_values(ModelVersion, row, ("id", "atlas_id", "weights_path")),
                    )
                )
            for row in _read_jsonl(members["loop_closures.jsonl"]):
                if row["frame_id"] not in frame_map:
                    continue
                session.add(
                    LoopClosure(
                        atlas_id=atlas.id,
                        **{
                            **_values(LoopClosure, row, ("id", "atlas_id")),
                            "frame_id": frame_map[row["frame_id"]],
                            "submap_id": submap_map[row["submap_id"]],
                        },
                    )
                )
            index = _rekeyed_index(members["index.faiss"], frame_map, robot_of)
            if index is not None:
                target = models_store.index_file(
                    settings.index_dir, atlas.id, int(manifest["active_model_version"])
                )
                index.save(target)
                written.append(target)
            session.flush()
    except Exception:
        for file in written:
            file.unlink(missing_ok=True)
        raise
    return name

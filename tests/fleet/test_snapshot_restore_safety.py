"""Restoring an archive never trusts it: sizes are bounded before anything is read, only the
format export writes is accepted, every row is validated before anything is written, a failed
restore leaves nothing behind, and each array is decompressed once."""

from __future__ import annotations

import hashlib
import io
import json
import tarfile
import tracemalloc
import zipfile
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from service.api.app import create_app
from service.fleet.snapshot_restore import restore_atlas
from service.storage import repository as repo
from tests.conftest import make_settings, wait_ready

MiB = 1024 * 1024


def members_of(archive: Path) -> dict[str, bytes]:
    with tarfile.open(archive) as source:
        return {m.name: source.extractfile(m).read() for m in source.getmembers()}  # type: ignore[union-attr]


def write_archive(members: dict[str, bytes], out: Path, *, checksums: bool = True) -> Path:
    """A tar of ``members``; the manifest's checksums recomputed so only the mutation counts."""
    members = dict(members)
    if checksums:
        manifest = json.loads(members["manifest.json"])
        manifest["checksums"] = {
            name: hashlib.sha256(data).hexdigest()
            for name, data in members.items()
            if name != "manifest.json"
        }
        members["manifest.json"] = json.dumps(manifest).encode()
    with tarfile.open(out, "w") as target:
        for name, data in members.items():
            info = tarfile.TarInfo(name)
            info.size = len(data)
            target.addfile(info, io.BytesIO(data))
    return out


def jsonl_edit(member: str, edit: Callable[[list[dict]], None]) -> Callable[[dict], None]:
    def mutate(members: dict[str, bytes]) -> None:
        rows = [json.loads(line) for line in members[member].decode().splitlines()]
        edit(rows)
        members[member] = "".join(json.dumps(r) + "\n" for r in rows).encode()

    return mutate


def npz_edit(edit: Callable[[dict[str, np.ndarray]], None]) -> Callable[[dict], None]:
    def mutate(members: dict[str, bytes]) -> None:
        with np.load(io.BytesIO(members["features.npz"])) as npz:
            arrays = {name: npz[name] for name in npz.files}
        edit(arrays)
        buffer = io.BytesIO()
        np.savez(buffer, **arrays)  # type: ignore[arg-type]
        members["features.npz"] = buffer.getvalue()

    return mutate


def _set(rows: list[dict], index: int, **values: object) -> None:
    rows[index].update(values)


def _no_weights_key(rows: list[dict]) -> None:
    for row in rows:
        del row["weights"]


def _huge_embed_dim(rows: list[dict]) -> None:
    rows[0]["config"]["heads"]["embed_dim"] = 150_000


def _heads_of_every_version(**values: int) -> Callable[[list[dict]], None]:
    """Heads configurations within the row bounds (4096) that do not fit the atlas's features
    (issue 24: each was a 500)."""

    def edit(rows: list[dict]) -> None:
        for row in rows:
            if row["weights"] is None:  # trained weights must match their row anyway
                row["config"]["heads"].update(values)

    return edit


def _none_active(rows: list[dict]) -> None:
    for row in rows:
        row["is_active"] = False


def _raw(member: str, data: bytes) -> Callable[[dict], None]:
    def mutate(members: dict[str, bytes]) -> None:
        members[member] = data

    return mutate


def _object_scores(arrays: dict[str, np.ndarray]) -> None:
    arrays["scores"] = np.array([{"x": 1}] * len(arrays["scores"]), dtype=object)


def _keypoints_3d(arrays: dict[str, np.ndarray]) -> None:
    arrays["keypoints"] = np.zeros((len(arrays["keypoints"]), 3), np.float32)


MALFORMED: dict[str, Callable[[dict], None]] = {
    "manifest is a list": _raw("manifest.json", b"[1, 2]"),
    "atlas.json is a string": _raw("atlas.json", b'"campus"'),
    "frame row is a list": _raw("frames.jsonl", b"[1, 2, 3]\n"),
    "frame robot id is a number": jsonl_edit("frames.jsonl", lambda r: _set(r, 0, robot_id=5)),
    "frame robot id is invalid": jsonl_edit(
        "frames.jsonl", lambda r: _set(r, 0, robot_id="robot a/../b")
    ),
    "frame width is text": jsonl_edit("frames.jsonl", lambda r: _set(r, 0, width="640")),
    "frame of an unknown submap": jsonl_edit("frames.jsonl", lambda r: _set(r, 0, submap_id=999)),
    "frame pose not a unit quaternion": jsonl_edit(
        "frames.jsonl", lambda r: _set(r, 0, qw=3.0, qx=0.0, qy=0.0, qz=0.0, tx=0.0, ty=0.0, tz=0.0)
    ),
    "submap name invalid": jsonl_edit("submaps.jsonl", lambda r: _set(r, 0, name="a b")),
    "model version without weights": jsonl_edit("model_versions.jsonl", _no_weights_key),
    "embed_dim beyond bounds": jsonl_edit("model_versions.jsonl", _huge_embed_dim),
    "embed_dim 4096 the features cannot fill": jsonl_edit(
        "model_versions.jsonl", _heads_of_every_version(embed_dim=4096)
    ),
    "hidden_dim 4096 with embed_dim 4096": jsonl_edit(
        "model_versions.jsonl", _heads_of_every_version(hidden_dim=4096, embed_dim=4096)
    ),
    "no active model version": jsonl_edit("model_versions.jsonl", _none_active),
    "loop closure of an unknown frame": jsonl_edit(
        "loop_closures.jsonl", lambda r: _set(r, 0, frame_id=987654)
    ),
    "object array in features.npz": npz_edit(_object_scores),
    "keypoints of shape N x 3": npz_edit(_keypoints_3d),
    "weights file is junk": _raw("models/v2.pt", b"not a torch file"),
    "index.faiss missing": lambda members: members.pop("index.faiss"),
}


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory, pipeline) -> Iterator[TestClient]:  # type: ignore[no-untyped-def]
    data_dir = tmp_path_factory.mktemp("restore-target")
    settings = make_settings(
        data_dir, snapshot_max_member_bytes=8 * MiB, snapshot_max_total_bytes=16 * MiB
    )
    with TestClient(create_app(settings, pipeline=pipeline)) as client:
        wait_ready(client)
        assert client.post("/v1/atlases", json={"name": "existing"}).status_code == 201
        yield client


def files_under(client: TestClient) -> list[str]:
    data_dir: Path = client.app.state.runtime.settings.data_dir  # type: ignore[attr-defined]
    return sorted(
        str(p.relative_to(data_dir))
        for folder in ("models", "indexes")
        for p in (data_dir / folder).rglob("*")
        if p.is_file()
    )


def restore(client: TestClient, archive: bytes, name: str = "copy"):  # type: ignore[no-untyped-def]
    return client.post(f"/v1/snapshots?name={name}", files={"archive": ("s.tar", archive)})


def assert_nothing_left(client: TestClient, files_before: list[str]) -> None:
    listing = client.get("/v1/atlases")
    assert listing.status_code == 200, listing.text
    assert [a["name"] for a in listing.json()] == ["existing"]
    assert files_under(client) == files_before
    service = client.app.state.runtime.service  # type: ignore[attr-defined]
    with service.sessions() as session:
        from service.storage.models import Atlas, Frame

        assert session.query(Atlas).count() == 1
        assert session.query(Frame).count() == 0


@pytest.mark.parametrize("case", sorted(MALFORMED))
def test_malformed_archives_answer_422_and_write_nothing(
    case: str, exported, server: TestClient, tmp_path: Path
) -> None:  # type: ignore[no-untyped-def]
    members = members_of(exported[0])
    MALFORMED[case](members)
    archive = write_archive(members, tmp_path / "bad.tar", checksums=case != "manifest is a list")
    before = files_under(server)
    answer = restore(server, archive.read_bytes())
    assert answer.status_code == 422, answer.text
    assert answer.json()["error"] == "InvalidInput"
    assert_nothing_left(server, before)


def test_the_unmodified_archive_restores(exported, server: TestClient, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    """The mutations above are refused for what they change, not for how they were rebuilt."""
    archive = write_archive(members_of(exported[0]), tmp_path / "same.tar")
    answer = restore(server, archive.read_bytes(), name="roundtrip")
    assert answer.status_code == 201, answer.text
    assert answer.json()["frames"] == 8
    assert server.delete("/v1/atlases/roundtrip").status_code == 204


def _tar_with(
    members: dict[str, bytes], extra: Callable[[tarfile.TarFile], None], out: Path
) -> bytes:
    write_archive(members, out)
    with tarfile.open(out, "a") as archive:
        extra(archive)
    return out.read_bytes()


def _add_file(name: str) -> Callable[[tarfile.TarFile], None]:
    def add(archive: tarfile.TarFile) -> None:
        info = tarfile.TarInfo(name)
        info.size = 2
        archive.addfile(info, io.BytesIO(b"{}"))

    return add


def _add_link(archive: tarfile.TarFile) -> None:
    info = tarfile.TarInfo("models/v7.pt")
    info.type = tarfile.SYMTYPE
    info.linkname = "/etc/passwd"
    archive.addfile(info)


def _add_folder(archive: tarfile.TarFile) -> None:
    info = tarfile.TarInfo("models")
    info.type = tarfile.DIRTYPE
    archive.addfile(info)


FOREIGN_MEMBERS = {
    "symlink": _add_link,
    "folder": _add_folder,
    "absolute path": _add_file("/tmp/loopnet-evil"),
    "parent path": _add_file("../evil.json"),
    "unknown member": _add_file("notes.txt"),
    "duplicate member": _add_file("atlas.json"),
}


@pytest.mark.parametrize("case", sorted(FOREIGN_MEMBERS))
def test_only_the_exported_format_is_accepted(
    case: str, exported, server: TestClient, tmp_path: Path
) -> None:  # type: ignore[no-untyped-def]
    data = _tar_with(members_of(exported[0]), FOREIGN_MEMBERS[case], tmp_path / "x.tar")
    before = files_under(server)
    answer = restore(server, data)
    assert answer.status_code == 422, answer.text
    assert_nothing_left(server, before)


def test_huge_member_is_refused_before_it_is_read(
    exported, server: TestClient, tmp_path: Path
) -> None:  # type: ignore[no-untyped-def]
    """A 64 MiB member of zeros compressed to a small .tar.gz: refused by its header's size,
    so the server's memory never grows by the member's size."""
    members = members_of(exported[0])
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w:gz", compresslevel=1) as archive:
        for name in ("manifest.json", "atlas.json"):
            info = tarfile.TarInfo(name)
            info.size = len(members[name])
            archive.addfile(info, io.BytesIO(members[name]))
        info = tarfile.TarInfo("features.npz")
        info.size = 64 * MiB
        archive.addfile(info, _Zeros(info.size))  # type: ignore[arg-type]
    data = buffer.getvalue()
    assert len(data) < MiB
    before = files_under(server)
    answer, peak = restore_traced(server, data)
    assert peak < 16 * MiB, f"restore allocated {peak / MiB:.0f} MiB"
    assert answer.status_code == 422, answer.text
    assert "LOOPNET_SNAPSHOT_MAX_MEMBER_BYTES" in answer.json()["detail"]
    assert_nothing_left(server, before)


def restore_traced(client: TestClient, archive: bytes):  # type: ignore[no-untyped-def]
    """The restore's answer, and the most bytes Python held meanwhile (tracemalloc)."""
    tracemalloc.start()
    try:
        answer = restore(client, archive)
        return answer, tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


class _Zeros:
    """A file-like stream of ``size`` zero bytes, never held whole."""

    def __init__(self, size: int) -> None:
        self.left = size

    def read(self, n: int = -1) -> bytes:
        n = self.left if n < 0 else min(n, self.left)
        self.left -= n
        return bytes(n)


def test_a_restore_failing_midway_leaves_nothing(
    exported, server: TestClient, monkeypatch: pytest.MonkeyPatch
) -> None:  # type: ignore[no-untyped-def]
    """Frames were written when the files fail: the atlas, its rows and its files go."""
    import service.fleet.snapshot_restore as snapshots

    def disk_full(*_args: object) -> None:
        raise OSError("no space left on device")

    monkeypatch.setattr(snapshots, "_write_files", disk_full)
    service = server.app.state.runtime.service  # type: ignore[attr-defined]
    before = files_under(server)
    with pytest.raises(OSError, match="no space left"):
        restore_atlas(service.settings, service.sessions, exported[0], name="copy")
    assert_nothing_left(server, before)
    with service.sessions() as session:
        assert [a.name for a in repo.list_atlases(session)] == ["existing"]


def test_restore_decompresses_each_array_once(
    exported, server: TestClient, monkeypatch: pytest.MonkeyPatch
) -> None:  # type: ignore[no-untyped-def]
    opened: list[tuple[int, str]] = []
    original = zipfile.ZipFile.open

    def counting_open(self: zipfile.ZipFile, name, *args, **kwargs):  # type: ignore[no-untyped-def]
        opened.append((id(self), name if isinstance(name, str) else name.filename))
        return original(self, name, *args, **kwargs)

    monkeypatch.setattr(zipfile.ZipFile, "open", counting_open)
    service = server.app.state.runtime.service  # type: ignore[attr-defined]
    restore_atlas(service.settings, service.sessions, exported[0], name="once")
    # each array of each npz member (features.npz has nine, thumbnails.npz three) read once
    assert len(opened) == len(set(opened)) == 12, opened
    service.delete_atlas("once")


def test_members_within_the_limits_are_streamed_to_disk(
    exported, server: TestClient, tmp_path: Path
) -> None:  # type: ignore[no-untyped-def]
    """Issue 24: members were read into memory, up to the limits (1 GiB each, 2 GiB in all): a
    408 KB .tar.gz of zeros raised the server by 794 MB before its 422. Members now go to disk
    through a bounded buffer: 14 MiB of members within this server's limits (8 MiB a member,
    16 MiB in all) cost the restore less than one of them."""
    members = members_of(exported[0])
    zeros = ("frames.jsonl", "features.npz")
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w:gz", compresslevel=1) as archive:
        for name in sorted(members.keys() - set(zeros)):
            info = tarfile.TarInfo(name)
            info.size = len(members[name])
            archive.addfile(info, io.BytesIO(members[name]))
        for name in zeros:
            info = tarfile.TarInfo(name)
            info.size = 7 * MiB
            archive.addfile(info, _Zeros(info.size))  # type: ignore[arg-type]
    data = buffer.getvalue()
    assert len(data) < 1024 * 1024
    before = files_under(server)
    answer, peak = restore_traced(server, data)
    assert answer.status_code == 422, answer.text
    assert "checksum" in answer.json()["detail"]
    assert peak < 4 * MiB, f"restore allocated {peak / MiB:.1f} MiB"
    assert_nothing_left(server, before)


def test_features_declaring_more_frames_than_the_manifest_are_refused_unread(
    exported, server: TestClient, tmp_path: Path
) -> None:  # type: ignore[no-untyped-def]
    """The arrays' declared shapes are checked against the manifest before any is inflated."""
    from tests.reliability.hostile import npy_declaring, replaced_member

    members = members_of(exported[0])
    members["features.npz"] = replaced_member(
        members["features.npz"], "frame_ids.npy", npy_declaring((10**9,), "<i8")
    )
    archive = write_archive(members, tmp_path / "bad.tar")
    before = files_under(server)
    answer = restore(server, archive.read_bytes())
    assert answer.status_code == 422, answer.text
    assert "holds 1000000000 frames, its manifest 8" in answer.json()["detail"]
    assert_nothing_left(server, before)

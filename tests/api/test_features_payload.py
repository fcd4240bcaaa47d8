"""Precomputed features: the same answers as posting the image; malformed payloads write nothing."""

from __future__ import annotations

import io
import json
import zipfile
from collections.abc import Callable

import numpy as np
import pytest
from fastapi.testclient import TestClient

from service.features_payload import encode_features
from service.ml.features import FrameFeatures
from service.ml.images import decode_image
from service.ml.presets import FeatureSignature
from tests.api.helpers import add_frame, create_atlas, stored_state
from tests.conftest import gardens_point_day_night
from tests.reliability.hostile import renamed_member, zip_tampering


def features_of(pipeline, image: bytes) -> FrameFeatures:  # type: ignore[no-untyped-def]
    """What a robot running the atlas's extractor on board computes."""
    return pipeline.extract(decode_image(image))


def post_frame(client: TestClient, payload: bytes, **fields: str):  # type: ignore[no-untyped-def]
    data = {"submap": "s0", "robot_id": "r1", **fields}
    return client.post(
        "/v1/atlases/campus/frames:features", data=data, files={"features": ("f.npz", payload)}
    )


def post_query(client: TestClient, payload: bytes, **fields: str):  # type: ignore[no-untyped-def]
    return client.post(
        "/v1/atlases/campus/query:features", data=fields, files={"features": ("f.npz", payload)}
    )


def test_features_give_the_same_answers_as_the_image(client: TestClient, pipeline) -> None:  # type: ignore[no-untyped-def]
    create_atlas(client)
    signature = pipeline.signature
    # Frames 0-2 as images, 3-5 as precomputed features.
    for i in range(3):
        add_frame(client, gardens_point_day_night(i, "ref"))
    for i in range(3, 6):
        payload = encode_features(
            features_of(pipeline, gardens_point_day_night(i, "ref")), signature
        )
        response = post_frame(client, payload, timestamp="12.5")
        assert response.status_code == 201, response.text
        frame = response.json()
        assert frame["keypoints"] > 0 and (frame["width"], frame["height"]) == (640, 360)
        assert frame["timestamp"] == 12.5

    for i in (1, 4, 7):
        image = gardens_point_day_night(i, "query")
        by_image = client.post(
            "/v1/atlases/campus/query", data={"k": "6"}, files={"image": ("q.jpg", image)}
        ).json()
        payload = encode_features(features_of(pipeline, image), signature)
        by_features = post_query(client, payload, k="6")
        assert by_features.status_code == 200, by_features.text
        body = by_features.json()
        assert [c["frame_id"] for c in body["candidates"]] == [
            c["frame_id"] for c in by_image["candidates"]
        ]
        np.testing.assert_allclose(
            [c["similarity"] for c in body["candidates"]],
            [c["similarity"] for c in by_image["candidates"]],
            atol=1e-5,
        )
        assert body["keypoints"] == by_image["keypoints"]
        assert "local_features" not in body["timings_ms"]  # no CNN ran on the server
        assert {"decode_features", "heads", "search", "total"} <= set(body["timings_ms"])


def _rewrite(payload: bytes, **changes: np.ndarray | None) -> bytes:
    """The payload with some arrays replaced (or dropped when None)."""
    arrays = dict(np.load(io.BytesIO(payload), allow_pickle=False))
    for name, value in changes.items():
        if value is None:
            arrays.pop(name)
        else:
            arrays[name] = value
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    return buffer.getvalue()


def _zip_bomb(payload: bytes) -> bytes:
    buffer = io.BytesIO()
    with (
        zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as archive,
        zipfile.ZipFile(io.BytesIO(payload)) as original,
    ):
        for info in original.infolist():
            if info.filename == "descriptors.npy":
                archive.writestr(info.filename, b"\0" * 50_000_000)
            else:
                archive.writestr(info.filename, original.read(info))
    return buffer.getvalue()


def _other_signature(signature: FeatureSignature) -> np.ndarray:
    other = signature.to_json()
    other["local"]["long_side"] = 1024
    return np.array(json.dumps(other))


MALFORMED: dict[str, tuple[Callable[[bytes, FeatureSignature, FrameFeatures], bytes], str]] = {
    "not a zip": (lambda p, s, f: b"hello", "not an .npz archive"),
    "missing array": (lambda p, s, f: _rewrite(p, scores=None), "must hold exactly"),
    "extra array": (lambda p, s, f: _rewrite(p, extra=np.zeros(3)), "must hold exactly"),
    "other extractor settings": (
        lambda p, s, f: _rewrite(p, signature=_other_signature(s)),
        "extracted with",
    ),
    "not a signature": (
        lambda p, s, f: _rewrite(p, signature=np.array(json.dumps({"local": {}}))),
        "not a feature signature",
    ),
    "descriptor width": (
        lambda p, s, f: _rewrite(p, descriptors=np.ones((f.local.count, 64), np.float32) / 8),
        "descriptors must be",
    ),
    "NaN descriptor": (
        lambda p, s, f: _rewrite(
            p, descriptors=np.where(np.arange(128) == 0, np.nan, f.local.descriptors)
        ),
        "NaN or infinite",
    ),
    "not unit": (
        lambda p, s, f: _rewrite(p, global_vector=f.global_vector * 2),
        "L2-normalised",
    ),
    "global width": (
        lambda p, s, f: _rewrite(p, global_vector=np.ones(512, np.float32) / np.sqrt(512)),
        "global_vector must have 2816",
    ),
    "scores count": (lambda p, s, f: _rewrite(p, scores=np.ones(3, np.float32)), "scores must"),
    "keypoint outside": (
        lambda p, s, f: _rewrite(p, keypoints=f.local.keypoints + 5000),
        "inside the",
    ),
    "integer keypoints": (
        lambda p, s, f: _rewrite(p, keypoints=f.local.keypoints.astype(np.int32)),
        "float16/32/64",
    ),
    "pickled object": (
        lambda p, s, f: _rewrite(p, scores=np.array([{"a": 1}], dtype=object)),
        "has type object",
    ),
    "keypoints with three columns": (
        lambda p, s, f: _rewrite(
            p, keypoints=np.concatenate([f.local.keypoints, f.local.keypoints[:, :1]], axis=1)
        ),
        "keypoints must be N x 2",
    ),
    "member without .npy": (lambda p, s, f: renamed_member(p, "scores.npy", "scores"), "exactly"),
    "image size": (lambda p, s, f: _rewrite(p, image_size=np.array([0, 10])), "image_size"),
    "zip bomb": (lambda p, s, f: _zip_bomb(p), "no valid header"),
    # issue 24: each was a 500 (a memory error, RuntimeError, NotImplementedError, zlib.error)
    "declared shape of 10^12": (
        lambda p, s, f: zip_tampering(p, "descriptors")["declares 10^12 values"],
        "declares shape (1000000000000,)",
    ),
    "encrypted member": (
        lambda p, s, f: zip_tampering(p, "keypoints")["encrypted member"],
        "is encrypted",
    ),
    "compression method 6": (
        lambda p, s, f: zip_tampering(p, "scores")["compression method 6"],
        "compression method 6",
    ),
    "corrupt deflate data": (
        lambda p, s, f: zip_tampering(p, "descriptors")["corrupt deflate"],
        "while decompressing data",
    ),
}


@pytest.fixture(scope="module")
def night_features(pipeline) -> FrameFeatures:  # type: ignore[no-untyped-def]
    return features_of(pipeline, gardens_point_day_night(2, "ref"))


@pytest.mark.parametrize("case", sorted(MALFORMED))
def test_malformed_payloads_are_refused_and_write_nothing(
    client: TestClient,
    pipeline,  # type: ignore[no-untyped-def]
    night_features: FrameFeatures,
    case: str,
) -> None:
    create_atlas(client)
    features = night_features
    good = encode_features(features, pipeline.signature)
    assert post_frame(client, good).status_code == 201  # the good payload is accepted
    make, message = MALFORMED[case]
    bad = make(good, pipeline.signature, features)
    before = stored_state(client)
    response = post_frame(client, bad)
    assert response.status_code == 422, response.text
    assert message in response.json()["detail"]
    query = post_query(client, bad)
    assert query.status_code == 422 and message in query.json()["detail"]
    assert stored_state(client) == before


def test_unknown_atlas_and_oversized_payload(client: TestClient, pipeline) -> None:  # type: ignore[no-untyped-def]
    payload = encode_features(
        features_of(pipeline, gardens_point_day_night(0, "ref")), pipeline.signature
    )
    assert post_query(client, payload).status_code == 404
    create_atlas(client)
    limit = client.app.state.runtime.service.settings.max_upload_bytes  # type: ignore[attr-defined]
    assert post_frame(client, payload + b"\0" * limit).status_code == 413


def test_hostile_archives_are_refused_in_bounded_memory(
    pipeline,  # type: ignore[no-untyped-def]
    night_features: FrameFeatures,
) -> None:
    """Every array of the payload, tampered every way: a 422 (InvalidInput), and the decoder's
    allocations stay far below the array's declared size (the payload itself is ~200 KB)."""
    import tracemalloc

    from service.errors import InvalidInput
    from service.features_payload import decode_features

    good = encode_features(night_features, pipeline.signature)
    for name in ("signature", "image_size", "keypoints", "descriptors", "scores", "global_vector"):
        for how, bad in zip_tampering(good, name).items():
            tracemalloc.start()
            try:
                with pytest.raises(InvalidInput):
                    decode_features(bad, pipeline.signature, max_image_pixels=10**7)
                peak = tracemalloc.get_traced_memory()[1]
            finally:
                tracemalloc.stop()
            assert peak < 8 * 1024 * 1024, (name, how, peak)

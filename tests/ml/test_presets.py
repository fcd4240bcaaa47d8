"""Named presets: the fast one runs XFeat and a small MobileNetV2 and serves end to end."""

from __future__ import annotations

import numpy as np
import pytest
from fastapi.testclient import TestClient

from service.ml.images import decode_image
from service.ml.pipeline import FeaturePipeline
from service.ml.presets import PRESETS, FeatureSignature, resolve_preset
from tests.conftest import gardens_point_day_night, make_settings, wait_ready


def test_presets_and_overrides() -> None:
    assert set(PRESETS) == {"default", "fast", "paper"}
    fast = resolve_preset("fast")
    assert (fast.local.name, fast.local.long_side, fast.backbone.input_size) == ("xfeat", 320, 160)
    assert resolve_preset("fast", long_side=256).local.long_side == 256
    with pytest.raises(ValueError, match="choose one of"):
        resolve_preset("quick")


def test_a_signature_round_trips_and_refuses_what_is_not_one() -> None:
    signature = PRESETS["fast"].signature
    assert FeatureSignature.from_json(signature.to_json()) == signature
    assert signature.dims == (64, 1280 + 96 * 16)  # GeM beside the 4 x 4 layout of 96 maps
    assert signature != PRESETS["default"].signature
    assert signature.matches(signature.to_json())
    assert not signature.matches(PRESETS["default"].signature.to_json())
    assert not signature.matches({})

    def edited(part: str, key: str, value: object) -> dict[str, object]:
        data = signature.to_json()
        data[part][key] = value
        return data

    for bad in (
        {},
        [],
        {**signature.to_json(), "extra": {}},
        edited("local", "max_keypoints", "512"),
        edited("local", "max_keypoints", 512.0),
        edited("local", "nms_window", True),
        edited("local", "name", "sift"),
        edited("backbone", "weights", "x"),
        edited("backbone", "pooling", "max"),
        {"local": signature.to_json()["local"], "backbone": None},
    ):
        with pytest.raises(ValueError):
            FeatureSignature.from_json(bad)


@pytest.fixture(scope="module")
def fast_pipeline() -> FeaturePipeline:
    return FeaturePipeline(resolve_preset("fast"))


def test_fast_preset_features(fast_pipeline: FeaturePipeline) -> None:
    rgb = decode_image(gardens_point_day_night(3, "query"))
    features = fast_pipeline.extract(rgb)
    assert 0 < features.local.count <= 512
    assert features.local.descriptors.shape[1] == 64
    assert features.global_vector.shape == (1280 + 96 * 16,)
    # unit length, up to the float16 rounding the feature store keeps it in
    assert abs(float(np.linalg.norm(features.global_vector)) - 1.0) < 1e-3
    assert np.array_equal(features.global_vector.astype(np.float16), features.global_vector)
    # keypoints come back in the decoded frame's pixels, not XFeat's 320-px working image
    assert features.local.keypoints[:, 0].max() > 320


def test_fast_preset_serves_a_revisit(tmp_path, fast_pipeline: FeaturePipeline) -> None:  # type: ignore[no-untyped-def]
    from service.api.app import create_app

    settings = make_settings(tmp_path, model_preset="fast", long_side=None, max_keypoints=None)
    with TestClient(create_app(settings, pipeline=fast_pipeline)) as client:
        wait_ready(client)
        assert client.post("/v1/atlases", json={"name": "a"}).status_code == 201
        assert client.post("/v1/atlases/a/submaps", json={"name": "s"}).status_code == 201
        ids = []
        for i in range(4):
            response = client.post(
                "/v1/atlases/a/frames",
                data={"submap": "s", "robot_id": "r"},
                files={"image": ("f.jpg", gardens_point_day_night(i, "query"))},
            )
            assert response.status_code == 201, response.text
            ids.append(response.json()["frame_id"])
        signature = client.get("/v1/atlases/a").json()["feature_signature"]
        assert signature["local"]["name"] == "xfeat"
        body = client.post(
            "/v1/atlases/a/query", files={"image": ("q.jpg", gardens_point_day_night(2, "query"))}
        ).json()
        assert body["match"]["frame_id"] == ids[2]
        assert body["match"]["similarity"] > 0.999

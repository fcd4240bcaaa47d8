"""The real pretrained networks: DISK through kornia and the global backbones."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from service.errors import WeightsUnavailable
from service.ml.backbones import BackboneConfig, build_backbone
from service.ml.backbones.resnet import ResNet18Trunk
from service.ml.images import decode_image
from service.ml.local_extractors import LocalExtractorConfig, build_local_extractor
from tests.conftest import gardens_point_day_night


@pytest.fixture(scope="module")
def disk():  # type: ignore[no-untyped-def]
    return build_local_extractor(LocalExtractorConfig(long_side=256, max_keypoints=300))


def test_disk_on_a_real_frame(disk) -> None:  # type: ignore[no-untyped-def]
    rgb = decode_image(gardens_point_day_night(0, "query"))  # 960 x 540
    found = disk.extract(rgb)
    assert 50 <= found.count <= 300
    assert np.allclose(np.linalg.norm(found.descriptors, axis=1), 1.0, atol=1e-4)
    # keypoints come back in the decoded image's pixels, not the 256 px working size
    assert found.keypoints[:, 0].max() > 300 and found.keypoints[:, 0].max() < 960
    assert found.keypoints[:, 1].max() < 540


def test_featureless_frame_is_valid_and_never_nan(disk, pipeline) -> None:  # type: ignore[no-untyped-def]
    blank = np.zeros((3, 500, 3), np.uint8)  # a black strip: DISK finds nothing at all
    assert disk.extract(blank).count == 0
    assert disk.extract(np.zeros((1, 1, 3), np.uint8)).count >= 0  # a 1-pixel frame works too
    features = pipeline.extract(blank)
    assert not np.isnan(features.local_vector).any()
    assert not np.isnan(features.global_vector).any()


@pytest.fixture(scope="module")
def xfeat():  # type: ignore[no-untyped-def]
    return build_local_extractor(
        LocalExtractorConfig(name="xfeat", long_side=256, max_keypoints=300)
    )


def test_xfeat_on_a_real_frame(xfeat) -> None:  # type: ignore[no-untyped-def]
    rgb = decode_image(gardens_point_day_night(0, "query"))  # 960 x 540
    found = xfeat.extract(rgb)
    assert xfeat.descriptor_dim == 64 and found.descriptors.shape == (found.count, 64)
    assert 50 <= found.count <= 300
    assert np.allclose(np.linalg.norm(found.descriptors, axis=1), 1.0, atol=1e-4)
    assert (np.diff(found.scores) <= 0).all()  # strongest first
    # keypoints come back in the decoded image's pixels, not the 256 px working size
    assert found.keypoints[:, 0].max() > 300 and found.keypoints[:, 0].max() < 960
    assert found.keypoints.min() > -0.5 and found.keypoints[:, 1].max() < 540


def test_xfeat_keypoints_do_not_depend_on_the_upload_size(xfeat) -> None:  # type: ignore[no-untyped-def]
    """The same frame uploaded at two sizes gives keypoints at the same scene points."""
    rgb = decode_image(gardens_point_day_night(2, "query"))  # 960 x 540
    half = rgb[::2, ::2].copy()  # 480 x 270: same working image after resizing to 256
    full, small = xfeat.extract(rgb), xfeat.extract(half)
    scaled = (small.keypoints + 0.5) * 2.0 - 0.5  # decoded pixels of the half-size upload
    nearest = np.linalg.norm(full.keypoints[:, None] - scaled[None], axis=-1).min(1)
    assert np.median(nearest) < 4.0  # pixels of the 960-wide frame (one working pixel is 3.75)


def test_xfeat_featureless_frame_gives_no_keypoints(xfeat) -> None:  # type: ignore[no-untyped-def]
    assert xfeat.extract(np.zeros((3, 500, 3), np.uint8)).count == 0
    assert xfeat.extract(np.zeros((1, 1, 3), np.uint8)).count == 0


def test_xfeat_rejects_another_nms_window() -> None:
    with pytest.raises(ValueError, match="fixed at 5"):
        build_local_extractor(LocalExtractorConfig(name="xfeat", nms_window=3))


def test_unknown_extractor_lists_choices() -> None:
    with pytest.raises(ValueError, match="choose one of"):
        build_local_extractor(LocalExtractorConfig(name="sift"))


def test_mobilenetv2_loads_the_imagenet_trunk_strictly() -> None:
    backbone = build_backbone(BackboneConfig(name="mobilenetv2"))
    vector = backbone.describe(decode_image(gardens_point_day_night(1, "query")))
    assert vector.shape == (1280,) and np.isclose(np.linalg.norm(vector), 1.0, atol=1e-5)


def test_mobilenetv2_same_place_is_closer_than_another_place() -> None:
    backbone = build_backbone(BackboneConfig(name="mobilenetv2"))
    day0 = backbone.describe(decode_image(gardens_point_day_night(0, "query")))
    day1 = backbone.describe(decode_image(gardens_point_day_night(1, "query")))
    uniform = backbone.describe(np.full((540, 960, 3), 90, np.uint8))
    assert day0 @ day1 > day0 @ uniform


def test_resnet18_has_torchvisions_layout() -> None:
    keys = set(ResNet18Trunk().state_dict())
    assert len(keys) == 120  # torchvision's resnet18 has 122 entries, 2 of them in fc
    assert {"conv1.weight", "bn1.running_var", "layer2.0.downsample.0.weight"} <= keys
    assert "layer4.1.bn2.num_batches_tracked" in keys


def test_resnet18_without_its_file_names_the_file(tmp_path, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    monkeypatch.setenv("TORCH_HOME", str(tmp_path))
    with pytest.raises(WeightsUnavailable) as raised:
        build_backbone(BackboneConfig(name="resnet18"))
    message = str(raised.value)
    assert "resnet18-f37072fd.pth" in message and str(tmp_path) in message


def test_resnet18_loads_a_torchvision_state_dict() -> None:
    source = ResNet18Trunk()
    state = dict(source.state_dict())
    state["fc.weight"], state["fc.bias"] = torch.zeros(1000, 512), torch.zeros(1000)
    ResNet18Trunk().load_torchvision_state_dict(state)

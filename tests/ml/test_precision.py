"""Accuracy guard of reduced-precision inference: bf16 against fp32 on real frames.

Reference: the networks as kornia and the weights files give them (fp32, NCHW, BatchNorm
unfolded). Candidate: the service's prepared path in bf16 (channels-last, folded, bf16 weights
with float32 normalisation statistics).
Descriptors keep cosine >= 0.99 with the reference: dense, at keypoints both find, aggregated
(D) and global (R); keypoints stay repeatable.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from service.ml import precision
from service.ml.backbones import BackboneConfig, build_backbone
from service.ml.backbones.registry import backbone_spec, pretrained_trunk
from service.ml.images import decode_image, resize_long_side, to_tensor
from service.ml.local_extractors import LocalExtractorConfig, build_local_extractor
from service.ml.pipeline import FeaturePipeline
from service.ml.precision import (
    Bf16InstanceNorm,
    FastInference,
    cpu_has_native_bf16,
    fold_batchnorm,
    optimise,
    resolve_precision,
)
from service.ml.presets import resolve_preset
from tests.conftest import gardens_point_day_night

needs_bf16 = pytest.mark.skipif(not cpu_has_native_bf16(), reason="CPU lacks native bf16")
FRAMES = [(1, "query"), (6, "ref")]  # a day and a night frame


def _frames() -> list[np.ndarray]:
    return [decode_image(gardens_point_day_night(i, side)) for i, side in FRAMES]


def _unwrapped(module: torch.nn.Module) -> torch.nn.Module:
    assert isinstance(module, FastInference)
    return module.inner


def _nearest(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For each row of ``a`` the index of, and distance to, the nearest row of ``b``."""
    distances = np.linalg.norm(a[:, None, :] - b[None, :, :], axis=-1)
    index = distances.argmin(1)
    return index, distances[np.arange(len(a)), index]


def test_resolve_precision() -> None:
    assert resolve_precision("fp32") == "fp32"
    assert resolve_precision("auto") == ("bf16" if cpu_has_native_bf16() else "fp32")
    with pytest.raises(ValueError, match="unknown precision"):
        resolve_precision("fp16")


def test_a_cpu_without_bf16_flags_falls_back_to_fp32(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    detect = cpu_has_native_bf16.__wrapped__  # type: ignore[attr-defined]
    cpuinfo = tmp_path / "cpuinfo"
    # a oneDNN that runs bf16 (as on any AVX-512 CPU, natively or not): the flags decide
    monkeypatch.setattr(precision, "_onednn_bf16_supported", lambda: True)
    cpuinfo.write_text("flags\t\t: fpu sse sse2 avx2 avx512f\n")
    assert not detect(cpuinfo)
    cpuinfo.write_text("flags\t\t: fpu sse avx512f avx512_bf16\n")
    assert detect(cpuinfo)
    cpuinfo.write_text("flags\t\t: fpu sse avx512f amx_bf16\n")
    assert detect(cpuinfo)
    # an AVX2-only CPU: oneDNN has no bf16 whatever the flags say
    monkeypatch.setattr(precision, "_onednn_bf16_supported", lambda: False)
    cpuinfo.write_text("flags\t\t: fpu sse avx512f avx512_bf16\n")
    assert not detect(cpuinfo)
    with pytest.raises(ValueError, match="no oneDNN bf16"):
        resolve_precision("bf16")


def test_bf16_instance_norm_rounds_the_float32_result_once() -> None:
    """Statistics in float32: each output is the float32 instance norm of the same bf16 input,
    rounded to bf16 (no bias from a bf16 mean); frames of a batch normalised apart; layout kept."""
    generator = torch.Generator().manual_seed(0)
    x = 20 + 0.5 * torch.randn(2, 16, 24, 40, generator=generator)
    x[1] = x[1] * 3 - 50  # another frame, other statistics
    x = x.to(torch.bfloat16).contiguous(memory_format=torch.channels_last)
    norm = torch.nn.InstanceNorm2d(16)
    with torch.inference_mode():
        got = Bf16InstanceNorm.replacing(norm)(x)
        want = norm(x.float())
        plain_bf16 = norm(x).float()  # torch's own: statistics rounded to bf16
    assert got.dtype == torch.bfloat16
    assert got.is_contiguous(memory_format=torch.channels_last)
    one_rounding = {"rtol": 2**-8, "atol": 2**-8}
    assert torch.allclose(got.float(), want, **one_rounding)
    assert not torch.allclose(plain_bf16, want, **one_rounding)
    with pytest.raises(ValueError, match="affine"):
        Bf16InstanceNorm.replacing(torch.nn.InstanceNorm2d(16, affine=True))


def test_disk_detect_equals_kornia_forward() -> None:
    """The extractor's own read of the U-Net output is kornia's DISK.forward (fp32, exactly)."""
    disk = build_local_extractor(LocalExtractorConfig(long_side=200, max_keypoints=300), "fp32")
    image = resize_long_side(to_tensor(_frames()[0]), 200)  # 200 x 112: padded to 208 x 112
    assert image.shape[-1] % 16 != 0
    with torch.inference_mode():
        want = disk.model(image, n=300, window_size=5, pad_if_not_divisible=True)[0]
        got = disk.detect(image)[0]
    assert torch.equal(got.keypoints, want.keypoints)
    assert torch.equal(got.scores, want.detection_scores)
    assert torch.allclose(got.descriptors, want.descriptors, atol=1e-6)


def test_disk_is_channels_last_in_bf16_only() -> None:
    # fp32 InstanceNorms copy a channels-last input to NCHW and back (0.80x of kornia at 512 px)
    def layout(precision: str) -> bool:
        net = torch.nn.Sequential(torch.nn.Conv2d(3, 8, 3), torch.nn.InstanceNorm2d(8))
        return bool(optimise(net, "disk", precision).channels_last)  # type: ignore[arg-type]

    assert layout("bf16") is True and layout("fp32") is False
    disk = build_local_extractor(LocalExtractorConfig(long_side=200, max_keypoints=300), "fp32")
    assert disk.model.unet.channels_last is False  # type: ignore[attr-defined]
    backbone = build_backbone(BackboneConfig("mobilenetv2", 160), precision="fp32")
    assert backbone.trunk.channels_last is True  # measured faster in fp32 too


def test_folding_batchnorm_keeps_the_backbone_output() -> None:
    backbone = build_backbone(BackboneConfig("mobilenetv2", 160), precision="fp32")
    trunk = _unwrapped(backbone.trunk)
    assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in trunk.modules())
    plain = pretrained_trunk(backbone_spec("mobilenetv2")).eval()
    assert any(isinstance(m, torch.nn.BatchNorm2d) for m in plain.modules())
    x = torch.rand(2, 3, 160, 160)
    with torch.inference_mode():
        assert torch.allclose(trunk(x), plain(x), atol=1e-4)
    assert fold_batchnorm(torch.nn.Identity()) is not None


@needs_bf16
@pytest.mark.parametrize("name, long_side", [("disk", 512), ("xfeat", 320)])
def test_bf16_local_features_match_fp32(name: str, long_side: int) -> None:
    config = LocalExtractorConfig(name=name, long_side=long_side, max_keypoints=1024)
    fast = build_local_extractor(config, "bf16")
    reference = build_local_extractor(config, "fp32")
    # the reference runs the network exactly as loaded: NCHW, fp32, no wrapper
    network = "unet" if name == "disk" else "net"
    plain = _unwrapped(getattr(reference.model, network)).to(memory_format=torch.contiguous_format)
    setattr(reference.model, network, plain)
    for rgb in _frames():
        if name == "disk":  # dense descriptors straight out of the U-Net
            image = resize_long_side(to_tensor(rgb), long_side)[..., :256, :496]
            with torch.inference_mode():
                dense_fp32 = plain(image)[:, :128]
                dense_bf16 = fast.model.unet(image)[:, :128].float()
            cosine = F.cosine_similarity(dense_fp32, dense_bf16, dim=1)
            assert cosine.mean() >= 0.99, cosine.mean()
        want, got = reference.extract(rgb), fast.extract(rgb)
        assert abs(got.count - want.count) <= 0.05 * want.count
        index, distance = _nearest(got.keypoints, want.keypoints)
        decoded_px_per_working_px = max(rgb.shape[:2]) / long_side
        repeated = distance <= decoded_px_per_working_px
        assert repeated.mean() >= 0.9, repeated.mean()
        matched = (got.descriptors[repeated] * want.descriptors[index[repeated]]).sum(1)
        assert matched.mean() >= 0.99, matched.mean()
        if name == "disk":
            from service.ml.aggregation import aggregate_descriptors

            d_fp32 = aggregate_descriptors(want.descriptors, want.scores)
            d_bf16 = aggregate_descriptors(got.descriptors, got.scores)
            assert float(d_fp32 @ d_bf16) >= 0.99


@needs_bf16
@pytest.mark.parametrize("name, size", [("mobilenetv2", 160), ("mobilenetv2", 224)])
def test_global_vectors_in_the_bf16_policy_match_fp32(name: str, size: int) -> None:
    """Whatever MODEL_POLICIES runs the backbone in when bf16 is asked for."""
    fast = build_backbone(BackboneConfig(name, size), precision="bf16")
    reference = build_backbone(BackboneConfig(name, size), precision="fp32")
    frames = _frames()
    want = reference.describe_batch(frames)
    got = fast.describe_batch(frames)
    assert ((want * got).sum(1) >= 0.99).all(), (want * got).sum(1)


def test_batched_extraction_equals_one_by_one() -> None:
    """Frames of two sizes in one batch: each gets what it gets alone (fp32: exact layout)."""
    pipeline = FeaturePipeline(resolve_preset("fast"), precision="fp32")
    frames = _frames()
    small = frames[0][::2, ::3].copy()  # another aspect ratio: its own group
    batch = [frames[0], small, frames[1]]
    together = pipeline.extract_batch(batch)
    for rgb, features in zip(batch, together, strict=True):
        alone = pipeline.extract(rgb)
        assert features.image_size == alone.image_size
        assert np.allclose(features.global_vector, alone.global_vector, atol=1e-4)
        assert float(features.local_vector @ alone.local_vector) >= 0.999
        assert abs(features.local.count - alone.local.count) <= 2


def test_bf16_re_embedding_keeps_embeddings_and_rankings() -> None:
    """Stored vectors re-embedded with bf16 matrix products: cosine >= 0.999 to fp32, and an
    exact search ranks the same nearest neighbours."""
    from service.ml.heads import HeadsConfig, LoopNetHeads
    from service.ml.pipeline import embed_vectors

    heads = LoopNetHeads(HeadsConfig(128, 1280, alpha=0.7)).eval()
    generator = torch.Generator().manual_seed(0)
    with torch.no_grad():  # away from the identity initialisation, like trained heads
        for parameter in heads.parameters():
            parameter.add_(0.05 * torch.randn(parameter.shape, generator=generator))
    rng = np.random.default_rng(0)
    places = rng.standard_normal((200, 128 + 1280)).astype(np.float32)
    stored = np.repeat(places, 5, axis=0) + 0.3 * rng.standard_normal((1000, 1408)).astype(
        np.float32
    )
    local, global_ = stored[:, :128].copy(), np.abs(stored[:, 128:])
    local /= np.linalg.norm(local, axis=1, keepdims=True)
    global_ /= np.linalg.norm(global_, axis=1, keepdims=True)
    fp32 = embed_vectors(heads, local, global_, "fp32")
    bf16 = embed_vectors(heads, local, global_, "bf16")
    assert bf16.dtype == np.float32
    assert np.allclose(np.linalg.norm(bf16, axis=1), 1.0, atol=1e-5)
    assert (fp32 * bf16).sum(1).min() >= 0.999
    queries = fp32[::5] + 0.01 * rng.standard_normal((200, fp32.shape[1])).astype(np.float32)
    top_fp32 = np.argsort(-(queries @ fp32.T), axis=1)[:, :5]
    top_bf16 = np.argsort(-(queries @ bf16.T), axis=1)[:, :5]
    assert (top_fp32[:, 0] == top_bf16[:, 0]).mean() >= 0.99

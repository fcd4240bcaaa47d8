"""Named model presets: which extractor, at what size, with which backbone.

``default`` is sized for a CPU (DISK at long side 512, several times cheaper than at 1024);
``paper`` uses the paper's settings (DISK at 1024, ResNet-18); ``fast`` is for CPU-only robots
and servers that must answer within tens of milliseconds (XFeat at long side 320, MobileNetV2
at 160 px). Timings come from ``benchmarks/stage_latency.py`` and
``benchmarks/http_latency.py``, accuracy from ``loopnet eval``; the figures are in
benchmarks/RESULTS.md.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from typing import Any

from service.ml.backbones import BackboneConfig
from service.ml.local_extractors import LocalExtractorConfig


@dataclass(frozen=True)
class ModelPreset:
    name: str
    local: LocalExtractorConfig
    backbone: BackboneConfig
    alpha: float = 0.7


PRESETS: dict[str, ModelPreset] = {
    "default": ModelPreset(
        "default",
        LocalExtractorConfig(name="disk", long_side=512, max_keypoints=1024, nms_window=5),
        BackboneConfig(name="mobilenetv2", input_size=224, pooling="gem"),
    ),
    "fast": ModelPreset(
        "fast",
        LocalExtractorConfig(name="xfeat", long_side=320, max_keypoints=512, nms_window=5),
        BackboneConfig(name="mobilenetv2", input_size=160, pooling="gem"),
    ),
    "paper": ModelPreset(
        "paper",
        LocalExtractorConfig(name="disk", long_side=1024, max_keypoints=2048, nms_window=5),
        BackboneConfig(name="resnet18", input_size=224, pooling="avg"),
    ),
}


def resolve_preset(
    name: str,
    *,
    extractor: str | None = None,
    backbone: str | None = None,
    long_side: int | None = None,
    max_keypoints: int | None = None,
    alpha: float | None = None,
) -> ModelPreset:
    """The preset ``name`` with any explicit overrides applied."""
    try:
        preset = PRESETS[name]
    except KeyError:
        raise ValueError(
            f"unknown model preset {name!r}; choose one of {sorted(PRESETS)}"
        ) from None
    local = preset.local
    if extractor is not None:
        local = replace(local, name=extractor)
    if long_side is not None:
        local = replace(local, long_side=long_side)
    if max_keypoints is not None:
        local = replace(local, max_keypoints=max_keypoints)
    model_backbone = replace(preset.backbone, name=backbone) if backbone else preset.backbone
    return replace(
        preset,
        local=local,
        backbone=model_backbone,
        alpha=preset.alpha if alpha is None else alpha,
    )


def preset_signature(preset: ModelPreset) -> dict[str, Any]:
    """What stored features mean (extractor and backbone settings); atlases record it."""
    return {"local": asdict(preset.local), "backbone": asdict(preset.backbone)}

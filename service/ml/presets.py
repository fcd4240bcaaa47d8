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
from typing import Any, get_type_hints

from service.ml.backbones import BackboneConfig
from service.ml.backbones.registry import BACKBONES, POOLINGS
from service.ml.heads import DEFAULT_ALPHA
from service.ml.local_extractors import LOCAL_EXTRACTORS, LocalExtractorConfig

NOT_A_SIGNATURE = "not a feature signature (exactly the 'local' and 'backbone' settings)"


@dataclass(frozen=True)
class FeatureSignature:
    """What stored features mean: the local extractor's and the backbone's settings.

    An atlas accepts only features of its own signature; two signatures are the same exactly
    when they compare equal. The atlas row, snapshots and features payloads hold it as JSON
    (:meth:`to_json`, :meth:`from_json`).
    """

    local: LocalExtractorConfig
    backbone: BackboneConfig

    @property
    def dims(self) -> tuple[int, int]:
        """(local descriptor dim, backbone vector dim) of features of this signature."""
        return LOCAL_EXTRACTORS[self.local.name].descriptor_dim, self.backbone.dim

    def to_json(self) -> dict[str, Any]:
        return {"local": asdict(self.local), "backbone": asdict(self.backbone)}

    @classmethod
    def from_json(cls, data: object) -> FeatureSignature:
        """The signature ``data`` holds; ValueError unless it is exactly one (every key, no
        other, each value of its type, known extractor and backbone names)."""
        if not isinstance(data, dict):
            raise ValueError(NOT_A_SIGNATURE)
        try:
            signature = cls(
                LocalExtractorConfig(**data["local"]), BackboneConfig(**data["backbone"])
            )
        except (KeyError, TypeError) as exc:
            raise ValueError(NOT_A_SIGNATURE) from exc
        kinds = {
            "local": get_type_hints(LocalExtractorConfig),
            "backbone": get_type_hints(BackboneConfig),
        }
        if signature.to_json() != data or any(
            type(value) is not kinds[part][key]
            for part, settings in signature.to_json().items()
            for key, value in settings.items()
        ):
            raise ValueError(NOT_A_SIGNATURE)
        if signature.local.name not in LOCAL_EXTRACTORS or signature.backbone.name not in BACKBONES:
            raise ValueError(f"unknown extractor or backbone in {signature}")
        if signature.backbone.pooling not in POOLINGS:
            raise ValueError(f"unknown pooling in {signature}")
        return signature

    def matches(self, stored: object) -> bool:
        """Whether JSON read from a row or an archive is this signature."""
        try:
            return FeatureSignature.from_json(stored) == self
        except ValueError:
            return False


@dataclass(frozen=True)
class ModelPreset:
    name: str
    local: LocalExtractorConfig
    backbone: BackboneConfig
    alpha: float = DEFAULT_ALPHA

    @property
    def signature(self) -> FeatureSignature:
        """What features extracted with this preset mean; atlases record it."""
        return FeatureSignature(self.local, self.backbone)


PRESETS: dict[str, ModelPreset] = {
    "default": ModelPreset(
        "default",
        LocalExtractorConfig(name="disk", long_side=512, max_keypoints=1024, nms_window=5),
        BackboneConfig(name="mobilenetv2", input_size=224, pooling="gem-layout"),
    ),
    "fast": ModelPreset(
        "fast",
        LocalExtractorConfig(name="xfeat", long_side=320, max_keypoints=512, nms_window=5),
        BackboneConfig(name="mobilenetv2", input_size=160, pooling="gem-layout"),
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

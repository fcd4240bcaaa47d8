"""Global CNN backbones, chosen by name from a registry (see :mod:`.registry`)."""

from service.ml.backbones.registry import (
    BACKBONES,
    BackboneConfig,
    GlobalBackbone,
    build_backbone,
)

__all__ = ["BACKBONES", "BackboneConfig", "GlobalBackbone", "build_backbone"]

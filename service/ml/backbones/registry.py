"""Global backbones by name: a CNN trunk, its weights file and a pooling into one vector (R)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from service.ml import weights
from service.ml.backbones.mobilenet import MobileNetV2Trunk
from service.ml.backbones.resnet import ResNet18Trunk
from service.ml.images import resize_exact, to_tensor
from service.ml.precision import Precision, optimise

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


@dataclass(frozen=True)
class BackboneConfig:
    """How the global branch runs.

    Attributes:
        name: registry key ("resnet18", "mobilenetv2").
        input_size: square side the frame is resized to (the paper's 224).
        pooling: "gem" (generalised mean, p=3; better for retrieval) or "avg".
    """

    name: str = "mobilenetv2"
    input_size: int = 224
    pooling: str = "gem"


@dataclass(frozen=True)
class BackboneSpec:
    """A registry entry: how to build the trunk, how to load its weights file, its width."""

    make_trunk: Callable[[], nn.Module]
    load_weights: Callable[[Any, dict[str, torch.Tensor]], None]
    dim: int
    weights: weights.WeightsFile


BACKBONES: dict[str, BackboneSpec] = {
    "resnet18": BackboneSpec(
        ResNet18Trunk,
        lambda trunk, state: trunk.load_torchvision_state_dict(state),
        ResNet18Trunk.out_channels,
        weights.RESNET18_IMAGENET,
    ),
    "mobilenetv2": BackboneSpec(
        MobileNetV2Trunk,
        lambda trunk, state: trunk.load_state_dict(state, strict=True),
        MobileNetV2Trunk.out_channels,
        weights.MOBILENETV2_TRUNK,
    ),
}


def pretrained_trunk(spec: BackboneSpec) -> nn.Module:
    trunk = spec.make_trunk()
    spec.load_weights(trunk, weights.load_checkpoint(spec.weights))
    return trunk


def gem(feature_map: torch.Tensor, p: float = 3.0, eps: float = 1e-6) -> torch.Tensor:
    """Generalised-mean pooling ``B x C x H x W`` -> ``B x C`` (Radenović et al.)."""
    return feature_map.clamp(min=eps).pow(p).mean(dim=(-2, -1)).pow(1.0 / p)


class GlobalBackbone:
    """An ImageNet CNN trunk with pooling: RGB frame -> L2-normalised ``dim`` vector."""

    def __init__(
        self, config: BackboneConfig, trunk: nn.Module | None = None, precision: Precision = "fp32"
    ) -> None:
        """``trunk`` replaces the pretrained one (benchmarks time a random-init trunk)."""
        spec = backbone_spec(config.name)
        if config.pooling not in ("gem", "avg"):
            raise ValueError(f"unknown pooling {config.pooling!r}; choose 'gem' or 'avg'")
        self.config = config
        self.dim = spec.dim
        raw = trunk if trunk is not None else pretrained_trunk(spec)
        self.trunk = optimise(raw, config.name, precision)
        self._mean = torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1)
        self._std = torch.tensor(IMAGENET_STD).view(1, 3, 1, 1)

    def describe(self, rgb: np.ndarray) -> np.ndarray:
        vector: np.ndarray = self.describe_batch([rgb])[0]
        return vector

    @torch.inference_mode()
    def describe_batch(self, rgbs: list[np.ndarray]) -> np.ndarray:
        """``len(rgbs) x dim`` float32 unit vectors; every frame is resized to the input size,
        so the whole list runs as one batch."""
        size = self.config.input_size
        image = torch.cat([resize_exact(to_tensor(rgb), size, size) for rgb in rgbs])
        feature_map = self.trunk((image - self._mean) / self._std)
        pooled = gem(feature_map) if self.config.pooling == "gem" else feature_map.mean((-2, -1))
        return F.normalize(pooled, dim=-1).numpy().astype(np.float32)


def backbone_spec(name: str) -> BackboneSpec:
    try:
        return BACKBONES[name]
    except KeyError:
        raise ValueError(f"unknown backbone {name!r}; choose one of {sorted(BACKBONES)}") from None


def build_backbone(config: BackboneConfig, precision: Precision = "fp32") -> GlobalBackbone:
    """Instantiate the backbone ``config.name`` with its pretrained ImageNet weights."""
    return GlobalBackbone(config, precision=precision)

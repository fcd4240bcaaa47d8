"""Global backbones by name: a CNN trunk, its weights file and a pooling into one vector (R).

Poolings:

- ``gem``: generalised-mean pooling of the last feature map (what the vector means in the
  retrieval literature; robust to viewpoint, blind to where things are in the frame).
- ``avg``: plain average of the last map (the paper's ResNet output).
- ``gem-layout``: the GeM vector beside a coarse *layout* of a mid-level map (the last map at
  stride 16, averaged over a 4 x 4 grid of cells), each half L2-normalised and the whole
  scaled to unit norm. Mid-level maps with their spatial arrangement survive appearance
  change (season, weather) far better than the last map's semantics (Sünderhauf et al., "On
  the performance of ConvNet features for place recognition", IROS 2015); measured on
  nordland_64x32 in benchmarks/RESULTS.md ("Figures behind choices in the code").
  The atlas's calibration then whitens the whole vector and keeps the directions the atlas
  varies in.
"""

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
        pooling: "gem" (generalised mean, p=3; better for retrieval), "avg", or
            "gem-layout" (GeM beside a 4 x 4 layout of the stride-16 map; module doc).
    """

    name: str = "mobilenetv2"
    input_size: int = 224
    pooling: str = "gem"

    @property
    def dim(self) -> int:
        """Length of the vector R this configuration produces."""
        spec = backbone_spec(self.name)
        if self.pooling == "gem-layout":
            return spec.dim + spec.layout_channels * LAYOUT_GRID**2
        return spec.dim


POOLINGS = ("gem", "avg", "gem-layout")
LAYOUT_GRID = 4  # cells per side of the layout (4 x 4: coarse enough for small shifts)


@dataclass(frozen=True)
class BackboneSpec:
    """A registry entry: how to build the trunk, how to load its weights file, its width, and
    where its stride-16 map is (``split``: the trunk as the stages before and after it)."""

    make_trunk: Callable[[], nn.Module]
    load_weights: Callable[[Any, dict[str, torch.Tensor]], None]
    dim: int
    weights: weights.WeightsFile
    split: Callable[[Any], tuple[nn.Module, nn.Module]]
    layout_channels: int


class TappedTrunk(nn.Module):
    """A trunk as two stages: ``x -> (last map, stride-16 map)`` in one traceable forward."""

    def __init__(self, stages: tuple[nn.Module, nn.Module]) -> None:
        super().__init__()
        self.stem, self.head = stages

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        middle = self.stem(x)
        return self.head(middle), middle


def _split_resnet(trunk: ResNet18Trunk) -> tuple[nn.Module, nn.Module]:
    stem = nn.Sequential(
        trunk.conv1, trunk.bn1, trunk.relu, trunk.maxpool, trunk.layer1, trunk.layer2, trunk.layer3
    )
    return stem, trunk.layer4


def _split_mobilenet(trunk: MobileNetV2Trunk) -> tuple[nn.Module, nn.Module]:
    end = MobileNetV2Trunk.stride16_end
    return trunk.features[:end], trunk.features[end:]


BACKBONES: dict[str, BackboneSpec] = {
    "resnet18": BackboneSpec(
        ResNet18Trunk,
        lambda trunk, state: trunk.load_torchvision_state_dict(state),
        ResNet18Trunk.out_channels,
        weights.RESNET18_IMAGENET,
        _split_resnet,
        256,
    ),
    "mobilenetv2": BackboneSpec(
        MobileNetV2Trunk,
        lambda trunk, state: trunk.load_state_dict(state, strict=True),
        MobileNetV2Trunk.out_channels,
        weights.MOBILENETV2_TRUNK,
        _split_mobilenet,
        96,
    ),
}


def pretrained_trunk(spec: BackboneSpec) -> nn.Module:
    trunk = spec.make_trunk()
    spec.load_weights(trunk, weights.load_checkpoint(spec.weights))
    return trunk


def gem(feature_map: torch.Tensor, p: float = 3.0, eps: float = 1e-6) -> torch.Tensor:
    """Generalised-mean pooling ``B x C x H x W`` -> ``B x C`` (Radenović et al.)."""
    return feature_map.clamp(min=eps).pow(p).mean(dim=(-2, -1)).pow(1.0 / p)


def layout(feature_map: torch.Tensor, grid: int = LAYOUT_GRID) -> torch.Tensor:
    """``B x C x H x W`` -> ``B x (C * grid * grid)``: the map averaged over a grid of cells."""
    return F.adaptive_avg_pool2d(feature_map, grid).flatten(1)


class GlobalBackbone:
    """An ImageNet CNN trunk with pooling: RGB frame -> L2-normalised ``dim`` vector."""

    def __init__(
        self, config: BackboneConfig, trunk: nn.Module | None = None, precision: Precision = "fp32"
    ) -> None:
        """``trunk`` replaces the pretrained one (benchmarks time a random-init trunk)."""
        spec = backbone_spec(config.name)
        if config.pooling not in POOLINGS:
            raise ValueError(
                f"unknown pooling {config.pooling!r}; choose one of {', '.join(POOLINGS)}"
            )
        self.config = config
        self.dim = config.dim
        raw = trunk if trunk is not None else pretrained_trunk(spec)
        if config.pooling == "gem-layout":
            raw = TappedTrunk(spec.split(raw))
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
        output = self.trunk((image - self._mean) / self._std)
        if self.config.pooling == "gem-layout":
            last, middle = output
            halves = (F.normalize(gem(last), dim=-1), F.normalize(layout(middle), dim=-1))
            pooled = torch.cat(halves, dim=-1)
        else:
            pooled = gem(output) if self.config.pooling == "gem" else output.mean((-2, -1))
        return F.normalize(pooled, dim=-1).numpy().astype(np.float32)


def backbone_spec(name: str) -> BackboneSpec:
    try:
        return BACKBONES[name]
    except KeyError:
        raise ValueError(f"unknown backbone {name!r}; choose one of {sorted(BACKBONES)}") from None


def build_backbone(config: BackboneConfig, precision: Precision = "fp32") -> GlobalBackbone:
    """Instantiate the backbone ``config.name`` with its pretrained ImageNet weights."""
    return GlobalBackbone(config, precision=precision)
